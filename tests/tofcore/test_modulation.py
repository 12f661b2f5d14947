"""Tests of tofcore.sensor.modulation: validation, raw-image bookkeeping and the correlation functions g_j(τ)."""

import pickle

import numpy as np
import pytest

from tofcore.errors import ConfigError
from tofcore.sensor.modulation import Modulation, ideal_raw, pulsed_correlation, sine_correlation, square_correlation
from tofcore.constants import SPEED_OF_LIGHT_M_S

KINECT = dict(frequencies_hz=(80e6, 16e6, 120e6), phase_steps=(3, 3, 3), exposure_s=(8e-3, 4e-3, 8e-3))


# ------------------------------------------------------------------ validation
@pytest.mark.parametrize("kwargs, pattern", [
    (dict(kind="cw_triangle", frequencies_hz=(20e6,)),
     r"kind must be one of \['pulsed', 'cw_square', 'cw_sine'\], got 'cw_triangle'"),
    (dict(kind="cw_sine", frequencies_hz=(20e6, -30e6)), r"frequencies_hz must be .*> 0, got \(20000000.0, -30000000.0\)"),
    (dict(kind="cw_sine", frequencies_hz=(float("nan"),)), r"frequencies_hz must be finite"),
    (dict(kind="cw_sine"), r"frequencies_hz must be at least one frequency"),
    (dict(kind="cw_square", frequencies_hz=(20e6,), phase_steps=(2,)), r"phase_steps must be .*>= 3, got \(2,\)"),
    (dict(kind="cw_square", frequencies_hz=(20e6,), phase_steps=4), r"phase_steps must be a sequence"),
    (dict(kind="cw_square", frequencies_hz=(20e6, 30e6), phase_steps=(4,)),
     r"phase_steps must have one value per frequency \(2\) or be empty, got \(4,\)"),
    (dict(kind="cw_square", frequencies_hz=(20e6,), exposure_s=(1e-3, 2e-3)),
     r"exposure_s must have one value per frequency \(1\)"),
    (dict(kind="cw_square", frequencies_hz=(20e6,), exposure_s=(-1e-3,)), r"exposure_s must be .*> 0"),
    (dict(kind="cw_square", frequencies_hz=(20e6,), duty_cycle=1.0), r"duty_cycle must be in \(0, 1\).*got 1.0"),
    (dict(kind="cw_sine", frequencies_hz=(20e6,), duty_cycle=0.3), r"duty_cycle must be 0.5 \(unused\)"),
    (dict(kind="cw_sine", frequencies_hz=(20e6,), pulse_width_s=1e-8), r"pulse_width_s must be None"),
    (dict(kind="pulsed"), r"pulse_width_s must be a finite number > 0 .*got None"),
    (dict(kind="pulsed", pulse_width_s=-1e-9), r"pulse_width_s must be .*got -1e-09"),
    (dict(kind="pulsed", pulse_width_s=5e-8, frequencies_hz=(20e6,)), r"frequencies_hz and phase_steps must be empty"),
    (dict(kind="pulsed", pulse_width_s=5e-8, duty_cycle=0.6), r"duty_cycle must be in \(0, 0.5\]"),
    (dict(kind="pulsed", pulse_width_s=5e-8, exposure_s=(1e-3, 1e-3)), r"exposure_s must be one value"),
])
def test_invalid_modulation_names_field_and_value(kwargs, pattern):
    with pytest.raises(ConfigError, match="Modulation: " + pattern):
        Modulation(**kwargs)


def test_defaults_and_normalised_fields():
    m = Modulation(kind="cw_square", frequencies_hz=[20e6, np.float32(30e6)])
    assert m.frequencies_hz == (20e6, 30e6) and m.phase_steps == (4, 4) and m.exposure_s == (1e-3, 1e-3)
    assert all(type(f) is float for f in m.frequencies_hz)
    assert Modulation(kind="pulsed", pulse_width_s=5e-8).exposure_s == (1e-3,)


