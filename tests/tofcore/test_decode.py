"""Tests of tofcore.decode on synthetic raw images of single returns: raw_j = S g_j(2d/c) + A_amb gate_duty_j."""

import time

import numpy as np
import pytest

from tofcore.decode import (decode, decode_cw, decode_pulsed, default_unwrap_tolerance_m, phase_amplitude_offset,
                            radial_to_z, systematic_error_curve, unwrap)
from tofcore.errors import ConfigError
from tofcore.frame import Reason
from tofcore.modulation import Modulation, ideal_raw
from tofcore.transport import SPEED_OF_LIGHT_M_S

C = SPEED_OF_LIGHT_M_S
KINECT = dict(frequencies_hz=(80e6, 16e6, 120e6), phase_steps=(3, 3, 3), exposure_s=(8e-3, 4e-3, 8e-3))


def _square_4_bucket_error_m(distance_m, d_amb_m):
    """Closed-form error of eq. 2.38 on the triangle correlation of a 50 % square wave.

    In cycles x = d / d_amb the steps see the triangle g(x) = 1 − 2|x| (circular distance to 0, 1/4, 1/2,
    3/4). For x ∈ [0, 1/4] that gives Q1 − Q2 = 1 − 4x and Q3 − Q4 = 4x, so with s = 4x the estimate is
    atan2(s, 1 − s) against the truth 2πx = πs/2; the other quarters repeat it rotated by π/2, so the
    error e(s) = atan2(s, 1 − s) − πs/2, s = 4 (x mod 1/4), is periodic in d_amb / 4.
    """
    s = 4 * np.mod(distance_m / d_amb_m, 0.25)
    return (np.arctan2(s, 1 - s) - np.pi * s / 2) / (2 * np.pi) * d_amb_m


def _square_4_bucket_amplitude_m(d_amb_m):
    """Max |e|: de/ds = 1/((1 − s)² + s²) − π/2 = 0 ⇔ 2s² − 2s + 1 − 2/π = 0 ⇔ s = (1 ± √(4/π − 1))/2."""
    s_star = (1 - np.sqrt(4 / np.pi - 1)) / 2
    return abs(_square_4_bucket_error_m(s_star * d_amb_m / 4, d_amb_m))


# ------------------------------------------------------------------ systematic error, noise off
@pytest.mark.parametrize("f_hz", [20e6, 30e6])
def test_square_wave_wiggling_error_matches_the_triangle_closed_form(f_hz):
    m = Modulation(kind="cw_square", frequencies_hz=(f_hz,))
    d_amb = m.ambiguity_distances_m()[0]
    distances = np.linspace(0.0, 2 * d_amb, 8001)
    error = systematic_error_curve(m, distances)[0]
    # the whole curve, not only its maximum, is the closed form (round-off only)
    np.testing.assert_allclose(error, _square_4_bucket_error_m(distances, d_amb), atol=1e-9)
    # periodic in d_amb / 4: shifting by 2000 samples = a quarter of d_amb
    np.testing.assert_allclose(error[2000:], error[:-2000], atol=1e-9)
    amplitude = _square_4_bucket_amplitude_m(d_amb)
    # the grid step d_amb/4000 is near the flat maximum: relative miss ≤ (π/4000)²-ish ≪ 1e-4
    assert np.abs(error).max() == pytest.approx(amplitude, rel=1e-4)
    print(f"\nsquare 4-bucket {f_hz / 1e6:g} MHz: amplitude {amplitude * 1e3:.2f} mm, period {d_amb / 4:.4f} m")


def test_sine_4_bucket_and_pulsed_without_ambient_have_no_systematic_error():
    distances = np.linspace(0.0, 7.4, 5001)
    sine = Modulation(kind="cw_sine", frequencies_hz=(20e6,))
    pulsed = Modulation(kind="pulsed", pulse_width_s=50e-9)  # d_max = 7.49 m
    assert np.abs(systematic_error_curve(sine, distances)).max() < 0.5e-3
    assert np.abs(systematic_error_curve(pulsed, distances)).max() < 0.5e-3


