"""Tests of tofcore.sensor.noise: raw shot + read noise reproduces Li's eq. 2.43 through decoding; Li, Keller; validation.

Derivation checked by the raw-noise tests (it is also in ``li_sigma_m``'s docstring).
A 4-bucket sine pixel collects, in bucket k (gate phase θ_k = k π/2),

    Q_k = A + B + c_d A cos(φ − θ_k)

electrons: A is the mean charge of the camera's light per bucket, B the charge of
everything else (ambient). With c_d = 1 these are the test's raw images
raw_k = S (1 + cos(φ − k π/2)) / 2 + B with S = 2A. Decoding takes
x = Q_0 − Q_2 = 2 c_d A cos φ, y = Q_1 − Q_3 = 2 c_d A sin φ, φ = atan2(y, x), and
to first order δφ = (x δy − y δx) / (x² + y²). Shot noise makes the Q_k
independent with Var Q_k = Q_k (read noise adds σ_r²), so Var δx = Q_0 + Q_2 =
2(A + B + σ_r²) = Var δy and

    Var δφ = (x² + y²) · 2(A + B + σ_r²) / (x² + y²)² = (A + B + σ_r²) / (2 c_d² A²),
    σ_d = c / (4π f) · σ_φ = c / (4√2 π f) · √(A + B + σ_r²) / (c_d A),

which is eq. 2.43 with B → B + σ_r². Normalisation: the thesis's A of eq. 2.40 is
the demodulated amplitude c_d A (= A for c_d = 1), but its B of eq. 2.41 is the
whole offset A + B; eq. 2.43 needs B without the signal's own A (else it
overestimates σ by √((2A + B)/(A + B))), checked in
``test_decoded_amplitude_and_offset_map_to_eq_2_43``.

Statistics: 40 000 samples per case give the sample standard deviation to
1/√(2N) = 0.35 % (1σ); the first-order expansion is good to O(σ_φ²) ≲ 1 % for
the σ_φ ≤ 0.1 rad used. Hence 10 % (the brief) is loose; 3 % is asserted.
"""

import math

import numpy as np
import pytest

from tofcore.errors import ConfigError
from tofcore.sensor.noise import (
    GAUSSIAN_MIN_MEAN, PTRS_MIN_MEAN, PTRS_ROUNDS, NoiseStream, add_distance_noise, add_raw_noise,
    keller_amplitude_noise, li_sigma_m, poisson,
)

C_M_S = 299_792_458.0
F_HZ = 80e6  # Kinect v2's main frequency; d_amb = 1.87 m
TRUE_DISTANCE_M = 0.9
N_SEEDS, PIXELS_PER_SEED = 40, 1000


def sine_raw(amplitude_e: float, ambient_e: float, contrast: float = 1.0, n: int = PIXELS_PER_SEED) -> np.ndarray:
    """(4, n) noise-free 4-bucket raw charge Q_k = A + B + c_d A cos(φ − k π/2) of one pixel, n copies."""
    phi = 4 * math.pi * F_HZ * TRUE_DISTANCE_M / C_M_S
    q = [amplitude_e + ambient_e + contrast * amplitude_e * math.cos(phi - k * math.pi / 2) for k in range(4)]
    return np.repeat(np.array(q)[:, None], n, axis=1)


