"""Adaptive sampling (tofcore.tracer.adaptive): the allocation rule against a naive reference and its contract
(pilot, multiples of R, budget, floor, cap, NaN), and adaptive traces (determinism, sample counts, no bias)."""

import numpy as np
import pytest

import tofcore
from tofcore import LED, Camera, trace
from tofcore.tracer.adaptive import CAP, FLOOR, PILOT_SPP, allocate_samples
from tofcore.tracer.qmc import REPLICATES as R

H, W = 12, 16
P = H * W


def reference_allocation(sigma, counts, n):
    """One pixel at a time, straight from the module docstring: v_p = σ_p² n_p, averaged over the finite
    values of the 3 × 3 neighbourhood; weight √v̄ (the mean weight where unknown), clipped to
    [FLOOR, CAP] × the mean known weight; target total ∝ weight; each pixel gets what it lacks, scaled
    to the budget n·P, rounded to a multiple of R. Returns (allocation, target totals)."""
    h, w = sigma.shape
    counts = counts.reshape(h, w).astype(float)
    weight = np.full((h, w), np.nan)
    for y in range(h):
        for x in range(w):
            vals = [sigma[j, i] ** 2 * counts[j, i]
                    for j in range(max(0, y - 1), min(h, y + 2)) for i in range(max(0, x - 1), min(w, x + 2))
                    if np.isfinite(sigma[j, i])]
            if vals:
                weight[y, x] = np.sqrt(np.mean(vals))
    known = np.isfinite(weight)
    mean = weight[known].mean() if known.any() and weight[known].mean() > 0 else 1.0
    weight = np.clip(np.where(known, weight, mean), FLOOR * mean, CAP * mean)
    target = (counts.sum() + n * h * w) * weight / weight.sum()
    lacking = np.maximum(target - counts, 0.0)
    extra = lacking * (n * h * w / lacking.sum())
    return (np.round(extra / R).astype(int) * R).reshape(-1), target.reshape(-1)


def check_contract(alloc, n, p=P):
    """Multiples of R, ≥ 0, summing to the budget n·P within the rounding of each pixel to a multiple of
    R (≤ R/2 each, so ≤ R·P/2 in all)."""
    assert alloc.shape == (p,) and alloc.dtype == np.int64
    assert (alloc >= 0).all() and (alloc % R == 0).all()
    assert abs(int(alloc.sum()) - n * p) <= R * p / 2


def lognormal_sigma(seed, spread=0.5):
    return np.exp(np.random.default_rng(seed).normal(0.0, spread, (H, W))) * 1e-3


# ------------------------------------------------------------------ allocate_samples
def test_no_allocation_during_the_pilot():
    """Uniform passes until every pixel has PILOT_SPP = 16 samples; counts may be (H, W) or (P,)."""
    sigma = lognormal_sigma(0)
    counts = np.full(P, PILOT_SPP)
    counts[7] = PILOT_SPP - 1
    assert allocate_samples(sigma, counts, 16) is None
    assert allocate_samples(sigma, np.full((H, W), 8), 16) is None
    assert allocate_samples(sigma, np.full(P, PILOT_SPP), 16) is not None
    np.testing.assert_array_equal(allocate_samples(sigma, np.full(P, PILOT_SPP), 16),
                                  allocate_samples(sigma, np.full((H, W), PILOT_SPP), 16))


@pytest.mark.parametrize("n", [1, 4, 6, 16, 64])
@pytest.mark.parametrize("seed", [1, 2])
def test_allocation_matches_the_reference_and_keeps_the_contract(n, seed):
    """Random σ (log-normal, factor e^±0.5; one NaN hole) and uneven earlier counts (16..80, multiples
    of R), several budgets: equal to the naive reference (same formulas, different summation order: a
    count can only differ where extra/R lands within ~1e-12 of a rounding boundary — none here)."""
    rs = np.random.default_rng(seed)
    sigma = lognormal_sigma(seed)
    sigma[3:6, 4:8] = np.nan
    counts = rs.integers(4, 21, P) * R
    alloc = allocate_samples(sigma, counts, n)
    check_contract(alloc, n)
    np.testing.assert_array_equal(alloc, reference_allocation(sigma, counts, n)[0])


