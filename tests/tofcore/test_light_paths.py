"""Light vertices with MIS (tofcore.tracer.light_paths) and LED emission sampling (LED.power_w, emission_pdf,
sample_emission): pdfs against quadrature and histograms, and the tracer with light paths unbiased against
the tracer without them.

Statistical checks use fixed seeds; chi-square thresholds are 99.9 % quantiles, agreement of two estimates
is asked within 4 combined standard errors taken from the spread over independent seeds (a correct
estimator fails such a check with probability ≈ 6e-5 for normal errors; with 6 seeds the t distribution
with 5 degrees of freedom makes it ≈ 1 %, hence the per-check margin noted in each test).
"""

import math

import numpy as np
import pytest

import tofcore
from tofcore import LED, Camera, trace
from tofcore import rng as tof_rng
from tofcore.tracer import qmc
from tofcore.tracer.estimator import bsdf_strategy_weight
from tofcore.tracer.light_paths import led_probabilities
from tofcore.tracer.sampler import EMISSION

LEDS = [LED(kind="point", intensity_w_sr=1.7), LED(kind="lambertian", intensity_w_sr=0.6)]


def chi2_quantile_999(df: int) -> float:
    """99.9 % quantile of chi-square with ``df`` degrees of freedom (Wilson–Hilferty, < 0.5 % off for df ≥ 15)."""
    z = 3.0902
    return df * (1.0 - 2.0 / (9.0 * df) + z * math.sqrt(2.0 / (9.0 * df))) ** 3


def mu_grid(n: int = 200_000):
    """Midpoints and width of a grid on cos θ ∈ [−1, 1] (nodes symmetric about 0, so the Lambertian kink at
    cos θ = 0 falls on a cell edge and the midpoint rule is O(h²) = 1e-10 accurate)."""
    h = 2.0 / n
    return -1.0 + h * (np.arange(n) + 0.5), h


# ------------------------------------------------------------------ LED emission
@pytest.mark.parametrize("led", LEDS, ids=lambda x: x.kind)
def test_emission_pdf_integrates_to_one_and_intensity_to_power(led):
    """∫ p dω = 2π ∫ p(μ) dμ = 1 and ∫ I dω = Φ = power_w (midpoint rule in μ = cos θ, error ~1e-10)."""
    mu, h = mu_grid()
    assert 2.0 * np.pi * np.sum(led.emission_pdf(mu)) * h == pytest.approx(1.0, abs=1e-8)
    assert 2.0 * np.pi * np.sum(led.intensity(mu)) * h == pytest.approx(led.power_w, rel=1e-8)


def test_power_of_point_and_lambertian_leds():
    assert LED(kind="point", intensity_w_sr=2.0).power_w == pytest.approx(8.0 * np.pi, rel=1e-15)
    assert LED(kind="lambertian", intensity_w_sr=2.0).power_w == pytest.approx(2.0 * np.pi, rel=1e-15)
    assert LED(intensity_w_sr=0.0).power_w == 0.0


@pytest.mark.parametrize("led", LEDS, ids=lambda x: x.kind)
def test_intensity_over_pdf_is_the_power(led):
    """I(θ)/p(θ) = Φ wherever p > 0 (the light vertex weight, module docstring); p = 0 exactly where I = 0."""
    mu = np.linspace(-1.0, 1.0, 2001)
    pdf = led.emission_pdf(mu)
    intensity = led.intensity(mu)
    assert (pdf >= 0).all()
    np.testing.assert_array_equal(pdf > 0, intensity > 0)
    np.testing.assert_allclose(intensity[pdf > 0] / pdf[pdf > 0], led.power_w, rtol=1e-14)


