"""Tests of tofcore.sensor.decode on synthetic raw images of single returns: raw_j = S g_j(2d/c) + A_amb gate_duty_j."""

import numpy as np
import pytest

from tofcore.sensor.decode import (
    DecodeSettings, decode, decode_cw, decode_pulsed, default_unwrap_tolerance_m, phase_amplitude_offset, radial_to_z,
    systematic_error_curve, unwrap,
)
from tofcore.errors import ConfigError
from tofcore.output.frame import Reason
from tofcore.sensor.modulation import Modulation, ideal_raw
from tofcore.constants import SPEED_OF_LIGHT_M_S

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
    loose = decode(raw, m, DecodeSettings(unwrap_tolerance_m=0.5))
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


def test_decoding_a_512x424_kinect_frame_keeps_its_shape_and_dtype():
    """A whole Kinect frame (its time: bench/bench_sensor.py) decodes to float32 images of its shape, every
    distance of the 0.5–18 m ramp recovered (ideal raw images, inside the 18.7 m unambiguous range) to within
    the square wave's wiggling error, the largest of the frequencies' (the unwrapped distance weighs them),
    plus 0.1 mm for float32 raw images."""
    m = Modulation(kind="cw_square", **KINECT)
    truth = np.linspace(0.5, 18.0, 424 * 512).reshape(424, 512)
    out = decode(ideal_raw(m, truth, 800.0, 200.0).astype(np.float32), m)
    assert out.distance.shape == (424, 512) and out.distance.dtype == np.float32
    wiggle_m = float(np.abs(systematic_error_curve(m, truth.ravel())).max())
    np.testing.assert_allclose(out.distance, truth, atol=wiggle_m + 1e-4)


# ------------------------------------------------------------------ validity and reasons
def _reason_fixture():
    m = Modulation(kind="cw_sine", frequencies_hz=(80e6, 16e6), exposure_s=(1e-3, 1e-3))
    distances = np.array([2.0, 2.0, 2.0, 2.0, 2.0, 9.0, 2.0])
    signal = np.array([500.0, 0.0, 0.0, 5.0, 50_000.0, 500.0, 500.0])
    ambient = np.array([100.0, 0.0, 400.0, 100.0, 100.0, 100.0, 100.0])
    return m, ideal_raw(m, distances, signal, ambient)


def test_reasons_and_no_nan_outside_invalid_pixels():
    m, raw = _reason_fixture()
    out = decode(raw, m, DecodeSettings(min_amplitude_e=10.0, saturation_e=20_000.0, range_m=(0.5, 8.0)))
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
    out = decode(raw, m, DecodeSettings(min_amplitude_e=1e6, saturation_e=20_000.0, range_m=(0.5, 1.0)))
    assert out.reason.tolist() == [Reason.LOW_AMPLITUDE, Reason.NO_RETURN, Reason.NO_RETURN, Reason.LOW_AMPLITUDE,
                                   Reason.SATURATED, Reason.LOW_AMPLITUDE, Reason.LOW_AMPLITUDE]


def test_pulsed_reasons():
    m = Modulation(kind="pulsed", pulse_width_s=50e-9)
    raw = np.array([[0.0, 300.0, 0.0], [0.0, 100.0, 400.0]])
    out = decode(raw, m, DecodeSettings(range_m=(0.0, 7.0)))
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
        decode(np.ones((4, 2)), m, DecodeSettings(range_m=(5.0, 1.0)))
    with pytest.raises(ConfigError, match="tolerance_m must be > 0"):
        decode(np.ones((4, 2)), m, DecodeSettings(unwrap_tolerance_m=0.0))


def test_decode_settings_are_checked_once_and_name_the_field():
    with pytest.raises(ConfigError,
                       match=r"DecodeSettings: phasor_filter must be one of \['none', 'bilateral'\], got 'box'"):
        DecodeSettings(phasor_filter="box")
    with pytest.raises(ConfigError, match=r"DecodeSettings: min_amplitude_e must be a finite number >= 0, got -1.0"):
        DecodeSettings(min_amplitude_e=-1.0)
    with pytest.raises(ConfigError, match=r"DecodeSettings: saturation_e must be > 0 \(electrons\) or None, got 0"):
        DecodeSettings(saturation_e=0)
    with pytest.raises(ConfigError, match="decode: settings must be a DecodeSettings, got dict"):
        decode(np.ones((4, 2)), Modulation(kind="cw_sine", frequencies_hz=(20e6,)), {"range_m": (0.0, 1.0)})
    assert DecodeSettings().replace(range_m=[0.5, 2]).range_m == (0.5, 2.0)