def test_pulsed_ambient_bias_matches_closed_form():
    t0, duty = 50e-9, 0.1
    m = Modulation(kind="pulsed", pulse_width_s=t0, duty_cycle=duty)
    distances = np.linspace(0.1, 7.4, 200)
    signal, ambient = 1000.0, 3000.0
    decoded = decode_pulsed(ideal_raw(m, distances, signal, ambient), m)
    # ambient adds the same a = ambient · duty to both buckets: d = (c t0/2)(S τ/t0 + a)/(S + 2a)
    a, tau = ambient * duty, 2 * distances / C
    np.testing.assert_allclose(decoded, C * t0 / 2 * (signal * tau / t0 + a) / (signal + 2 * a), rtol=1e-12)


# ------------------------------------------------------------------ ambiguity and unwrapping
def test_single_frequency_wraps_beyond_the_ambiguity_distance():
    m = Modulation(kind="cw_sine", frequencies_hz=(30e6,))
    d_amb = m.ambiguity_distances_m()[0]
    out = decode(ideal_raw(m, np.array([1.0, d_amb + 1.0]), 500.0), m)
    np.testing.assert_allclose(out.distance, [1.0, 1.0], atol=1e-5)  # float32 output: ~1e-7 relative


@pytest.mark.parametrize("kind", ["cw_sine", "cw_square"])
def test_kinect_v2_unwraps_from_half_a_metre_to_18_m(kind):
    m = Modulation(kind=kind, **KINECT)
    distances = np.linspace(0.5, 18.0, 20001)
    out = decode(ideal_raw(m, distances, 800.0, 200.0), m)
    assert out.valid.all()
    error = np.abs(out.distance - distances)
    if kind == "cw_sine":
        bound = 1e-3
    else:  # the unwrapped distance is a weighted mean of the per-frequency distances, so the largest
        # per-frequency systematic error (3-step square) bounds it; + 1e-5 for the float32 output
        bound = np.abs(systematic_error_curve(m, np.linspace(0, 9.37, 20001))).max() + 1e-5
    assert error.max() < bound
    print(f"\n{kind} Kinect v2 unwrapped: max error {error.max() * 1e3:.3f} mm (bound {bound * 1e3:.3f} mm)")


def test_kinect_v2_unwraps_noisy_data():
    m = Modulation(kind="cw_sine", **KINECT)
    rng = np.random.default_rng(7)
    distances = rng.uniform(0.5, 18.0, 50_000)
    clean = ideal_raw(m, distances, 2000.0, 1000.0)
    # shot noise: A = S/π ≈ 640 e⁻, B = 1500 e⁻, 3 steps → σ_φ ≈ √(2B/3)/A ≈ 0.05 rad, i.e. σ_d ≈ 74 mm at
    # 16 MHz, 15 mm at 80 MHz, 10 mm at 120 MHz; the weighted mean has σ ≈ 8 mm, so 0.1 m is > 10 σ
    raw = rng.poisson(clean).astype(np.float64)
    out = decode(raw, m)
    error = out.distance - distances
    # no wrong wrap, nothing flagged at this SNR; the residual (~1 cm) keeps the confidence high
    assert out.valid.all() and np.abs(error).max() < 0.1
    assert 0.005 < error.std() < 0.012
    assert 0.8 < out.confidence.mean() <= 1.0


def test_disagreeing_frequencies_fail_to_unwrap():
    # a mixed pixel: the 80 MHz images see a surface half their ambiguity distance (0.94 m) behind the one
    # the 16 and 120 MHz images see; no distance explains both (best weighted RMS disagreement 0.16 m)
    m = Modulation(kind="cw_sine", **KINECT)
    shift = m.ambiguity_distances_m()[0] / 2
    near, far = ideal_raw(m, np.array([3.0]), 1000.0), ideal_raw(m, np.array([3.0 + shift]), 1000.0)
    raw = np.concatenate([far[:3], near[3:]])
    out = decode(raw, m)
    assert out.reason[0] == Reason.UNWRAPPING_FAILED and np.isnan(out.distance[0]) and out.confidence[0] == 0
    assert unwrap(decode_cw(raw, m), m).residual[0] > 2 * default_unwrap_tolerance_m(m)
    # a larger tolerance accepts it with a low confidence
    loose = decode(raw, m, unwrap_tolerance_m=0.5)
    assert loose.valid[0] and 0 < loose.confidence[0] < 0.75


