"""Randomized QMC samples (tofcore.tracer.qmc): bit tricks, the Sobol' net property, scrambling, replicates, determinism.

Statistical checks use fixed seeds, so each is deterministic; thresholds are quantiles a correct sampler
exceeds with probability ≤ 0.1 % (chi-square) or ≈ 6e-5 (|corr| < 4/√N, a 4σ bound for uncorrelated
uniforms, whose sample correlation has standard deviation 1/√N).
"""

import math

import numpy as np
import pytest

from tofcore import rng as tof_rng
from tofcore.tracer import qmc

U32 = np.uint32
R = qmc.REPLICATES
KEY = tof_rng.seed_key(2024)


def chi2_quantile_999(df: int) -> float:
    """99.9 % quantile of chi-square with ``df`` degrees of freedom (Wilson–Hilferty, < 0.5 % off for df ≥ 15)."""
    z = 3.0902  # standard normal 99.9 % quantile
    return df * (1.0 - 2.0 / (9.0 * df) + z * math.sqrt(2.0 / (9.0 * df))) ** 3


def chi2_uniform(values: np.ndarray, bins: int) -> float:
    counts = np.bincount(np.minimum((values * bins).astype(np.int64), bins - 1), minlength=bins)
    expected = len(values) / bins
    return float(((counts - expected) ** 2 / expected).sum())


def to_fixed(u: np.ndarray) -> np.ndarray:
    """Floats k · 2⁻³² back to their uint32 fixed point (exact: 32-bit integers times a power of two)."""
    k = u * 4294967296.0
    assert np.array_equal(k, np.floor(k)), "samples must be multiples of 2^-32"
    return k.astype(np.uint64).astype(U32)


def assert_is_0m2_net(x: np.ndarray, y: np.ndarray, m: int) -> None:
    """Every elementary box 2^-a × 2^-(m-a), a = 0..m, holds exactly one of the 2^m points (uint32 fixed point)."""
    assert len(x) == 1 << m
    for a in range(m + 1):
        bx = x.astype(np.uint64) >> np.uint64(32 - a)
        by = y.astype(np.uint64) >> np.uint64(32 - (m - a))
        box = (bx << np.uint64(m - a)) | by
        assert len(np.unique(box)) == 1 << m, f"boxes of shape 2^-{a} x 2^-{m - a}: some box holds two points"


# ------------------------------------------------------------------ bit tricks
def test_reverse_bits_is_an_involution_and_reverses():
    rs = np.random.default_rng(0)
    x = rs.integers(0, 2**32, 10_000, dtype=np.uint64).astype(U32)
    np.testing.assert_array_equal(qmc.reverse_bits(qmc.reverse_bits(x)), x)
    # Single bits: bit b goes to bit 31 − b.
    b = np.arange(32, dtype=U32)
    np.testing.assert_array_equal(qmc.reverse_bits(U32(1) << b), U32(1) << (U32(31) - b))
    np.testing.assert_array_equal(qmc.reverse_bits(np.array([0, 0xFFFFFFFF, 0x0000FFFF], U32)),
                                  np.array([0, 0xFFFFFFFF, 0xFFFF0000], U32))


@pytest.mark.parametrize("seed", [0, 1, 0x9E3779B9, 0xFFFFFFFF])
def test_owen_scramble_permutes_every_aligned_block(seed):
    """Bit b of the output depends only on the input bits above b (and on its own bit by XOR), so an aligned
    block [c·2^m, (c+1)·2^m) maps onto an aligned block: its top 32 − m bits are one constant, its low m
    bits a permutation of 0..2^m − 1 (m = 8 here, and the whole low range 0..255 as the sample index uses it)."""
    for c in (0, 1, 0xABCDE, (1 << 24) - 1):
        x = (np.arange(256, dtype=np.uint64) + np.uint64(c << 8)).astype(U32)
        y = qmc.owen_scramble(x, U32(seed))
        assert len(np.unique(y >> U32(8))) == 1, "the top 24 bits must be shared by the whole block"
        np.testing.assert_array_equal(np.sort(y & U32(0xFF)), np.arange(256, dtype=U32))