# ------------------------------------------------------------------ z-depth
def test_radial_to_z_is_distance_times_ray_z():
    directions = np.array([[[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]], [[0.0, -0.28, 0.96], [0.0, 0.0, 1.0]]])
    distance = np.array([[2.0, 5.0], [1.0, np.nan]], dtype=np.float32)
    z = radial_to_z(distance, directions)
    np.testing.assert_allclose(z[0], [2.0, 4.0], rtol=1e-6)
    assert z[1, 0] == pytest.approx(0.96) and np.isnan(z[1, 1]) and z.dtype == np.float32
    with pytest.raises(ConfigError, match="ray_directions must have shape"):
        radial_to_z(distance, directions[..., :2])


# ------------------------------------------------------------------ linearisation (distance_gradient)
from tofcore import load_preset  # noqa: E402
from tofcore.sensor.decode import distance_gradient, unwrap_weights  # noqa: E402


def _random_returns(n, max_m, seed):
    """n single returns: distance in [0.3, max_m) m, signal 200–2000 e⁻, ambient 0–500 e⁻ per unit duty."""
    rs = np.random.default_rng(seed)
    return rs.uniform(0.3, max_m, n), rs.uniform(200.0, 2000.0, n), rs.uniform(0.0, 500.0, n)


def _central_differences(distance_of, raw, step_e):
    """(R, n) central differences of ``distance_of(raw)`` with respect to each raw image."""
    grad = np.zeros_like(raw)
    for j in range(raw.shape[0]):
        up, down = raw.copy(), raw.copy()
        up[j] += step_e
        down[j] -= step_e
        grad[j] = (distance_of(up) - distance_of(down)) / (2.0 * step_e)
    return grad


def _away_from_phase_wraps(raw, m, margin_rad=1e-3):
    """Pixels whose every frequency's phase is ≥ ``margin_rad`` from 0 ≡ 2π (where a difference would jump)."""
    phase = decode_cw(raw, m).phase
    return np.all((phase > margin_rad) & (phase < 2.0 * np.pi - margin_rad), axis=0)


def _unwrapped(m):
    return lambda raw: unwrap(decode_cw(raw, m), m).distance


# Central differences with a 0.01 e⁻ step on raw images of ~10² – 10³ e⁻: truncation error ~ (0.01/A)² ~ 1e-9
# relative, round-off ~ 1e-16 · 18 m / 0.01 e⁻ ~ 2e-13 m/e⁻ against gradients of ~1e-4 m/e⁻; hence rtol 1e-6
# (of each pixel's largest component) where the linearisation is exact. Measured: ≤ 3e-9.
FD_STEP_E = 1e-2
FD_RTOL = 1e-6


def _assert_gradients_close(grad, reference, rtol):
    scale = np.abs(reference).max(axis=0)
    assert (scale > 0).all()
    error = np.abs(grad - reference).max(axis=0) / scale
    assert error.max() < rtol, f"max relative error {error.max():.3g} (median {np.median(error):.3g})"


def test_distance_gradient_is_exact_for_consistent_sine_data_at_kinect_frequencies():
    """Sine correlation at the Kinect v2 frequencies and steps (80, 16, 120 MHz × 3 steps), with ambient:
    every frequency gives the true distance, so the weights of the unwrapping (held fixed by the
    linearisation) change nothing to first order: the gradient equals central differences of the
    float64 unwrapped distance."""
    kinect = load_preset("kinect_v2").modulation
    m = Modulation(kind="cw_sine", frequencies_hz=kinect.frequencies_hz, phase_steps=kinect.phase_steps,
                   exposure_s=kinect.exposure_s)
    d, s, a = _random_returns(2000, 18.0, seed=11)
    raw = ideal_raw(m, d, s, a)
    keep = _away_from_phase_wraps(raw, m)
    assert keep.mean() > 0.99
    raw = raw[:, keep]
    grad = distance_gradient(raw, m)
    assert grad.shape == raw.shape == (9, keep.sum())
    _assert_gradients_close(grad, _central_differences(_unwrapped(m), raw, FD_STEP_E), FD_RTOL)