def test_raw_bookkeeping_kinect():
    m = Modulation(kind="cw_square", **KINECT)
    assert m.raw_count == 9 and len(m.correlations()) == 9
    assert m.raw_labels()[:4] == ("f80MHz_s0", "f80MHz_s1", "f80MHz_s2", "f16MHz_s0")
    np.testing.assert_allclose(m.raw_exposure_s(), np.repeat([8e-3, 4e-3, 8e-3], 3) / 3)
    np.testing.assert_allclose(m.gate_duty(), 0.5)
    np.testing.assert_allclose(m.ambiguity_distances_m(), SPEED_OF_LIGHT_M_S / (2 * np.array([80e6, 16e6, 120e6])))
    # beat frequency 8 MHz (thesis §2.2.2: 18.73 m)
    assert m.unambiguous_range_m() == pytest.approx(SPEED_OF_LIGHT_M_S / 16e6) and round(m.unambiguous_range_m(), 3) == 18.737


def test_raw_bookkeeping_pulsed():
    m = Modulation(kind="pulsed", pulse_width_s=50e-9, duty_cycle=0.1, exposure_s=(2e-3,))
    assert m.raw_labels() == ("pulsed_C1", "pulsed_C2")
    np.testing.assert_allclose(m.gate_duty(), [0.1, 0.1])
    np.testing.assert_allclose(m.raw_exposure_s(), [2e-3, 2e-3])
    assert m.unambiguous_range_m() == pytest.approx(SPEED_OF_LIGHT_M_S * 50e-9 / 2)  # eq. 2.37: 7.49 m


def test_correlations_pickle_and_keep_shape():
    m = Modulation(kind="cw_sine", frequencies_hz=(20e6,))
    g = pickle.loads(pickle.dumps(m.correlations()))
    tau = np.zeros((3, 5))
    assert g[0](tau).shape == (3, 5) and g[0](tau).dtype == np.float64


@pytest.mark.parametrize("modulation", [
    Modulation(kind="cw_square", frequencies_hz=(80e6, 16e6, 120e6), phase_steps=(3, 3, 3)),
    Modulation(kind="cw_square", frequencies_hz=(30e6, 20e6), phase_steps=(5, 3), duty_cycle=0.8),
    Modulation(kind="cw_square", frequencies_hz=(30e6,), phase_steps=(4,), duty_cycle=0.3),
    Modulation(kind="cw_sine", frequencies_hz=(80e6, 16e6), phase_steps=(4, 3)),
    Modulation(kind="pulsed", pulse_width_s=50e-9, duty_cycle=0.2),
], ids=["kinect", "square_d08", "square_d03", "sine", "pulsed"])
def test_correlation_bank_equals_the_functions_bit_for_bit(modulation):
    """The bank evaluates each frequency's steps as one block in place: the same values as the list of
    g_j, over delays from 0 to 20 unambiguous ranges (wraps, negative phases, both pulse edges)."""
    tau = np.random.default_rng(3).uniform(-5e-9, 20 * 2 * 18.8 / SPEED_OF_LIGHT_M_S, 10_001)
    bank = modulation.correlation_bank()
    expected = np.stack([g(tau) for g in modulation.correlations()])
    assert len(bank) == modulation.raw_count == len(expected)
    np.testing.assert_array_equal(bank(tau), expected)
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(bank))(tau[:5]), expected[:, :5])
    grid = tau[:21].reshape(3, 7)  # delays of any shape, as the functions take them
    np.testing.assert_array_equal(bank(grid), np.stack([g(grid) for g in modulation.correlations()]))


# ------------------------------------------------------------------ correlation against brute-force integration
def _brute_force(tau_s, period_s, emitted, gate):
    """(1/T) ∫ m(t − τ) G(t) dt on a fine midpoint grid over one period (error ~ 1/steps)."""
    t = (np.arange(200_000) + 0.5) / 200_000 * period_s
    return np.array([np.mean(emitted(t - tau) * gate(t)) for tau in tau_s])