def test_owen_scramble_is_a_nested_scramble():
    """Owen's structure on random pairs: inputs that share their top t bits and differ in bit 31 − t give
    outputs that share the same top t bits and also differ in bit 31 − t (each node of the binary tree of
    intervals is flipped or not, as a whole). Implies bijectivity; checked for all t = 0..31."""
    rs = np.random.default_rng(1)
    n = 4096
    t = rs.integers(0, 32, n).astype(U32)
    a = rs.integers(0, 2**32, n, dtype=np.uint64).astype(U32)
    flip = U32(0x80000000) >> t                                  # bit 31 − t
    low = (flip - U32(1)) & rs.integers(0, 2**32, n, dtype=np.uint64).astype(U32)  # random bits below it
    high_mask = ~((flip << U32(1)) - U32(1)) & U32(0xFFFFFFFF)
    high_mask = np.where(t == 0, U32(0), high_mask)              # t = 0: no shared bits
    b = (a & high_mask) | (~a & flip) | low
    for seed in (U32(7), U32(0xC0FFEE)):
        ya, yb = qmc.owen_scramble(a, seed), qmc.owen_scramble(b, seed)
        np.testing.assert_array_equal(ya & high_mask, yb & high_mask)
        np.testing.assert_array_equal((ya ^ yb) & flip, flip)


def test_owen_scramble_depends_on_the_seed():
    x = np.arange(1024, dtype=U32)
    assert not np.array_equal(qmc.owen_scramble(x, U32(1)), qmc.owen_scramble(x, U32(2)))


# ------------------------------------------------------------------ Sobol' points
def test_sobol_2d_first_points():
    """The first 8 points of Sobol' dimensions 1, 2 (van der Corput; Joe–Kuo's second dimension, direct
    index order as in scipy.stats.qmc.Sobol(scramble=False))."""
    x, y = qmc.sobol_2d(np.arange(8, dtype=U32))
    np.testing.assert_array_equal(x / 2.0**32, [0, 0.5, 0.25, 0.75, 0.125, 0.625, 0.375, 0.875])
    np.testing.assert_array_equal(y / 2.0**32, [0, 0.5, 0.75, 0.25, 0.625, 0.125, 0.375, 0.875])


@pytest.mark.parametrize("m", [1, 4, 7, 10, 12])
def test_sobol_2d_prefixes_and_aligned_blocks_are_0m2_nets(m):
    """A (0, 2)-sequence: points 0..2^m − 1, and any aligned block of 2^m points, form a (0, m, 2)-net."""
    x, y = qmc.sobol_2d(np.arange(1 << m, dtype=U32))
    assert_is_0m2_net(x, y, m)
    for c in (1, 5, 1 << (20 - m)):
        x, y = qmc.sobol_2d((np.arange(1 << m, dtype=np.uint64) + np.uint64(c << m)).astype(U32))
        assert_is_0m2_net(x, y, m)


def test_sobol_2d_high_index_bits_use_all_four_tables():
    """Index bits above 2^24 (table 3) still give nets: a block of 2^8 points starting at 3·2^29."""
    x, y = qmc.sobol_2d((np.arange(256, dtype=np.uint64) + np.uint64(3 << 29)).astype(U32))
    assert_is_0m2_net(x, y, 8)


def replicate_points(pixel: int, replicate: int, m: int, dim: int, start: int = 0):
    """Points j = start..start + 2^m − 1 of one replicate: samples i = replicate + R·j of ``pixel``."""
    j = np.arange(start, start + (1 << m))
    sample = replicate + R * j
    return qmc.sample_2d(KEY, np.full(len(j), pixel), sample, dim)