def test_distance_gradient_of_the_kinect_v2_preset_holds_the_weights_fixed():
    """The Kinect v2 preset (square wave, 3 × 3 raw images, ambient): its per-frequency distances carry
    different wiggling errors, so the unwrapped distance also moves through the weights w_i ∝ (f A)²/(A+B).
    The documented linearisation holds the weights (and wraps) fixed: against central differences of
    Σ w_i D_i with w_i and the wraps of the unperturbed raw images it is exact (rtol 1e-6, measured
    3e-9); against the full derivative its components differ by at most 3.1 % of the largest (asked
    < 5 %), and the Poisson error it propagates, √(Σ g² Q), by at most 0.6 % (asked < 1 %)."""
    m = load_preset("kinect_v2").modulation
    assert m.kind == "cw_square" and m.raw_count == 9
    d, s, a = _random_returns(2000, 18.0, seed=12)
    raw = ideal_raw(m, d, s, a)
    raw = raw[:, _away_from_phase_wraps(raw, m)]
    grad = distance_gradient(raw, m)

    cw = decode_cw(raw, m)
    weight = unwrap_weights(cw, m)
    d_amb = m.ambiguity_distances_m()[:, None]
    wraps = np.round((unwrap(cw, m).distance - cw.wrapped_distance) / d_amb)

    def fixed_weights(r):
        return (weight * (decode_cw(r, m).wrapped_distance + wraps * d_amb)).sum(axis=0)

    _assert_gradients_close(grad, _central_differences(fixed_weights, raw, FD_STEP_E), FD_RTOL)
    full = _central_differences(_unwrapped(m), raw, FD_STEP_E)
    _assert_gradients_close(grad, full, 0.05)
    sigma_ratio = np.sqrt((grad**2 * raw).sum(axis=0) / (full**2 * raw).sum(axis=0))
    assert np.abs(sigma_ratio - 1.0).max() < 0.01


def test_unwrap_weights_are_normalised_inverse_variances():
    """w_i ∝ (f_i A_i)² / (A_i + B_i) summing to one (eq. 2.43); equal where there is no light at all."""
    m = Modulation(kind="cw_sine", **KINECT)
    raw = ideal_raw(m, np.array([3.0, 7.0]), np.array([1000.0, 300.0]), np.array([100.0, 0.0]))
    raw = np.concatenate([raw, np.zeros((9, 1))], axis=1)  # third pixel: dark
    cw = decode_cw(raw, m)
    w = unwrap_weights(cw, m)
    f = np.array(KINECT["frequencies_hz"])[:, None]
    expected = (f * cw.amplitude[:, :2]) ** 2 / (cw.amplitude[:, :2] + cw.offset[:, :2])
    np.testing.assert_allclose(w[:, :2], expected / expected.sum(axis=0), rtol=1e-12)
    np.testing.assert_allclose(w[:, 2], 1.0 / 3.0, rtol=1e-12)


def test_distance_gradient_of_the_pulsed_xtion2_preset():
    """Xtion 2 preset (pulsed, Q1, Q2): d = (c t0/2) Q2/(Q1+Q2) is differentiable everywhere Q1+Q2 > 0;
    the gradient equals central differences of decode_pulsed (float64) within 1e-6 (measured 2e-9), and the ratio's
    invariance to scaling both buckets gives Σ_j Q_j ∂d/∂Q_j = 0."""
    m = load_preset("xtion2").modulation
    assert not m.is_cw and m.raw_count == 2
    d, s, a = _random_returns(2000, 0.98 * m.ambiguity_distances_m()[0], seed=13)
    raw = ideal_raw(m, d, s, a)
    grad = distance_gradient(raw, m)
    _assert_gradients_close(grad, _central_differences(lambda r: decode_pulsed(r, m), raw, FD_STEP_E), FD_RTOL)
    np.testing.assert_allclose((grad * raw).sum(axis=0), 0.0, atol=1e-12 * np.abs(grad * raw).max())


def test_distance_gradient_ignores_ambient_per_frequency():
    """Adding the same charge to every step of one frequency moves no phase: the gradient of each
    frequency's block sums to zero (Σ_k sin θ_k = Σ_k cos θ_k = 0), as does Σ_j Q_j ∂D/∂Q_j (A scales)."""
    m = Modulation(kind="cw_square", **KINECT)
    d, s, a = _random_returns(500, 18.0, seed=14)
    raw = ideal_raw(m, d, s, a)
    grad = distance_gradient(raw, m)
    scale = np.abs(grad).max()
    for block in (slice(0, 3), slice(3, 6), slice(6, 9)):
        np.testing.assert_allclose(grad[block].sum(axis=0), 0.0, atol=1e-12 * scale)
        np.testing.assert_allclose((grad[block] * raw[block]).sum(axis=0), 0.0, atol=1e-12 * scale * raw.max())


@pytest.mark.parametrize("preset", ["kinect_v2", "xtion2", "o3d303"])
def test_distance_gradient_is_zero_without_light(preset):
    """Dark pixels (all raw images zero) → zero gradient, no NaN."""
    m = load_preset(preset).modulation
    grad = distance_gradient(np.zeros((m.raw_count, 3)), m)
    assert grad.shape == (m.raw_count, 3)
    np.testing.assert_array_equal(grad, 0.0)


