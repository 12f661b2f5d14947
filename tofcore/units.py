"""Lengths as people type them: ``"5mm"``, ``"0.5 cm"``, ``"0.005m"``, or a bare number in millimetres.

One unit everywhere a person types a depth error: the command lines' ``--target-error`` and the
Blender add-on's *Target Error* field both read a bare number as millimetres; a value may carry its
own unit instead. Files (set files, presets, ``frame.json``) keep SI units named in their keys
(``target_error_m``).

=========  ===========
suffix     metres
=========  ===========
``mm``     0.001
``cm``     0.01
``m``      1
(none)     0.001 (mm)
=========  ===========
"""

from __future__ import annotations

import math
import re

#: Metres per unit of the suffixes a typed length may carry.
LENGTH_UNITS_M = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}

#: The unit of a bare number.
BARE_LENGTH_UNIT = "mm"

#: A depth-error target outside this range (metres) is accepted with a warning: below 10 µm no ToF
#: camera (nor a render of reasonable length) gets there, above 1 m the target stops nothing.
PLAUSIBLE_ERROR_M = (1e-5, 1.0)

_LENGTH = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-zA-Z]*)\s*$")


def parse_length_m(text: str) -> float:
    """Metres of a typed length: a number with an optional unit (mm, cm, m); a bare number is millimetres.

    Raises ValueError naming the text and the accepted forms.
    """
    match = _LENGTH.match(text)
    unit = match.group(2).lower() if match else ""
    if match is None or (unit and unit not in LENGTH_UNITS_M):
        raise ValueError(f"must be a length such as 5mm, 0.5cm or 0.005m (a bare number is in "
                         f"{BARE_LENGTH_UNIT}), got {text!r}")
    return float(match.group(1)) * LENGTH_UNITS_M[unit or BARE_LENGTH_UNIT]


def implausible_error_warning(error_m: float, flag: str) -> str | None:
    """A one-line warning when a depth-error target is outside :data:`PLAUSIBLE_ERROR_M`, else None."""
    lo, hi = PLAUSIBLE_ERROR_M
    if lo <= error_m <= hi or not math.isfinite(error_m):
        return None
    mm = error_m * 1000
    hint = (f"a bare number is in {BARE_LENGTH_UNIT}: for {mm:g} m write {mm:g}m" if error_m < lo
            else "the render would stop at its first estimate")
    return f"warning: {flag} {mm:g} mm is implausible for a depth error ({hint})"