@pytest.mark.parametrize("pixel, replicate, dim", [(0, 0, 0), (37, 1, 1), (12345, 3, 5), (7, 2, 1_000_001)])
def test_each_scrambled_replicate_is_a_0m2_net(pixel, replicate, dim):
    """Owen scrambling keeps the net property: the first 2^10 points of one replicate of one pixel, and their
    aligned sub-blocks of 2^6 points, have one point in every elementary box."""
    u, v = replicate_points(pixel, replicate, 10, dim)
    x, y = to_fixed(u), to_fixed(v)
    assert_is_0m2_net(x, y, 10)
    for c in range(0, 16, 5):
        assert_is_0m2_net(x[c * 64:(c + 1) * 64], y[c * 64:(c + 1) * 64], 6)


def test_sample_1d_replicate_is_stratified():
    """sample_1d, a scrambled van der Corput sequence: 2^m points of one replicate, one per interval 2^-m."""
    j = np.arange(1 << 10)
    for replicate in range(R):
        u = qmc.sample_1d(KEY, np.full(len(j), 99), replicate + R * j, dim=4)
        assert len(np.unique(to_fixed(u) >> U32(22))) == 1 << 10


def test_samples_are_in_the_unit_interval_and_float64():
    pixel = np.arange(5000)
    for u in (*qmc.sample_2d(KEY, pixel, pixel % 16, 3), qmc.sample_1d(KEY, pixel, pixel % 16, 2)):
        assert u.dtype == np.float64 and u.shape == pixel.shape
        assert (u >= 0).all() and (u < 1).all()


# ------------------------------------------------------------------ statistics over pixels
N_PIXELS = 1 << 14


@pytest.mark.parametrize("sample, dim", [(0, 0), (5, 1), (17, 3), (63, 1_000_001)])
def test_marginals_over_pixels_are_uniform(sample, dim):
    """One sample of 2^14 pixels: u, v and (u, v) histograms (64 bins, 16 × 16 cells) pass chi-square at
    the 99.9 % quantile (df 63: 103.5; df 255: 311.5)."""
    pixel = np.arange(N_PIXELS)
    u, v = qmc.sample_2d(KEY, pixel, np.full(N_PIXELS, sample), dim)
    w = qmc.sample_1d(KEY, pixel, np.full(N_PIXELS, sample), dim + 1)
    for values in (u, v, w):
        assert chi2_uniform(values, 64) < chi2_quantile_999(63)
    cells = np.minimum((u * 16).astype(int), 15) * 16 + np.minimum((v * 16).astype(int), 15)
    assert chi2_uniform((cells + 0.5) / 256, 256) < chi2_quantile_999(255)


def test_coordinates_and_dimensions_are_uncorrelated_over_pixels():
    """Over 2^14 pixels (one sample each): u and v of one pair, the same coordinate of different dimension
    pairs (pixel jitter, lens, bounce directions, light vertex), 1-D against 2-D dimensions and different
    replicates of the same pixel: |corr| < 4/√N = 0.031."""
    pixel = np.arange(N_PIXELS)
    sample = np.full(N_PIXELS, 6)
    draws = {}
    for dim in (0, 1, 3, 5, 1_000_001):
        draws[f"u{dim}"], draws[f"v{dim}"] = qmc.sample_2d(KEY, pixel, sample, dim)
    for dim in (2, 4, 1_000_000):
        draws[f"s{dim}"] = qmc.sample_1d(KEY, pixel, sample, dim)
    draws["u0 of sample 7"] = qmc.sample_2d(KEY, pixel, sample + 1, 0)[0]  # replicate 3 against replicate 2
    names = list(draws)
    values = np.stack([draws[k] for k in names])
    corr = np.corrcoef(values)
    bound = 4.0 / math.sqrt(N_PIXELS)
    for a in range(len(names)):
        for b in range(a):
            assert abs(corr[a, b]) < bound, f"corr({names[a]}, {names[b]}) = {corr[a, b]:.4f}"