@pytest.mark.parametrize("duty", [0.5, 0.2, 0.75])
@pytest.mark.parametrize("offset", [0.0, 1 / 3, 0.75])
def test_square_correlation_is_the_periodic_overlap(duty, offset):
    f = 20e6
    period = 1 / f
    tau = np.linspace(-1.5, 2.5, 41) * period  # several periods: the correlation is periodic in τ

    def emitted(t):  # on while the square wave of sin(2πft) phase is on, pulse centred on a quarter period
        return (np.mod(f * t - 0.25 + duty / 2, 1.0) < duty) / duty

    def gate(t):
        return np.mod(f * t - offset, 1.0) < 0.5

    # grid error: one of 2e5 samples flips per edge → 2 · 1/(2e5 · duty) ≤ 5e-5
    np.testing.assert_allclose(square_correlation(tau, f, offset, duty), _brute_force(tau, period, emitted, gate),
                               atol=1e-4)


@pytest.mark.parametrize("offset", [0.0, 0.25, 2 / 3])
def test_sine_correlation_is_eq_2_48(offset):
    f = 16e6
    tau = np.linspace(-1, 2, 31) / f

    def emitted(t):
        return 1.0 + np.sin(2 * np.pi * f * t)

    def gate(t):
        return np.mod(f * t - offset, 1.0) < 0.5

    np.testing.assert_allclose(sine_correlation(tau, f, offset), _brute_force(tau, 1 / f, emitted, gate), atol=1e-4)


@pytest.mark.parametrize("bucket", [0, 1])
def test_pulsed_correlation_is_the_pulse_overlap(bucket):
    t0, duty = 40e-9, 0.25
    period = t0 / duty
    tau = np.linspace(0, 2.5, 26) * t0

    def emitted(t):  # height 1/duty on [0, t0): mean 1; only this pulse (no periodic repetition)
        return ((t >= 0) & (t < t0)) / duty

    def gate(t):
        return (t >= bucket * t0) & (t < (bucket + 1) * t0)

    np.testing.assert_allclose(pulsed_correlation(tau, t0, bucket), _brute_force(tau, period, emitted, gate),
                               atol=1e-4)


# ------------------------------------------------------------------ normalisation
@pytest.mark.parametrize("kind, duty", [("cw_square", 0.5), ("cw_square", 0.3), ("cw_sine", 0.5)])
def test_cw_normalisation(kind, duty):
    m = Modulation(kind=kind, frequencies_hz=(30e6,), phase_steps=(6,), duty_cycle=duty)
    tau = (np.arange(6000) + 0.5) / 6000 / 30e6  # one period, midpoints
    g = np.array([gj(tau) for gj in m.correlations()])
    # mean over τ of m(t − τ) is 1, so the mean of g_j is the gate duty
    np.testing.assert_allclose(g.mean(axis=1), m.gate_duty(), atol=1e-12)
    # complementary gates (k and k + N/2) cover the whole period: their sum is the mean of m, 1
    np.testing.assert_allclose(g[:3] + g[3:], 1.0, atol=1e-12)
    assert g.min() >= 0.0


def test_pulsed_normalisation():
    m = Modulation(kind="pulsed", pulse_width_s=30e-9, duty_cycle=0.1)
    g1, g2 = m.correlations()
    tau = np.linspace(0, 30e-9, 101)
    # the D = duty cancels: a pulse of height 1/D repeated every t0/D gives g1 + g2 = 1 within d_max
    np.testing.assert_allclose(g1(tau) + g2(tau), 1.0, atol=1e-12)
    late = np.linspace(61e-9, 1e-6, 7)  # beyond 2 t0 no bucket sees the light
    assert np.all(g1(late) == 0) and np.all(g2(late) == 0)


def test_ideal_raw_adds_ambient_times_gate_duty():
    m = Modulation(kind="pulsed", pulse_width_s=30e-9, duty_cycle=0.2)
    raw = ideal_raw(m, np.array([1.0, 2.0]), 100.0, 50.0)
    assert raw.shape == (2, 2)
    np.testing.assert_allclose(raw.sum(axis=0), 100.0 + 2 * 0.2 * 50.0)
