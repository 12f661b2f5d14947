"""Typed lengths: units in the value, a bare number in millimetres, warnings for implausible targets."""

import math

import pytest

from tofcore.units import implausible_error_warning, parse_length_m


@pytest.mark.parametrize("text, metres", [("5mm", 0.005), ("5 mm", 0.005), ("0.5cm", 0.005), ("0.005m", 0.005),
                                          ("5", 0.005), ("5MM", 0.005), ("2.5e-3m", 0.0025), (".5", 0.0005)])
def test_lengths_with_and_without_units(text, metres):
    assert math.isclose(parse_length_m(text), metres, rel_tol=1e-12)


@pytest.mark.parametrize("text", ["", "mm", "5 furlongs", "5km", "inf", "nan", "5mm m", "1,5mm"])
def test_bad_lengths_name_the_text_and_the_forms(text):
    with pytest.raises(ValueError, match=r"must be a length such as 5mm, 0\.5cm or 0\.005m \(a bare number is "
                                         r"in mm\), got " + repr(text).replace("(", r"\(").replace(".", r"\.")):
        parse_length_m(text)


def test_implausible_targets_warn_and_plausible_ones_do_not():
    # 0.005 typed bare is 5 micrometres: the hint says how to write 5 mm... in metres
    warning = implausible_error_warning(parse_length_m("0.005"), "--target-error")
    assert warning == ("warning: --target-error 0.005 mm is implausible for a depth error (a bare number is in mm: "
                       "for 0.005 m write 0.005m)")
    assert "would stop at its first estimate" in implausible_error_warning(2.0, "--target-error")
    for metres in (1e-5, 0.001, 0.05, 1.0):
        assert implausible_error_warning(metres, "--target-error") is None