@pytest.mark.parametrize("source", ["rng", "qmc"])
@pytest.mark.parametrize("led", LEDS, ids=lambda x: x.kind)
def test_sample_emission_follows_the_pdf(led, source):
    """2^17 directions: unit vectors; the histogram of cos θ (32 bins) against N·2π∫p dμ per bin and the
    azimuth (32 bins) against uniform pass chi-square at 99.9 % (df 31: 61.1 — Lambertian: 15 bins with
    expected counts, the other 16 must stay empty). ``qmc``: one EMISSION pair per pixel, as traced."""
    n = 1 << 17
    if source == "rng":
        u1, u2 = np.random.default_rng(5).random((2, n))
    else:
        u1, u2 = qmc.sample_2d(tof_rng.seed_key(5), np.arange(n), np.full(n, 3), EMISSION)
    d = led.sample_emission(u1, u2)
    assert d.shape == (n, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    bins = 32
    edges = np.linspace(-1.0, 1.0, bins + 1)
    counts = np.histogram(d[:, 2], edges)[0]
    mu, h = mu_grid(bins * 4096)
    expected = n * 2.0 * np.pi * (led.emission_pdf(mu) * h).reshape(bins, -1).sum(axis=1)
    assert counts.sum() == n and expected.sum() == pytest.approx(n, rel=1e-8)
    empty = expected < 1e-9
    assert (counts[empty] == 0).all(), "directions where the LED emits nothing"
    live = ~empty
    chi2 = np.sum((counts[live] - expected[live]) ** 2 / expected[live])
    assert chi2 < chi2_quantile_999(int(live.sum()) - 1), chi2
    phi = np.arctan2(d[:, 1], d[:, 0])
    counts_phi = np.histogram(phi, np.linspace(-np.pi, np.pi, bins + 1))[0]
    chi2_phi = np.sum((counts_phi - n / bins) ** 2 / (n / bins))
    assert chi2_phi < chi2_quantile_999(bins - 1), chi2_phi


def test_led_probabilities_are_proportional_to_power():
    """q_l = Φ_l / ΣΦ: point I=1 (4π W), Lambertian I=2 (2π W), a dark LED (0) → 2/3, 1/3, 0; all dark → 0."""
    q = led_probabilities([LED(intensity_w_sr=1.0), LED(kind="lambertian", intensity_w_sr=2.0),
                           LED(intensity_w_sr=0.0)])
    np.testing.assert_allclose(q, [2.0 / 3.0, 1.0 / 3.0, 0.0], rtol=1e-15)
    np.testing.assert_array_equal(led_probabilities([LED(intensity_w_sr=0.0)] * 2), [0.0, 0.0])


def test_bsdf_strategy_weight_is_the_balance_heuristic():
    """Strategy A's weight p_A / (p_A + p_B) with p_B = q p_l(θ) cosθ_y / d²; 1 after a mirror bounce or
    where neither strategy has density (and p_B = 0 behind a Lambertian LED)."""
    led = LED(kind="lambertian", intensity_w_sr=3.0)
    p_a = np.array([2.0, 2.0, 0.0, 2.0, 0.0])
    cos_axis = np.array([0.5, 0.5, 0.5, -0.5, -0.5])
    cos_geo, dist, q = 0.8, 0.4, 0.25
    delta = np.array([False, True, False, False, False])
    w = bsdf_strategy_weight(p_a, delta, led, q, cos_axis, cos_geo, dist)
    p_b = q * 0.5 / np.pi * cos_geo / dist**2
    np.testing.assert_allclose(w, [2.0 / (2.0 + p_b), 1.0, 0.0, 1.0, 1.0], rtol=1e-14)


# ------------------------------------------------------------------ the tracer with light vertices
def room():
    """The room, isotropic LED 2.5 cm beside the lens: walls and table near the LED give the fireflies that
    light vertices remove (docs/benchmarks.md)."""
    scene = tofcore.demo_scene("room")
    return scene, Camera.from_fov(24, 18, 70.6), dict(world_from_sensor=tofcore.suggested_pose(scene))


CORRELATIONS = [lambda tau: np.cos(2 * np.pi * 30e6 * tau), lambda tau: np.sin(2 * np.pi * 30e6 * tau)]
"""Phasor of 30 MHz (10 m wavelength of L): the light-vertex path lengths |x − y| + |y − l| are checked too."""


def frame_sums(scene, cam, leds, seeds, **kw):
    """(seeds, K, 1 + J) frame-summed per-sample means per bounce bucket (signal, correlations), and the traces."""
    out, traces = [], []
    for s in seeds:
        t = trace(scene, cam, leds, correlations=CORRELATIONS, seed=s, **kw)
        n = t.sample_count.astype(np.float64)
        out.append(np.concatenate([(t.signal_sum / n).sum(-1)[:, None], (t.correlation_sum / n).sum(-1)], axis=1))
        traces.append(t)
    return np.array(out), traces


def mean_and_se(x):
    return x.mean(axis=0), x.std(axis=0, ddof=1) / np.sqrt(len(x))


def test_light_paths_are_unbiased_and_reduce_variance():
    """Room, 64 spp, 3 vertices, 6 seeds each way: per bounce bucket the frame sums of the signal and of the
    30 MHz phasor agree with and without light vertices within 4 combined standard errors (measured at most
    2.3 SE over the 9 numbers, 40-seed runs agree within 2.0 SE). Bucket 1 is next-event only: the same
    to rounding. The variance of the pixel means (replicate estimate, summed over pixels, mean over seeds)
    falls by 67× with light vertices (crosscheck room: 77×, docs/benchmarks.md); asked: more than 20×.
    Sensitivity (tried by patching the tracer): light-vertex weights 5 % too large fail at 5.4 SE, their
    path lengths 0.3 m too long at 11 SE; the SE is dominated by the fireflies of the run without."""
    scene, cam, kw = room()
    kw = dict(kw, spp=64, max_depth=3)
    led = [LED(position_m=(0.025, 0, 0), kind="point")]
    with_lv, t_with = frame_sums(scene, cam, led, range(6), light_paths=True, **kw)
    without, t_without = frame_sums(scene, cam, led, range(6), light_paths=False, **kw)
    assert t_with[0].stats.light_rays == cam.width * cam.height * 64
    assert t_without[0].stats.light_rays == 0
    np.testing.assert_allclose(with_lv[:, 0], without[:, 0], rtol=1e-12)
    m1, se1 = mean_and_se(with_lv)
    m0, se0 = mean_and_se(without)
    z = (m1 - m0) / np.hypot(se1, se0)
    assert np.all(np.abs(z[1:]) < 4.0), f"light vertices vs none, in combined SE per bucket:\n{z}"
    assert m1[1, 0] > 0.5 * m1[0, 0], "the room must have substantial 2-bounce light for this test to mean much"
    var_with = np.mean([t.variance_of_mean()[0].sum() for t in t_with])
    var_without = np.mean([t.variance_of_mean()[0].sum() for t in t_without])
    assert var_without / var_with > 20.0, f"variance reduction {var_without / var_with:.1f}x"


def test_two_leds_add_in_expectation_with_light_paths():
    """Point LED + brighter Lambertian LED: each sample's light vertex comes from one LED chosen ∝ power,
    so the two-LED trace equals the sum of the single-LED traces only in expectation. Room, 32 spp, 6
    independent seeds per trace: per bounce bucket, signal and 30 MHz phasor agree within 4 combined SE
    (measured at most 0.92 SE; 1.6 SE at 64 spp). Bucket 1 (next event to every LED) adds sample by
    sample at equal seeds."""
    scene, cam, kw = room()
    kw = dict(kw, spp=32, max_depth=3, light_paths=True)
    a = LED(position_m=(0.025, 0, 0), kind="point")
    b = LED(position_m=(-0.03, 0.01, 0), kind="lambertian", intensity_w_sr=2.5)
    both, _ = frame_sums(scene, cam, [a, b], range(10, 16), **kw)
    only_a, _ = frame_sums(scene, cam, [a], range(20, 26), **kw)
    only_b, _ = frame_sums(scene, cam, [b], range(30, 36), **kw)
    (m, se), (ma, sea), (mb, seb) = mean_and_se(both), mean_and_se(only_a), mean_and_se(only_b)
    z = (m - ma - mb) / np.sqrt(se**2 + sea**2 + seb**2)
    assert np.all(np.abs(z) < 4.0), f"two LEDs vs the sum of one each, in combined SE:\n{z}"
    same_seed = [trace(scene, cam, leds, seed=3, **kw).signal_sum[0] for leds in ([a, b], [a], [b])]
    np.testing.assert_allclose(same_seed[0], same_seed[1] + same_seed[2], rtol=1e-12)


def test_max_depth_one_ignores_light_paths():
    """Light vertices connect camera vertices to a second surface vertex: with one vertex they do nothing,
    not even a light ray; the sums are equal bit for bit."""
    scene, cam, kw = room()
    kw = dict(kw, spp=8, max_depth=1, seed=11, correlations=CORRELATIONS)
    led = [LED(position_m=(0.025, 0, 0))]
    on, off = trace(scene, cam, led, light_paths=True, **kw), trace(scene, cam, led, light_paths=False, **kw)
    assert on.stats.light_rays == 0
    for name in ("signal_sum", "correlation_sum", "replicate_sum"):
        np.testing.assert_array_equal(getattr(on, name), getattr(off, name))


def test_dark_leds_trace_no_light_vertices():
    """All LEDs dark (ΣΦ = 0): no LED can be chosen; the tracer falls back to next-event only (zero signal)."""
    scene, cam, kw = room()
    t = trace(scene, cam, [LED(intensity_w_sr=0.0)], spp=4, max_depth=2, seed=1, **kw)
    assert t.stats.light_rays == 0
    assert np.all(t.signal_sum == 0)