def test_random_inconsistent_frequencies_are_mostly_flagged():
    # each frequency sees an unrelated distance: the default tolerance (d_min/16) flags about two thirds of
    # them (a few percent with d_min/8); this fixed sample of 2000 gives 0.67 ± 0.01
    m = Modulation(kind="cw_sine", **KINECT)
    rng = np.random.default_rng(11)
    raw = np.concatenate([ideal_raw(m, rng.uniform(0, 20, 2000), 1000.0)[3 * i:3 * i + 3] for i in range(3)])
    failed = decode(raw, m).reason == Reason.UNWRAPPING_FAILED
    assert 0.6 < failed.mean() < 0.75


def test_three_steps_give_the_same_distance_as_four_for_sine():
    distances = np.linspace(0.1, 7.0, 500)
    three = Modulation(kind="cw_sine", frequencies_hz=(20e6,), phase_steps=(3,))
    four = Modulation(kind="cw_sine", frequencies_hz=(20e6,), phase_steps=(4,))
    d3 = decode_cw(ideal_raw(three, distances, 100.0, 30.0), three).wrapped_distance[0]
    d4 = decode_cw(ideal_raw(four, distances, 100.0, 30.0), four).wrapped_distance[0]
    np.testing.assert_allclose(d3, distances, atol=1e-9)
    np.testing.assert_allclose(d3, d4, atol=1e-9)


def test_four_step_dft_is_eq_2_38_to_2_41():
    q = np.random.default_rng(3).uniform(0, 100, (4, 50))  # steps k = 0..3 are buckets C1, C3, C2, C4
    q1, q3, q2, q4 = q
    phase, amplitude, offset = phase_amplitude_offset(q)
    np.testing.assert_allclose(phase, np.mod(np.arctan2(q3 - q4, q1 - q2), 2 * np.pi), atol=1e-12)
    np.testing.assert_allclose(amplitude, np.hypot(q1 - q2, q3 - q4) / 2, atol=1e-12)
    np.testing.assert_allclose(offset, (q1 + q2 + q3 + q4) / 4, atol=1e-12)


def test_amplitude_and_offset_of_an_ideal_sine_return():
    m = Modulation(kind="cw_sine", frequencies_hz=(20e6,), phase_steps=(5,))
    cw = decode_cw(ideal_raw(m, np.array([2.0]), 300.0, 80.0), m)
    # g_k = 1/2 + cos(φ − θ_k)/π: A = S/π, B = S/2 + ambient/2
    np.testing.assert_allclose(cw.amplitude[0], 300.0 / np.pi)
    np.testing.assert_allclose(cw.offset[0], 150.0 + 40.0)


def test_decoding_512x424_kinect_is_fast():
    m = Modulation(kind="cw_square", **KINECT)
    raw = ideal_raw(m, np.linspace(0.5, 18.0, 424 * 512).reshape(424, 512), 800.0, 200.0).astype(np.float32)
    decode(raw[:, :8, :8], m)  # warm-up
    start = time.perf_counter()
    out = decode(raw, m)
    seconds = time.perf_counter() - start
    print(f"\ndecode 512x424, 3 frequencies x 3 steps: {seconds * 1e3:.0f} ms")
    assert out.distance.shape == (424, 512) and out.distance.dtype == np.float32
    assert seconds < 2.0  # typically ~0.1 s; loose for loaded CI machines


# ------------------------------------------------------------------ validity and reasons
def _reason_fixture():
    m = Modulation(kind="cw_sine", frequencies_hz=(80e6, 16e6), exposure_s=(1e-3, 1e-3))
    distances = np.array([2.0, 2.0, 2.0, 2.0, 2.0, 9.0, 2.0])
    signal = np.array([500.0, 0.0, 0.0, 5.0, 50_000.0, 500.0, 500.0])
    ambient = np.array([100.0, 0.0, 400.0, 100.0, 100.0, 100.0, 100.0])
    return m, ideal_raw(m, distances, signal, ambient)


