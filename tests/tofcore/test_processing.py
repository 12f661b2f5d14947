"""The camera's own processing (tofcore/sensor/processing.py) and the presets' depth noise against the real cameras."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import tofcore
from tofcore.sensor import decode
from tofcore.errors import ConfigError
from tofcore.sensor.modulation import Modulation, ideal_raw
from tofcore.sensor.processing import BILATERAL_KERNEL, bilateral_phasor_filter, frequency_weights

KINECT = Modulation(kind="cw_square", frequencies_hz=(80e6, 16e6, 120e6), phase_steps=(3, 3, 3),
                    exposure_s=(8e-3, 4e-3, 8e-3))


def test_bilateral_filter_divides_phase_variance_by_the_kernel_sum_of_squares():
    """On a flat phasor field with small independent noise the filter is the kernel-weighted mean:
    Var φ' / Var φ = Σk² / (Σk)² = 0.1113 (d ≈ 0 so the range term is ≈ 1); 200 × 200 pixels give
    the variance ratio to ±1 % (1 s.e.), tolerance 5 %."""
    rng = np.random.default_rng(7)
    phase = 1.0 + 0.01 * rng.standard_normal((200, 200))
    re, im = bilateral_phasor_filter(np.cos(phase), np.sin(phase))
    inner = (slice(1, -1),) * 2
    ratio = np.var(np.arctan2(im, re)[inner]) / np.var(phase[inner])
    expected = (BILATERAL_KERNEL**2).sum() / BILATERAL_KERNEL.sum() ** 2
    assert ratio == pytest.approx(expected, rel=0.05)
    np.testing.assert_array_equal(re[0], np.cos(phase[0]))  # the border passes through


def test_bilateral_filter_keeps_an_edge():
    """Across a phase step of π a neighbour's weight falls by e^{-b} = 1/32: the edge pixel's phase moves by
    less than 0.1 rad, where a plain 3 × 3 mean would cancel its phasor's 3 opposite neighbours."""
    phase = np.where(np.arange(8)[None, :] < 4, 0.5, 0.5 + np.pi) * np.ones((8, 1))
    re, im = bilateral_phasor_filter(np.cos(phase), np.sin(phase))
    assert abs(np.arctan2(im, re)[4, 3] - 0.5) < 0.1


def test_weak_neighbours_get_no_weight():
    re = np.ones((3, 3))
    re[0, 0] = -100.0  # strong and opposite: the range term alone cuts it to ~1/32 of its kernel weight
    im = np.zeros((3, 3))
    strong_only, _ = bilateral_phasor_filter(re, im, min_amplitude=200.0)  # the centre is weak: plain mean
    assert strong_only[1, 1] == pytest.approx((BILATERAL_KERNEL * re).sum())


def test_frequency_weights_sum_the_cycles_as_libfreenect2():
    w = frequency_weights((80e6, 16e6, 120e6), (2,))
    np.testing.assert_allclose(w[:, 0], [80 / 216, 16 / 216, 120 / 216])


def test_frequency_weighted_decode_is_exact_without_noise():
    """Both combinations return the true distance of consistent, noise-free phases (sine: no wiggling)."""
    mod = dataclasses.replace(KINECT, kind="cw_sine")
    d = np.array([0.6, 1.7, 3.9, 4.4])
    raw = ideal_raw(mod, d, 1000.0)
    for weights in ("inverse_variance", "frequency"):
        decoded = decode.decode(raw, mod, decode.DecodeSettings(unwrap_weights=weights))
        np.testing.assert_allclose(decoded.distance, d, atol=1e-5)


def test_bad_processing_names_the_field_and_choices():
    with pytest.raises(ConfigError, match=r"unwrap_weights must be one of \['inverse_variance', 'frequency'\], "
                                          r"got 'equal'"):
        tofcore.load_preset("kinect_v2").replace(**{"processing.unwrap_weights": "equal"})
    with pytest.raises(ConfigError, match=r"processing must be the defaults for a pulsed sensor"):
        tofcore.load_preset("xtion2").replace(**{"processing.phasor_filter": "bilateral"})