def test_dimensions_of_one_pixel_are_decorrelated_by_the_index_scramble():
    """Within one pixel (4096 samples, all replicates) the pairs of different dimensions are shuffled
    independently ("padding"): |corr| < 4/√4096 = 0.0625 between coordinates of different dimensions."""
    sample = np.arange(4096)
    pixel = np.full(len(sample), 321)
    u0, v0 = qmc.sample_2d(KEY, pixel, sample, 0)
    u1, v1 = qmc.sample_2d(KEY, pixel, sample, 1)
    u3, _ = qmc.sample_2d(KEY, pixel, sample, 3)
    s2 = qmc.sample_1d(KEY, pixel, sample, 2)
    pairs = {"u0-u1": (u0, u1), "v0-v1": (v0, v1), "u0-v1": (u0, v1), "u1-u3": (u1, u3), "u0-s2": (u0, s2)}
    for name, (a, b) in pairs.items():
        c = np.corrcoef(a, b)[0, 1]
        assert abs(c) < 4.0 / 64.0, f"{name}: corr {c:.4f}"


def test_replicates_are_different_randomizations():
    """Point j of the four replicates of a pixel: no two replicates share a point (with 2^32 fixed-point
    values per coordinate a collision of correct independent scrambles has probability ≈ 2^-32 per pair)."""
    pts = [tuple(map(to_fixed, replicate_points(5, r, 6, dim=1))) for r in range(R)]
    for a in range(R):
        for b in range(a):
            assert not np.any((pts[a][0] == pts[b][0]) & (pts[a][1] == pts[b][1]))
            assert not np.array_equal(np.sort(pts[a][0]), np.sort(pts[b][0]))


def test_seed_key_and_pixel_change_the_points():
    pixel = np.zeros(64, np.int64)
    sample = np.arange(64)
    a = qmc.sample_2d(KEY, pixel, sample, 0)[0]
    assert not np.array_equal(a, qmc.sample_2d(tof_rng.seed_key(2025), pixel, sample, 0)[0])
    assert not np.array_equal(a, qmc.sample_2d(KEY, pixel + 1, sample, 0)[0])


# ------------------------------------------------------------------ samplers and determinism
def test_independent_sampler_is_rng_uniform_in_the_documented_dims():
    """``"independent"``: pair ``dim`` takes rng dims 2·dim, 2·dim + 1; 1-D ``dim`` takes 2·dim."""
    pixel = np.arange(300) % 37
    sample = np.arange(300) // 37
    for dim in (0, 1, 4, 1_000_001):
        u, v = qmc.sample_2d(KEY, pixel, sample, dim, sampler="independent")
        np.testing.assert_array_equal(u, tof_rng.uniform(KEY, pixel, sample, 2 * dim))
        np.testing.assert_array_equal(v, tof_rng.uniform(KEY, pixel, sample, 2 * dim + 1))
        np.testing.assert_array_equal(qmc.sample_1d(KEY, pixel, sample, dim, sampler="independent"),
                                      tof_rng.uniform(KEY, pixel, sample, 2 * dim))
    assert qmc.SAMPLERS == ("sobol", "independent")


@pytest.mark.parametrize("sampler", qmc.SAMPLERS)
def test_a_sample_depends_only_on_its_coordinates(sampler):
    """(key, pixel, sample, dim) fixes the bits: a shuffled batch and one-element batches give the same values."""
    rs = np.random.default_rng(3)
    pixel = rs.integers(0, 512 * 424, 2000)
    sample = rs.integers(0, 4096, 2000)
    order = rs.permutation(2000)
    for dim in (0, 3):
        u, v = qmc.sample_2d(KEY, pixel, sample, dim, sampler)
        us, vs = qmc.sample_2d(KEY, pixel[order], sample[order], dim, sampler)
        np.testing.assert_array_equal(us, u[order])
        np.testing.assert_array_equal(vs, v[order])
        s = qmc.sample_1d(KEY, pixel, sample, dim + 1, sampler)
        np.testing.assert_array_equal(qmc.sample_1d(KEY, pixel[order], sample[order], dim + 1, sampler), s[order])
        for i in range(0, 2000, 199):
            one = qmc.sample_2d(KEY, pixel[i:i + 1], sample[i:i + 1], dim, sampler)
            assert one[0][0] == u[i] and one[1][0] == v[i]
