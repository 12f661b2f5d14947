"""The preview denoiser (tofcore/sensor/denoise.py): noise removed on flat regions, edges kept, invalid pixels
untouched, and only where asked for (render's ``preview_denoise``)."""

import dataclasses

import numpy as np
import pytest

import tofcore
from tofcore import Camera, load_preset, render
from tofcore.sensor.config import Noise, Scattering
from tofcore.sensor.denoise import preview_denoise

SIGMA = 0.005  # m, the "render noise" of the synthetic images


def _noisy(shape=(60, 80), seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(0.0, SIGMA, shape), np.full(shape, SIGMA)


def test_flat_region_is_smoothed_without_bias():
    """A flat wall at 2 m, Gaussian noise σ, uniform amplitude: the noise falls (the plane's three
    parameters from ~20 effective neighbours, fewer through the range term: more than 2× in standard
    deviation), the mean stays (the weights are symmetric in the noise)."""
    noise, sigma = _noisy()
    depth = 2.0 + noise
    out = preview_denoise(depth, np.full(depth.shape, 500.0), sigma)
    inner = (slice(2, -2), slice(2, -2))
    assert np.std(out[inner] - 2.0) < np.std(noise[inner]) / 2.0
    # the mean of 3,500 correlated pixels: |bias| well under σ/10
    assert abs(np.mean(out[inner]) - np.mean(depth[inner])) < SIGMA / 10


def test_a_depth_step_with_the_same_amplitude_is_kept():
    """An occluding edge (20 σ step) where the amplitude does not change: the depth range term keeps the
    two sides apart (cross weight exp(−20²/(2·2.5²·2)) ≈ 1e-7)."""
    noise, sigma = _noisy()
    truth = np.where(np.arange(80)[None, :] < 40, 2.0, 2.0 + 20 * SIGMA) * np.ones((60, 1))
    out = preview_denoise(truth + noise, np.full(truth.shape, 500.0), sigma)
    edge = (slice(2, -2), slice(38, 42))
    assert np.abs(out[edge] - truth[edge]).max() < 5 * SIGMA
    assert abs(np.mean(out[edge] - truth[edge])) < SIGMA / 5


def test_an_amplitude_edge_stops_the_averaging():
    """A 2 σ depth step (the range term alone would mix it) at a 4× amplitude edge: the guide keeps it
    (amplitude weight exp(−ln²4/(2·0.3²)) ≈ 2e-5)."""
    shape = (40, 40)
    truth = np.where(np.arange(40)[None, :] < 20, 2.0, 2.0 + 2 * SIGMA) * np.ones((40, 1))
    amplitude = np.where(np.arange(40)[None, :] < 20, 200.0, 800.0) * np.ones((40, 1))
    out = preview_denoise(truth, amplitude, np.full(shape, SIGMA))
    np.testing.assert_allclose(out, truth, atol=1e-3 * SIGMA)


def test_a_slope_with_lopsided_windows_is_kept():
    """A floor rising 1 cm per pixel with 30 % of the pixels invalid at random (lopsided windows): the local
    plane reproduces a linear depth exactly, where a weighted mean would pull each pixel towards its
    valid neighbours' side (up to ~1 cm)."""
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:40, 0:50]
    truth = 3.0 + 0.01 * x + 0.004 * y
    depth = np.where(rng.random(truth.shape) < 0.3, np.nan, truth)
    out = preview_denoise(depth, np.full(truth.shape, 500.0), np.full(truth.shape, 0.01))
    ok = np.isfinite(depth)
    np.testing.assert_allclose(out[ok], truth[ok], atol=2e-6)


def test_invalid_and_unknown_pixels():
    noise, sigma = _noisy((20, 20))
    depth = 3.0 + noise
    depth[5, 5] = np.nan                         # invalid: stays invalid, adds nothing to its neighbours
    depth[10:, :] = 9.0                           # a far region
    depth[10:, :][noise[10:, :] > 0] = np.nan
    sigma[0, 0] = np.nan                          # no error estimate yet: left as it is
    amplitude = np.full(depth.shape, 300.0)
    amplitude[3, 15] = 0.0                        # no signal: left as it is, not a neighbour
    out = preview_denoise(depth, amplitude, sigma)
    assert np.array_equal(np.isnan(out), np.isnan(depth))
    assert out[0, 0] == depth[0, 0] and out[3, 15] == depth[3, 15]
    assert np.nanmax(np.abs(out[:8] - 3.0)) < 5 * SIGMA and out.dtype == depth.dtype
    with pytest.raises(ValueError, match="radius_px must be an integer >= 1, got 0"):
        preview_denoise(depth, amplitude, sigma, radius_px=0)
    with pytest.raises(ValueError, match=r"one \(H, W\) shape, got \(20, 20\), \(20, 20\), \(3, 3\)"):
        preview_denoise(depth, amplitude, np.ones((3, 3)))


def _sensor(depth_output="radial"):
    sensor = load_preset("kinect_v2")
    return dataclasses.replace(sensor, camera=Camera.from_fov(32, 24, 60.0), noise=Noise(model="none"),
                               scattering=Scattering(model="none"), depth_output=depth_output)


@pytest.mark.parametrize("depth_output", ["radial", "z"])
def test_render_filters_only_when_asked(depth_output):
    scene, sensor = tofcore.demo_scene("box_on_wall"), _sensor(depth_output)
    plain = render(scene, sensor, spp=8, max_depth=2, seed=4)
    smooth = render(scene, sensor, spp=8, max_depth=2, seed=4, preview_denoise=True)
    assert plain.stats["preview_denoise"] is None
    assert smooth.stats["preview_denoise"]["filter"] == "joint bilateral, amplitude-guided"
    for name in ("amplitude", "gt_depth", "gt_distance", "direct_distance", "render_error", "valid"):
        assert np.array_equal(getattr(plain, name), getattr(smooth, name), equal_nan=name != "valid"), name
    assert np.array_equal(np.isnan(plain.depth), np.isnan(smooth.depth))
    assert not np.array_equal(plain.depth, smooth.depth, equal_nan=True)
    expected = preview_denoise(plain.depth, plain.amplitude, plain.render_error)
    np.testing.assert_array_equal(smooth.depth, expected)
    z = np.abs(smooth.ray_directions[..., 2]) if depth_output == "z" else 1.0
    np.testing.assert_allclose(smooth.distance * z, smooth.depth, rtol=1e-6)
    with pytest.raises(tofcore.ConfigError, match="preview_denoise must be True or False, got 'yes'"):
        render(scene, sensor, spp=1, preview_denoise="yes")