def test_render_error_estimate_follows_the_filter_on_smooth_surfaces():
    """The render's Monte Carlo error estimate, propagated through the linearised filter, matches the spread
    of 8 independent renders of the corner (two smooth walls) with and without the filter: 768 pixels × 7
    degrees of freedom pin the RMS ratio to ~2 %; measured 0.974 (filter) and 0.973 (none), bounds ±20 %."""
    base = tofcore.load_preset("kinect_v2").replace(**{"noise.model": "none", "scattering.model": "none"})
    base = dataclasses.replace(base, camera=tofcore.Camera.from_fov(32, 24, 40.0, 30.0))
    scene = tofcore.demo_scene("corner")
    for phasor_filter in ("bilateral", "none"):
        sensor = base.replace(**{"processing.phasor_filter": phasor_filter})
        frames = [tofcore.render(scene, sensor, spp=4, max_depth=3, seed=k, adaptive=False) for k in range(8)]
        spread = np.nanstd(np.stack([f.depth for f in frames]), axis=0, ddof=1)
        estimate = np.sqrt(np.nanmean(np.stack([f.render_error for f in frames]) ** 2, axis=0))
        ok = np.isfinite(spread) & np.isfinite(estimate)
        ratio = np.sqrt(np.mean(estimate[ok] ** 2) / np.mean(spread[ok] ** 2))
        assert 0.8 <= ratio <= 1.2, (phasor_filter, ratio)


# ------------------------------------------------------------------ the Kinect v2 preset against the camera
#: thesis Fig. 4.8, Kinect v2 on white paper: medians of the data in ±150 mm bins (issue 25), mm
KINECT_WHITE_MM = {1.0: 1.2, 1.5: 1.3, 2.0: 1.3, 2.5: 1.6, 3.0: 2.2, 3.5: 2.4, 4.0: 2.7}


def _plane_depth_sigma_mm(sensor: tofcore.Sensor, z_m: float, seeds: int, size: int = 16, border: int = 3) -> float:
    """Temporal σ (mm) of the depth of a white (ρ = 0.85) plane at z: RMS over the inner pixels of a
    size × size crop around the principal point of each pixel's standard deviation over ``seeds`` renders."""
    cam = sensor.camera
    x0, y0 = int(round(cam.cx)) - size // 2, int(round(cam.cy)) - size // 2
    small = dataclasses.replace(sensor, camera=dataclasses.replace(cam, width=size, height=size,
                                                                   cx=cam.cx - x0, cy=cam.cy - y0))
    v = np.array([[-5.0, -5.0, z_m], [5.0, -5.0, z_m], [5.0, 5.0, z_m], [-5.0, 5.0, z_m]])
    scene = tofcore.Scene.from_arrays(v, np.array([[0, 1, 2], [0, 2, 3]]), np.zeros(2, int),
                                      [tofcore.Material(name="white", reflectance=0.85, roughness=1.0)])
    inner = (slice(border, size - border),) * 2
    depth = np.array([tofcore.render(scene, small, np.eye(4), spp=4, max_depth=1, seed=s, adaptive=False).depth[inner]
                      for s in range(seeds)], np.float64)
    assert np.isfinite(depth).all(), f"invalid pixels at {z_m} m"
    return float(np.sqrt(np.mean(np.var(depth, axis=0, ddof=1)))) * 1000.0


def test_kinect_v2_white_depth_noise_within_25_percent_of_the_camera():
    """The preset's σ(z) on white paper stays within 25 % of the thesis's Kinect v2 at 1–4 m.

    24 seeds × 100 inner pixels: each σ is known to about ±3.5 % (1 s.e.; 23 degrees of freedom per
    pixel, the 3 × 3 filter correlating neighbours leaves ~20 independent pixels), so a preset that is
    within ~18 % passes at 2 s.e.; the seeds are fixed, so the result is reproducible. ~10 s.
    """
    sensor = tofcore.load_preset("kinect_v2")
    ratios = {z: _plane_depth_sigma_mm(sensor, z, seeds=24) / mm for z, mm in KINECT_WHITE_MM.items()}
    assert all(0.75 <= r <= 1.25 for r in ratios.values()), ratios


def test_frequency_weights_average_but_do_not_judge_the_unwrapping():
    """The Kinect's fixed weights give the low frequency, whose multipath error is the largest, 6× the weight
    it has in the agreement test: the wrap is chosen and judged with the inverse-variance weights, and only the
    output averages with the camera's. A 0.3 m multipath bias on 16 MHz alone (80 and 120 MHz agree) passes
    the d_min/16 = 78 mm tolerance — its inverse-variance residual is ≈ 33 mm, its frequency-weighted one would
    be ≈ 79 mm — and the distance is the frequency-weighted mean of the three unwrapped distances."""
    true, bias = np.array([2.0, 3.1]), np.array([0.0, 0.3, 0.0])[:, None]
    d_amb = np.asarray(KINECT.ambiguity_distances_m())[:, None]
    amplitude = np.full((3, 2), 1000.0)
    cw = decode.CwDecoding(phase=np.zeros((3, 2)), amplitude=amplitude, offset=amplitude,
                           wrapped_distance=np.mod(true[None] + bias, d_amb))
    got = decode.unwrap(cw, KINECT, weights="frequency")
    assert not got.failed.any() and (got.residual < 0.04).all()
    np.testing.assert_allclose(got.distance, true + 0.3 * 16 / 216, atol=1e-9)