def test_distance_gradient_is_zero_for_ambient_only_with_four_steps():
    """Ambient only (equal steps, A = 0, B > 0), 4-step sine: zero gradient, as documented."""
    m = Modulation(kind="cw_sine", frequencies_hz=(20e6, 50e6))
    raw = ideal_raw(m, np.array([2.0, 4.0]), 0.0, np.array([7.0, 300.0]))
    np.testing.assert_array_equal(distance_gradient(raw, m), 0.0)


def test_distance_gradient_is_zero_for_ambient_only_with_three_steps():
    """Ambient only on the Kinect v2 preset (3 steps per frequency): decode calls it NO_RETURN, and the
    gradient is zero. The 3-step DFT weights round asymmetrically (round(sin(2π/3), 15) ≠ −round(sin(4π/3), 15)),
    so equal steps leave |Z| ≈ 4e-14·B: the test must be decode's relative one, not |Z| > 0 (was ±2e12 m/e⁻)."""
    m = load_preset("kinect_v2").modulation
    raw = np.full((m.raw_count, 2), 40.0)
    assert (decode(raw, m).reason == int(Reason.NO_RETURN)).all()
    np.testing.assert_array_equal(distance_gradient(raw, m), 0.0)


def test_range_applies_to_the_scaled_distance():
    """A z-depth camera limits z (libfreenect2 compares z with min_depth): with range_scale = the ray's z
    component, a pixel at radial 0.52 m on a ray 20° off axis (z = 0.489 m) is OUT_OF_RANGE for [0.5, 4.5]."""
    m = Modulation(kind="cw_sine", frequencies_hz=(80e6, 16e6, 120e6), phase_steps=(3, 3, 3))
    raw = ideal_raw(m, np.array([0.52, 0.52]), 1000.0)
    scale = np.array([1.0, np.cos(np.radians(20.0))])
    radial = decode(raw, m, DecodeSettings(range_m=(0.5, 4.5)))
    z = decode(raw, m, DecodeSettings(range_m=(0.5, 4.5), range_scale=scale))
    assert radial.valid.tolist() == [True, True]
    assert z.valid.tolist() == [True, False] and z.reason[1] == Reason.OUT_OF_RANGE


# ------------------------------------------------------------------ noise-floor amplitude threshold
from tofcore.sensor.decode import amplitude_noise_e, decode  # noqa: E402
from tofcore.sensor.noise import NoiseStream, add_raw_noise, keller_amplitude_noise  # noqa: E402


@pytest.mark.parametrize("k", [2.0, 3.0])
def test_unmodulated_pixels_pass_the_noise_floor_threshold_at_the_rayleigh_rate(k):
    """Ambient light only (no LED return): with shot, read and gain noise on the 3 raw images, the amplitude
    is Rayleigh(σ_A) with σ_A = √(2v/N), v = B + σ_read² + (βB)², so exp(−k²/2) of the pixels reach k σ_A.
    Tolerance: 5 binomial standard deviations of the 200 000-pixel share."""
    mod = Modulation(kind="cw_sine", frequencies_hz=(80e6,), phase_steps=(3,))
    rng = NoiseStream.from_seed(7)
    n, ambient_e, read_e, beta = 200_000, 4000.0, 20.0, 0.012
    raw = add_raw_noise(np.full((3, n), ambient_e), read_noise_e=read_e, rng=rng)
    raw = keller_amplitude_noise(raw, alpha_e=0.0, beta=beta, rng=rng)
    out = decode(raw, mod, DecodeSettings(min_amplitude_snr=k, read_noise_e=read_e, gain_noise=beta))
    expected = np.exp(-k * k / 2.0)
    passed = np.mean(out.reason != Reason.LOW_AMPLITUDE)
    assert abs(passed - expected) < 5.0 * np.sqrt(expected * (1.0 - expected) / n), (passed, expected)
    sigma = amplitude_noise_e(np.float64(ambient_e), 3, read_e, beta)
    assert sigma == pytest.approx(np.sqrt(2.0 / 3.0 * (ambient_e + read_e ** 2 + (beta * ambient_e) ** 2)))
    assert np.std(out.amplitude) == pytest.approx(np.sqrt(2.0 - np.pi / 2.0) * sigma, rel=0.02)  # Rayleigh σ


def test_noise_floor_threshold_keeps_a_signal_well_above_it():
    mod = Modulation(kind="cw_sine", frequencies_hz=(80e6,), phase_steps=(3,))
    raw = ideal_raw(mod, np.array([1.0]), 3000.0, 4000.0)  # σ_A ≈ 75 e-
    assert decode(raw, mod, DecodeSettings(min_amplitude_snr=3.0, read_noise_e=20.0, gain_noise=0.012)).valid.all()
    assert not decode(raw, mod, DecodeSettings(min_amplitude_snr=30.0, read_noise_e=20.0,
                                               gain_noise=0.012)).valid.any()