def test_uniform_sigma_gives_a_uniform_allocation():
    """Equal σ and counts: every pixel gets n; an n that is no multiple of R is rounded the same way in
    every pixel (6 → 4 or 8: extra/R = 1.5 up to the last bit, so which one is float rounding)."""
    sigma = np.full((H, W), 2e-3)
    for n in (4, 16, 64):
        np.testing.assert_array_equal(allocate_samples(sigma, np.full(P, 16), n), n)
    alloc = allocate_samples(sigma, np.full(P, 16), 6)
    assert (alloc == alloc[0]).all() and alloc[0] in (4, 8)


def test_noisier_pixels_get_more_samples_in_neyman_proportion():
    """A 4 × 4 block with 10× the σ of the rest (16 pilot samples each, budget 64): the block's pixels get
    the most samples, its interior far more than distant pixels. All pixels lack samples here, so after the
    pass each pixel's total is the Neyman target ∝ √(3×3 mean of σ² n) within the rounding to R/2: the
    block interior (√100 = 10× the weight) holds 10× the total of a distant pixel."""
    sigma = np.full((H, W), 1e-3)
    sigma[4:8, 6:10] = 1e-2
    counts = np.full(P, 16)
    alloc = allocate_samples(sigma, counts, 64).reshape(H, W)
    check_contract(alloc.reshape(-1), 64)
    assert alloc[4:8, 6:10].min() > alloc[:, :3].max()
    assert alloc.max() == alloc[5:7, 7:9].max()
    total = alloc + 16
    _, target = reference_allocation(sigma, counts, 64)
    np.testing.assert_allclose(total.reshape(-1), target, atol=R / 2)
    assert total[5, 7] / total[0, 0] == pytest.approx(10.0, rel=0.05)


def test_nan_pixels_get_at_least_the_floor_share():
    """Unknown σ (NaN: no sample in some replicate yet) never starves a pixel: a NaN block with no finite
    neighbour takes the mean weight, its border pixels their neighbours' weight; every NaN pixel gets
    more than FLOOR × the mean allocation. All NaN: uniform."""
    sigma = lognormal_sigma(3)
    sigma[2:9, 3:11] = np.nan
    alloc = allocate_samples(sigma, np.full(P, 16), 32).reshape(H, W)
    check_contract(alloc.reshape(-1), 32)
    assert (alloc[2:9, 3:11] >= FLOOR * 32).all() and (alloc[2:9, 3:11] > 0).all()
    np.testing.assert_array_equal(allocate_samples(np.full((H, W), np.nan), np.full(P, 16), 32), 32)


def test_floor_and_cap_bound_the_target_totals():
    """σ = 0 in a corner block (no return) and one pixel with 300× the σ of the rest: the zero block's
    weight is raised to FLOOR and the hot pixel's 3 × 3 neighbourhood lowered to CAP × the mean weight,
    so their target totals differ by exactly CAP/FLOOR = 160 while the bulk stays between (1.79× the
    floor). At a budget of 400 every pixel lacks samples and gets its target within R/2. At a budget
    of 16 the floor share (3.5 samples) is below the 16 the corner has: it gets none this pass."""
    sigma = np.full((H, W), 1e-3)
    sigma[:4, :4] = 0.0
    sigma[6, 10] = 0.3
    counts = np.full(P, 16)
    alloc = allocate_samples(sigma, counts, 400)
    check_contract(alloc, 400)
    expected, target = reference_allocation(sigma, counts, 400)
    np.testing.assert_array_equal(alloc, expected)
    np.testing.assert_allclose(alloc + counts, target, atol=R / 2)
    target = target.reshape(H, W)
    assert target[6, 10] == target.max() and target[0, 0] == target.min()
    assert target.max() / target.min() == pytest.approx(CAP / FLOOR, rel=1e-12)
    np.testing.assert_allclose(target[5:8, 9:12], target.max(), rtol=1e-12)  # the whole neighbourhood is capped
    assert 1.5 < target[0, 15] / target.min() < 2.0
    assert (alloc.reshape(H, W)[:3, :3] > 0).all()
    low = allocate_samples(sigma, counts, 16).reshape(H, W)
    assert (low[:3, :3] == 0).all() and low[6, 10] > 16