def decode(raw: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distance (m, eq. 2.38/2.39/2.34), amplitude (eq. 2.40) and offset (eq. 2.41) of 4-bucket raw (4, …)."""
    x, y = raw[0] - raw[2], raw[1] - raw[3]
    phi = np.mod(np.arctan2(y, x), 2 * math.pi)
    return C_M_S * phi / (4 * math.pi * F_HZ), np.hypot(x, y) / 2, raw.mean(axis=0)


def distance_std(amplitude_e: float, ambient_e: float, *, read_noise_e: float = 0.0, contrast: float = 1.0) -> float:
    """Sample std of the decoded distance over N_SEEDS seeds × PIXELS_PER_SEED pixels."""
    raw = sine_raw(amplitude_e, ambient_e, contrast)
    errors = [decode(add_raw_noise(raw, read_noise_e=read_noise_e, rng=NoiseStream.from_seed(seed)))[0]
              - TRUE_DISTANCE_M for seed in range(N_SEEDS)]
    return float(np.std(np.concatenate(errors)))


# 1. Raw noise reproduces eq. 2.43

RAW_CASES = {  # (A, B, read noise, c_d)
    "no-ambient": (2000.0, 0.0, 0.0, 1.0),
    "bright-with-ambient": (2000.0, 3000.0, 0.0, 1.0),
    "dark-with-ambient": (400.0, 3000.0, 0.0, 1.0),
    "read-noise": (800.0, 500.0, 20.0, 1.0),
    "half-contrast": (1500.0, 1000.0, 0.0, 0.5),
}


@pytest.mark.parametrize("amplitude, ambient, read_noise, contrast", RAW_CASES.values(), ids=RAW_CASES.keys())
def test_raw_shot_noise_reproduces_eq_2_43(amplitude, ambient, read_noise, contrast):
    measured = distance_std(amplitude, ambient, read_noise_e=read_noise, contrast=contrast)
    predicted = li_sigma_m(amplitude, ambient + read_noise ** 2, F_HZ, contrast)
    assert measured / predicted == pytest.approx(1.0, abs=0.03)


def test_doubling_ambient_raises_sigma_by_the_square_root_law():
    amplitude, ambient = 1000.0, 2000.0
    ratio = distance_std(amplitude, 2 * ambient) / distance_std(amplitude, ambient)
    expected = math.sqrt((amplitude + 2 * ambient) / (amplitude + ambient))  # √((A+2B)/(A+B)) = 1.29
    assert ratio == pytest.approx(expected, rel=0.03)  # two independent 0.35 % estimates


def test_dark_surfaces_are_noisier_than_bright_ones_at_the_same_ambient():
    ambient = 3000.0
    bright, dark = distance_std(2000.0, ambient), distance_std(500.0, ambient)
    expected = (math.sqrt(500.0 + ambient) / 500.0) / (math.sqrt(2000.0 + ambient) / 2000.0)  # = 3.35
    assert dark > 2.5 * bright
    assert dark / bright == pytest.approx(expected, rel=0.03)


def test_decoded_amplitude_and_offset_map_to_eq_2_43():
    """Eq. 2.40/2.41 from decoding give c_d A and A + B; eq. 2.43 needs A and B (the ambient part only)."""
    amplitude, ambient, contrast = 1500.0, 1000.0, 0.5
    _, decoded_amplitude, decoded_offset = decode(sine_raw(amplitude, ambient, contrast, n=1))
    assert decoded_amplitude[0] == pytest.approx(contrast * amplitude, rel=1e-12)
    assert decoded_offset[0] == pytest.approx(amplitude + ambient, rel=1e-12)
    a = decoded_amplitude / contrast
    sigma = li_sigma_m(a, decoded_offset - a, F_HZ, contrast)
    assert sigma[0] == pytest.approx(li_sigma_m(amplitude, ambient, F_HZ, contrast), rel=1e-12)
    # The thesis (§5.2.2) put eq. 2.41's offset in for B: with c_d = 1 that overestimates σ by √((2A+B)/(A+B)).
    _, amplitude_1, offset_1 = decode(sine_raw(amplitude, ambient, 1.0, n=1))
    thesis = li_sigma_m(amplitude_1, offset_1, F_HZ, 1.0)
    assert thesis[0] / li_sigma_m(amplitude, ambient, F_HZ, 1.0) == pytest.approx(
        math.sqrt((2 * amplitude + ambient) / (amplitude + ambient)), rel=1e-12)


# 2. add_raw_noise itself

def test_raw_noise_mean_and_variance_are_poisson_plus_read_noise():
    charge, read_noise = 400.0, 15.0
    noisy = add_raw_noise(np.full(200_000, charge), read_noise_e=read_noise, rng=NoiseStream.from_seed(3))
    assert noisy.dtype == np.float64
    assert noisy.mean() == pytest.approx(charge, abs=4 * math.sqrt((charge + read_noise ** 2) / noisy.size))
    assert noisy.var() == pytest.approx(charge + read_noise ** 2, rel=0.02)  # var of var: √(2/N) = 0.3 %


def test_raw_noise_clips_at_zero_and_treats_negative_charge_as_none():
    raw = np.array([[-50.0, 0.0, 0.3]] * 10_000)
    noisy = add_raw_noise(raw, read_noise_e=5.0, rng=NoiseStream.from_seed(4))
    assert noisy.min() == 0.0
    np.testing.assert_allclose(noisy[:, 0].mean(), noisy[:, 1].mean(), rtol=0.05)  # both: max(0, N(0, 5²))


def test_raw_noise_is_deterministic_per_seed_and_differs_between_seeds():
    raw = np.random.default_rng(0).random((9, 16, 12)) * 1e3
    first = add_raw_noise(raw, read_noise_e=3.0, rng=NoiseStream.from_seed(42))
    np.testing.assert_array_equal(first, add_raw_noise(raw, read_noise_e=3.0, rng=NoiseStream.from_seed(42)))
    assert not np.array_equal(first, add_raw_noise(raw, read_noise_e=3.0, rng=NoiseStream.from_seed(43)))
    assert first.shape == raw.shape


def test_raw_noise_is_the_same_whatever_the_block_size(monkeypatch):
    """The host code draws block by block (noise.BLOCK elements): a value depends on its flat index only. Charges
    from 0 to 1e12 e⁻ reach every branch (inversion, PTRS, Gaussian); blocks of 7 and 64 elements and one
    block for all give the same frame."""
    from tofcore.sensor import noise

    g = np.random.default_rng(15)
    raw = np.exp(g.uniform(np.log(0.05), np.log(1e12), (3, 20, 21))) - 0.1
    frames = []
    for block in (7, 64, raw.size):
        monkeypatch.setattr(noise, "BLOCK", block)
        frames.append(add_raw_noise(raw, read_noise_e=3.0, rng=NoiseStream.from_seed(5)))
    np.testing.assert_array_equal(frames[0], frames[2])
    np.testing.assert_array_equal(frames[1], frames[2])


def _chi2_critical(dof: int, z: float = 3.719) -> float:
    """Upper 1e-4 quantile of χ²(dof) (z = 3.719 standard normal) by Wilson–Hilferty (rel. error < 1 %, dof ≥ 3)."""
    a = 2.0 / (9.0 * dof)
    return dof * (1.0 - a + z * math.sqrt(a)) ** 3


def _poisson_chi2(counts: np.ndarray, lam: float) -> tuple[float, int]:
    """Pearson's χ² of ``counts`` against the Poisson(λ) pmf, cells with expected ≥ 5 (tails merged), and
    its degrees of freedom."""
    n = counts.size
    k = np.arange(int(lam + 12 * math.sqrt(lam) + 30))
    pmf = np.exp(-lam + k * math.log(lam) - np.array([math.lgamma(x + 1.0) for x in k]))
    keep = np.flatnonzero(n * pmf >= 5)
    lo, hi = keep[0], keep[-1]
    expected = np.concatenate([[pmf[:lo].sum()], pmf[lo:hi + 1], [1.0 - pmf[:hi + 1].sum()]]) * n
    observed = np.concatenate([[np.sum(counts < lo)], np.bincount(counts.astype(np.int64), minlength=hi + 1)[lo:hi + 1],
                               [np.sum(counts > hi)]])
    cells = expected > 0
    chi2 = float(np.sum((observed[cells] - expected[cells]) ** 2 / expected[cells]))
    return chi2, int(cells.sum()) - 1


@pytest.mark.parametrize("lam", [0.3, 2.0, 7.5, 9.99, 10.0, 37.5, 400.0, 25_000.0])
def test_poisson_counts_follow_the_exact_pmf(lam):
    """Inversion below 10, PTRS from 10 on: exact in distribution, so Pearson's χ² of 200 000 counts against
    the Poisson pmf (cells with ≥ 5 expected) stays below its upper 1e-4 quantile (a false alarm once in 10⁴
    seeds; seeds fixed). Mean and variance within 5 standard errors (var of the sample variance:
    (μ₄ − σ⁴)/N = (λ + 2λ²)/N)."""
    n = 200_000
    counts = poisson(np.full(n, lam), NoiseStream.from_seed(11).key, 0)
    assert counts.dtype == np.float64 and np.array_equal(counts, np.round(counts)) and counts.min() >= 0
    chi2, dof = _poisson_chi2(counts, lam)
    assert chi2 < _chi2_critical(dof), (chi2, dof)
    assert abs(counts.mean() - lam) < 5 * math.sqrt(lam / n)
    assert abs(counts.var() - lam) < 5 * math.sqrt((lam + 2 * lam * lam) / n)


def test_poisson_beyond_any_full_well_is_gaussian_with_the_poisson_moments():
    """From 1e10 e⁻ on N(λ, λ) rounded (skewness λ^-1/2 = 1e-5 is all it misses): mean and variance
    within 5 standard errors over 100 000 draws."""
    lam, n = 4.0 * GAUSSIAN_MIN_MEAN, 100_000
    counts = poisson(np.full(n, lam), NoiseStream.from_seed(12).key, 0)
    assert abs(counts.mean() - lam) < 5 * math.sqrt(lam / n)
    assert counts.var() / lam == pytest.approx(1.0, abs=5 * math.sqrt(2.0 / n))


def test_each_ptrs_round_accepts_at_least_75_percent():
    """PTRS_ROUNDS rounds leave a count open with probability ≤ 0.25^24 ≈ 3.6e-15 (noise.PTRS_ROUNDS): each round
    accepts with probability 1/α, 0.75 at λ = 10 rising to 1/1.1239 = 0.89; measured on 100 000 pairs
    (binomial standard error 0.14 %), above 0.745 everywhere."""
    from tofcore.sensor import noise

    assert PTRS_ROUNDS == 24 and PTRS_MIN_MEAN == 10.0
    uv = np.random.default_rng(13).random((2, 100_000)) * (1 - 2 ** -53) + 2 ** -54
    for lam in (10.0, 13.0, 50.0, 1e3, 1e6, 1e9):
        lam_arr = np.full(uv.shape[1], lam)
        _, accepted = noise._ptrs(lam_arr, *noise._ptrs_hat(lam_arr), uv[0], uv[1])
        assert accepted.mean() > 0.745, (lam, accepted.mean())


def test_poisson_stays_below_2_to_the_33_and_is_one_number_per_element_and_dimension():
    """Counts depend on (key, element index, dim) only: a sub-array's counts are the full array's where the
    index is the same (the first elements), and another dim gives other counts."""
    mean = np.concatenate([np.linspace(0.0, 30.0, 300), np.geomspace(30.0, 1e12, 300)])
    key = NoiseStream.from_seed(14).key
    full = poisson(mean, key, 64)
    np.testing.assert_array_equal(poisson(mean[:100], key, 64), full[:100])
    assert not np.array_equal(poisson(mean, key, 128), full)


# 3. Li's model

def test_li_sigma_value_units_and_limits():
    # c / (4√2 π · 80 MHz) = 0.2108 m; √(1000 + 3000) / 1000 = 0.0632.
    assert li_sigma_m(1000.0, 3000.0, F_HZ, 1.0) == pytest.approx(C_M_S / (4 * math.sqrt(2) * math.pi * F_HZ)
                                                                 * math.sqrt(4000.0) / 1000.0, rel=1e-14)
    assert li_sigma_m(1000.0, 3000.0, F_HZ / 2, 1.0) == pytest.approx(2 * li_sigma_m(1000.0, 3000.0, F_HZ, 1.0))
    assert li_sigma_m(1000.0, 3000.0, F_HZ, 0.5) == pytest.approx(2 * li_sigma_m(1000.0, 3000.0, F_HZ, 1.0))
    with np.errstate(all="raise"):
        sigma = li_sigma_m(np.array([0.0, 0.0, np.nan, 100.0, 100.0]), np.array([5.0, 0.0, 1.0, np.nan, -500.0]),
                           F_HZ, 1.0)
    np.testing.assert_array_equal(sigma, [np.inf, np.inf, np.nan, np.nan, 0.0])
    assert li_sigma_m(np.ones((2, 3)), 1.0, F_HZ, 1.0).shape == (2, 3)


def test_add_distance_noise_matches_li_sigma():
    amplitude = np.array([300.0, 1000.0, 5000.0])[:, None]
    sigma = li_sigma_m(amplitude, 2000.0, F_HZ, 0.8)
    distance = np.full((3, 100_000), 2.5)
    noisy = add_distance_noise(distance, sigma, NoiseStream.from_seed(5))
    np.testing.assert_allclose(noisy.std(axis=1) / sigma[:, 0], 1.0, atol=0.03)  # N = 1e5: 0.22 % (1σ)
    assert np.all(np.abs(noisy.mean(axis=1) - 2.5) < 4 * sigma[:, 0] / math.sqrt(1e5))  # unbiased


def test_add_distance_noise_invalidates_where_sigma_is_unknown():
    with np.errstate(all="raise"):
        noisy = add_distance_noise(np.array([1.0, np.nan, 2.0, 3.0]), np.array([np.inf, 0.1, np.nan, 0.0]),
                                   NoiseStream.from_seed(0))
    np.testing.assert_array_equal(noisy, [np.nan, np.nan, np.nan, 3.0])
    a = add_distance_noise(np.ones((4, 5)), 0.01, NoiseStream.from_seed(9))
    np.testing.assert_array_equal(a, add_distance_noise(np.ones((4, 5)), 0.01, NoiseStream.from_seed(9)))


# 4. Keller's model

def test_keller_noise_has_std_alpha_plus_beta_times_value():
    value, alpha, beta = 2000.0, 10.0, 0.01
    noisy = keller_amplitude_noise(np.full(100_000, value), alpha_e=alpha, beta=beta, rng=NoiseStream.from_seed(6))
    assert noisy.std() == pytest.approx(alpha + beta * value, rel=0.03)
    assert noisy.mean() == pytest.approx(value, abs=4 * (alpha + beta * value) / math.sqrt(1e5))


# 5. Validation

@pytest.mark.parametrize("call, match", [
    (lambda: add_raw_noise(np.ones(3), read_noise_e=-1.0, rng=NoiseStream.from_seed(0)),
     "add_raw_noise: read_noise_e must be a finite number >= 0, got -1.0"),
    (lambda: add_raw_noise(np.ones(3), read_noise_e=1.0, rng=np.random.default_rng(0)),
     "add_raw_noise: rng must be a tofcore.sensor.noise.NoiseStream"),
    (lambda: NoiseStream.from_seed(-1), "NoiseStream: seed must be an integer >= 0, got -1"),
    (lambda: add_raw_noise(np.array([1.0, np.nan]), read_noise_e=1.0, rng=NoiseStream.from_seed(0)),
     "add_raw_noise: raw must be finite, got 1 non-finite"),
    (lambda: li_sigma_m(1.0, 1.0, 0.0, 1.0), "li_sigma_m: f_hz must be a finite number > 0, got 0.0"),
    (lambda: li_sigma_m(1.0, 1.0, F_HZ, 1.2),
     "li_sigma_m: modulation_contrast must be a number in \\(0, 1\\], got 1.2"),
    (lambda: add_distance_noise(np.ones(2), np.array([0.1, -0.2]), NoiseStream.from_seed(0)),
     "add_distance_noise: sigma must be >= 0 \\(m\\), got minimum -0.2"),
    (lambda: keller_amplitude_noise(np.ones(2), alpha_e=1.0, beta=-0.1, rng=NoiseStream.from_seed(0)),
     "keller_amplitude_noise: beta must be a finite number >= 0, got -0.1"),
])
def test_bad_parameters_raise_config_error_naming_them(call, match):
    with pytest.raises(ConfigError, match=match):
        call()