def test_reasons_and_no_nan_outside_invalid_pixels():
    m, raw = _reason_fixture()
    out = decode(raw, m, min_amplitude_e=10.0, saturation_e=20_000.0, range_m=(0.5, 8.0))
    expected = [Reason.VALID, Reason.NO_RETURN, Reason.NO_RETURN, Reason.LOW_AMPLITUDE, Reason.SATURATED,
                Reason.OUT_OF_RANGE, Reason.VALID]
    assert out.reason.tolist() == expected and out.reason.dtype == np.uint8
    assert (out.valid == (out.reason == Reason.VALID)).all()
    assert (np.isnan(out.distance) == ~out.valid).all()
    for image in (out.amplitude, out.offset, out.intensity, out.confidence):
        assert np.isfinite(image).all() and image.dtype == np.float32
    assert (out.confidence[~out.valid] == 0).all()
    np.testing.assert_allclose(out.distance[out.valid], 2.0, atol=1e-5)
    np.testing.assert_allclose(out.intensity, raw.mean(axis=0), rtol=1e-6)


def test_reason_precedence():
    m, raw = _reason_fixture()
    # a saturated and weak pixel is SATURATED; a weak, out-of-range pixel is LOW_AMPLITUDE
    out = decode(raw, m, min_amplitude_e=1e6, saturation_e=20_000.0, range_m=(0.5, 1.0))
    assert out.reason.tolist() == [Reason.LOW_AMPLITUDE, Reason.NO_RETURN, Reason.NO_RETURN, Reason.LOW_AMPLITUDE,
                                   Reason.SATURATED, Reason.LOW_AMPLITUDE, Reason.LOW_AMPLITUDE]


def test_pulsed_reasons():
    m = Modulation(kind="pulsed", pulse_width_s=50e-9)
    raw = np.array([[0.0, 300.0, 0.0], [0.0, 100.0, 400.0]])
    out = decode(raw, m, range_m=(0.0, 7.0))
    assert out.reason.tolist() == [Reason.NO_RETURN, Reason.VALID, Reason.OUT_OF_RANGE]  # Q1 = 0: d = d_max
    np.testing.assert_allclose(out.distance[1], C * 50e-9 / 2 * 0.25, rtol=1e-6)
    assert np.isfinite(out.amplitude).all() and out.amplitude.tolist() == [0.0, 400.0, 400.0]


def test_decode_rejects_bad_inputs():
    m = Modulation(kind="cw_sine", frequencies_hz=(20e6,))
    with pytest.raises(ConfigError, match=r"raw must have 4 raw images on axis 0 .*got shape \(3, 2\)"):
        decode(np.zeros((3, 2)), m)
    with pytest.raises(ConfigError, match="raw must be finite"):
        decode(np.full((4, 2), np.nan), m)
    with pytest.raises(ConfigError, match=r"range_m must satisfy 0 <= min < max .*got \(5.0, 1.0\)"):
        decode(np.ones((4, 2)), m, range_m=(5.0, 1.0))
    with pytest.raises(ConfigError, match="tolerance_m must be > 0"):
        decode(np.ones((4, 2)), m, unwrap_tolerance_m=0.0)


# ------------------------------------------------------------------ z-depth
def test_radial_to_z_is_distance_times_ray_z():
    directions = np.array([[[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]], [[0.0, -0.28, 0.96], [0.0, 0.0, 1.0]]])
    distance = np.array([[2.0, 5.0], [1.0, np.nan]], dtype=np.float32)
    z = radial_to_z(distance, directions)
    np.testing.assert_allclose(z[0], [2.0, 4.0], rtol=1e-6)
    assert z[1, 0] == pytest.approx(0.96) and np.isnan(z[1, 1]) and z.dtype == np.float32
    with pytest.raises(ConfigError, match="ray_directions must have shape"):
        radial_to_z(distance, directions[..., :2])