# ------------------------------------------------------------------ adaptive traces
def corner():
    scene = tofcore.demo_scene("corner")
    return scene, Camera.from_fov(W, H, 70.6), dict(world_from_sensor=tofcore.suggested_pose(scene))


CORRELATIONS = [lambda tau: np.cos(2 * np.pi * 30e6 * tau)]
LEDS = [LED(position_m=(0.025, 0, 0))]


def signal_error_allocator(log=None):
    """Allocation by the standard error of each pixel's mean signal (replicate estimate)."""
    def allocate(transport, n):
        counts = allocate_samples(np.sqrt(transport.variance_of_mean()[0]), transport.sample_count, n)
        if log is not None:
            log.append((n, None if counts is None else counts.copy()))
        return counts
    return allocate


def test_adaptive_trace_is_independent_of_chunk_size_and_counts_add_up():
    """64 spp (pilot 1+1+2+4+8, then three adaptive passes of 16): the per-pixel counts are the sum of the
    allocations (n everywhere for the pilot passes), vary between pixels, average 64 within R/2, and the
    sums are the same bit for bit with chunks of about 301 paths (whole pixels, so the chunk boundaries
    move with every pass's allocation) as with one chunk."""
    scene, cam, kw = corner()
    kw = dict(kw, spp=64, max_depth=3, seed=5, correlations=CORRELATIONS, progressive=True)
    log = []
    big = trace(scene, cam, LEDS, allocate=signal_error_allocator(log), **kw)
    small = trace(scene, cam, LEDS, allocate=signal_error_allocator(), chunk_size=301, **kw)
    for name in ("sample_count", "signal_sum", "correlation_sum", "replicate_sum"):
        np.testing.assert_array_equal(getattr(big, name), getattr(small, name), err_msg=name)
    assert [n for n, _ in log] == [1, 1, 2, 4, 8, 16, 16, 16]
    assert [c is None for _, c in log] == [True] * 5 + [False] * 3
    expected = sum(np.full(P, n) if c is None else c for n, c in log)
    np.testing.assert_array_equal(big.sample_count, expected)
    assert big.sample_count.min() < 64 < big.sample_count.max()
    assert abs(big.sample_count.mean() - 64) <= R / 2
    assert (big.sample_count % R == 0).all()
    means, n = big.replicate_means()
    assert (n == n[0]).all(), "every replicate has the same number of samples in every pixel"


def test_adaptive_sampling_is_unbiased():
    """8 seeds adaptive against 8 seeds uniform, 64 spp, corner: the frame sums of the mean signal and of
    the 30 MHz correlation agree within 4 combined standard errors, over all pixels and separately over
    those the allocation favoured (more than 64 samples on average) and the rest — a bias from allocating
    by the pixels' own estimates would show up with opposite signs there. Measured: at most 2.1 SE."""
    scene, cam, kw = corner()
    kw = dict(kw, spp=64, max_depth=3, correlations=CORRELATIONS)

    def run(allocate, seeds):
        traces = [trace(scene, cam, LEDS, seed=s, allocate=allocate, **kw) for s in seeds]
        return (np.array([np.stack([t.signal(), t.correlation()[0]]) for t in traces]),
                np.mean([t.sample_count for t in traces], axis=0).reshape(H, W))

    adaptive, counts = run(signal_error_allocator(), range(8))
    uniform, _ = run(None, range(100, 108))
    favoured = counts > 64
    assert 0.2 * P < favoured.sum() < 0.8 * P
    for mask in (np.ones((H, W), bool), favoured, ~favoured):
        a, u = adaptive[:, :, mask].sum(-1), uniform[:, :, mask].sum(-1)
        z = (a.mean(0) - u.mean(0)) / np.sqrt(a.var(0, ddof=1) / len(a) + u.var(0, ddof=1) / len(u))
        assert np.all(np.abs(z) < 4.0), z
