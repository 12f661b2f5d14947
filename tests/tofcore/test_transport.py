"""The path tracer: radiometry against analytic values, path lengths, bucketing, shadows, determinism."""

import numpy as np
import pytest

import tofcore
from tofcore import LED, Ambient, Camera, ConfigError, Material, Scene
from tofcore import rng as tof_rng
from tofcore.tracer import qmc, sampler
from tofcore.constants import SPEED_OF_LIGHT_M_S
from tofcore.tracer.trace import pass_schedule, trace

C = SPEED_OF_LIGHT_M_S
RHO = 0.8
D = 2.0  # distance of the plane from the lens, metres


def lambert_plane(detail: int = 3) -> Scene:
    """A large plane z = D in the sensor frame (identity pose), facing the lens; pure Lambert (η = 1: no Fresnel)."""
    s = 4.0
    v = np.array([[-s, -s, D], [s, -s, D], [s, s, D], [-s, s, D]], np.float32)
    return Scene.from_arrays(v, [[0, 2, 1], [0, 3, 2]], materials=[Material(reflectance=RHO, roughness=0.0, ior=1.0)])


def small_camera(w=40, h=30, f=40.0, **kw) -> Camera:
    return Camera(width=w, height=h, fx=f, fy=f, cx=(w - 1) / 2, cy=(h - 1) / 2, **kw)


def tau_recorder():
    """A correlation g(τ) = τ: Σw·g / Σw is the signal-weighted mean delay of a pixel."""
    return lambda tau: tau


@pytest.mark.parametrize("led_x", [0.0, 0.025])
def test_direct_radiance_of_lambert_plane_matches_inverse_square_cosine(led_x):
    """k = 1 radiance = ρ/π · I cosθ_x / r² at every pixel (eq. 2.8, 2.14), within 0.5 %.

    The estimate is exact up to the spread of the jittered rays within a pixel: with pixels of
    2.5 mrad the radiance (∝ cos³θ) changes by < 0.2 % across a pixel even at the image edge,
    and the mean of 4 jittered samples is within a small fraction of that.
    """
    cam = small_camera(40, 30, f=400.0)
    intensity = 3.0
    t = trace(lambert_plane(), cam, [LED(position_m=(led_x, 0, 0), intensity_w_sr=intensity)],
              spp=4, max_depth=1, seed=1)
    d = cam.pixel_center_directions().astype(np.float64)
    x = d * (D / d[..., 2:3])                       # hit points on z = D
    to_led = np.array([led_x, 0, 0]) - x
    r = np.linalg.norm(to_led, axis=-1)
    cos_x = to_led[..., 2] / r * -1                 # plane normal faces −z (towards the lens)
    expected = RHO / np.pi * intensity * np.abs(cos_x) / r**2
    np.testing.assert_allclose(t.signal(), expected, rtol=5e-3)


@pytest.mark.parametrize("led_x", [0.0, 0.025])
def test_direct_path_length_is_exact(led_x):
    """With one sample per pixel, Σwτ/Σw = (|LED − x| + |x − lens|)/c for the sample's own hit point x, to 1e-9."""
    cam = small_camera(16, 12)
    key = tof_rng.seed_key(7)
    t = trace(lambert_plane(), cam, [LED(position_m=(led_x, 0, 0))], correlations=[tau_recorder()],
              spp=1, max_depth=1, seed=7)
    pixel = np.arange(cam.width * cam.height)
    sample = np.zeros_like(pixel)
    o, d = cam.generate_rays(pixel, *qmc.sample_2d(key, pixel, sample, sampler.PIXEL),
                             *qmc.sample_2d(key, pixel, sample, sampler.LENS))
    x = o + d * ((D - o[:, 2]) / d[:, 2])[:, None]
    expected = (np.linalg.norm(x - [led_x, 0, 0], axis=1) + np.linalg.norm(x - o, axis=1)) / C
    measured = (t.correlation()[0] / t.signal()).reshape(-1)
    np.testing.assert_allclose(measured, expected, rtol=1e-9)


def test_first_hit_ground_truth_on_plane():
    cam = small_camera()
    t = trace(lambert_plane(), cam, [LED()], spp=1, max_depth=1)
    d = cam.pixel_center_directions().astype(np.float64)
    np.testing.assert_allclose(t.first_hit.distance_m, D / d[..., 2], rtol=1e-6)
    np.testing.assert_allclose(t.first_hit.normal[..., 2], -1.0)
    assert (t.first_hit.object_id == 0).all() and (t.first_hit.material_id == 0).all()


def test_lambertian_led_falls_off_with_cosine():
    cam = small_camera(40, 30, f=400.0)  # narrow pixels: the per-pixel average is the centre value to < 0.2 %
    kw = dict(spp=2, max_depth=1, seed=3)
    point = trace(lambert_plane(), cam, [LED(kind="point")], **kw).signal()
    lamb = trace(lambert_plane(), cam, [LED(kind="lambertian")], **kw).signal()
    cos_axis = cam.pixel_center_directions()[..., 2]
    np.testing.assert_allclose(lamb / point, cos_axis, rtol=5e-3)


def corner_setup(w=48, h=36):
    scene = tofcore.demo_scene("corner")
    cam = Camera.from_fov(w, h, 70.0)
    return scene, cam, dict(world_from_sensor=tofcore.suggested_pose(scene))


def test_corner_has_multipath_and_partial_sums_match_shorter_traces():
    scene, cam, kw = corner_setup()
    g = [tau_recorder(), lambda tau: np.cos(2 * np.pi * 80e6 * tau)]
    leds = [LED(position_m=(0.025, 0, 0))]
    deep = trace(scene, cam, leds, correlations=g, spp=4, max_depth=5, seed=11, **kw)
    direct = trace(scene, cam, leds, correlations=g, spp=4, max_depth=1, seed=11, **kw)
    per_k = deep.signal_per_bounce()
    walls = ~np.isnan(deep.first_hit.distance_m)
    # A cosine-sampled bounce from one wall reaches the other with probability ~1/3: with 4 samples
    # most pixels get some k = 2 light.
    assert (per_k[1][walls] > 0).mean() > 0.6, "k = 2 (one interreflection) should reach most wall pixels"
    for k in range(2, 5):
        assert per_k[k][walls].sum() > 0, f"bucket k={k + 1} should not be empty"
    # Bucket k = 1 of a deep trace is bit for bit the max_depth = 1 trace (same seed).
    np.testing.assert_array_equal(direct.signal_sum[0], deep.signal_sum[0])
    np.testing.assert_array_equal(direct.correlation_sum[0], deep.correlation_sum[0])
    np.testing.assert_allclose(deep.signal(max_k=1), direct.signal())
    # Multipath travels further: its mean delay exceeds the direct one wherever both exist.
    corr = deep.correlation_per_bounce()
    both = walls & (per_k[1] > 0)
    assert (corr[1, 0][both] / per_k[1][both] > corr[0, 0][both] / per_k[0][both]).all()


def test_same_seed_same_result_whatever_the_chunk_size_and_worker_count():
    scene, cam, kw = corner_setup(24, 18)
    g = [lambda tau: np.cos(2 * np.pi * 16e6 * tau)]
    amb = Ambient(radiance_w_m2_sr=0.1)
    runs = [trace(scene, cam, [LED()], correlations=g, ambient=amb, spp=6, max_depth=3, seed=5, chunk_size=c, **kw)
            for c in (7, 1000, 1 << 16)] + [
        trace(scene, cam, [LED()], correlations=g, ambient=amb, spp=6, max_depth=3, seed=5, chunk_size=500, workers=1, **kw)]
    for other in runs[1:]:
        for key in ("signal_sum", "correlation_sum", "ambient_sum", "replicate_sum", "sample_count"):
            np.testing.assert_array_equal(getattr(other, key), getattr(runs[0], key), err_msg=key)
    different = trace(scene, cam, [LED()], correlations=g, spp=6, max_depth=3, seed=6, **kw)
    assert not np.array_equal(different.signal_sum, runs[0].signal_sum)


def test_shadow_of_box_under_offset_led():
    """LED 2.5 cm right of the lens: a band of wall left of the box gets no direct light, only multipath.

    Geometry (world x = image right): the box (x ∈ ±0.15 m, 1.2–1.5 m from the lens) hides the wall
    for |x| < 0.25 m as seen from the lens; from the LED at x = +0.025 m its shadow on the wall spans
    x ∈ [−0.267, 0.233] m. So a ~1.7 cm band x ∈ [−0.267, −0.25] is visible but unlit by the LED,
    and the right side has no visible shadow.
    Light reaches that band only after k = 3 (wall → box back face → lit wall → LED), so the
    indirect signal is summed over the strip's 20 rows × 32 samples per column.
    """
    scene = tofcore.demo_scene("box_on_wall")
    cam = Camera(width=400, height=20, fx=1000.0, fy=1000.0, cx=199.5, cy=9.5)  # ±0.2 rad strip across the box
    t = trace(scene, cam, [LED(position_m=(0.025, 0, 0))], spp=32, max_depth=3, seed=2,
              world_from_sensor=tofcore.suggested_pose(scene))
    per_k = t.signal_per_bounce()
    wall = (t.first_hit.object_id == 0).all(axis=0)             # columns that see the wall in every row
    direct = per_k[0].max(axis=0)
    indirect = per_k[1:].sum(axis=(0, 1))
    shadow = wall & (direct == 0)
    x_wall = t.first_hit.position_m[cam.height // 2, :, 0]
    assert shadow.sum() >= 6, "expected a band of shadowed wall columns"
    assert (indirect[shadow] > 0).all(), "the shadow must still receive multipath light"
    assert (x_wall[shadow] < -0.249).all() and (x_wall[shadow] > -0.268).all()
    assert (direct[wall & (np.abs(x_wall) > 0.27)] > 0).all()
    assert not (shadow & (x_wall > 0)).any(), "no shadow visible right of the box"


def test_corner_edge_has_no_gap():
    """Looking straight into the corner edge: every pixel hits a wall (no ray slips through the seam)."""
    scene, cam, kw = corner_setup(64, 48)
    t = trace(scene, cam, [LED()], spp=2, max_depth=2, seed=0, **kw)
    assert np.isfinite(t.first_hit.distance_m).all()
    assert (t.signal_per_bounce()[0] > 0).all()


def test_ambient_on_lambert_plane_is_exact():
    """Uniform background L_bg over a single Lambertian plane: reflected ambient = ρ·L_bg exactly
    (cosine sampling of a Lambertian lobe has weight ρ, and every bounce ray escapes)."""
    cam = small_camera()
    t = trace(lambert_plane(), cam, [LED()], ambient=Ambient(radiance_w_m2_sr=2.0), spp=4, max_depth=2)
    np.testing.assert_allclose(t.ambient(), RHO * 2.0, rtol=1e-12)
    assert np.max(t.variance_of_mean()[-1]) < 1e-24  # the replicates agree up to rounding


def test_environment_map_seen_directly():
    """Rays that miss everything see the environment map; Blender's equirect mapping: row 0 is the zenith."""
    env = np.zeros((8, 16), np.float32)
    env[:4] = 5.0  # upper hemisphere bright
    tiny = Scene.from_arrays(np.array([[50, 50, 50], [51, 50, 50], [50, 51, 50]], np.float32), [[0, 1, 2]])
    cam = small_camera(8, 8)
    up = tofcore.look_at((0, 0, 0), (0, 0, 1), up=(0, 1, 0))
    down = tofcore.look_at((0, 0, 0), (0, 0, -1), up=(0, 1, 0))
    amb = Ambient(environment=env)
    assert np.allclose(trace(tiny, cam, [LED()], ambient=amb, spp=1, world_from_sensor=up).ambient(), 5.0)
    assert np.allclose(trace(tiny, cam, [LED()], ambient=amb, spp=1, world_from_sensor=down).ambient(), 0.0)


def test_transient_histogram_preserves_weight_and_mean_length():
    scene, cam, kw = corner_setup(16, 12)
    t = trace(scene, cam, [LED()], correlations=[tau_recorder()], spp=2, max_depth=3,
              transient_bin_m=0.05, transient_max_m=20.0, **kw)
    hist = t.transient()
    centres = (np.arange(hist.shape[-1]) + 0.5) * 0.05
    np.testing.assert_allclose(hist.sum(-1), t.signal(), rtol=1e-9)
    np.testing.assert_allclose((hist * centres).sum(-1), t.correlation()[0] * C, rtol=1e-9)


def test_variance_of_mean_shrinks_with_samples():
    """Monte Carlo would give 16x from 4 to 64 spp; the scrambled nets of the replicates fall faster."""
    scene, cam, kw = corner_setup(16, 12)
    v4 = trace(scene, cam, [LED()], spp=4, max_depth=3, seed=1, **kw).variance_of_mean()[0]
    v64 = trace(scene, cam, [LED()], spp=64, max_depth=3, seed=1, **kw).variance_of_mean()[0]
    assert np.isfinite(v64).all() and (v64 >= 0).all()
    ratio = np.median(v4 / v64)
    assert ratio > 16, f"variance of the mean should fall at least ~16x from 4 to 64 spp, got {ratio:.1f}x"


def test_variance_of_mean_is_honest():
    """The replicate estimate matches the spread of the pixel means over independent seeds.

    40 seeds × 16 spp on the corner: the mean over seeds of the estimated variance and the variance of the
    means over seeds, pooled over 192 pixels (each side has a sampling error of ≈ √(2/39) ≈ 23 % per pixel
    and ≈ 2 % pooled), agree within 15 %.
    """
    scene, cam, kw = corner_setup(16, 12)
    runs = [trace(scene, cam, [LED()], spp=16, max_depth=3, seed=100 + s, **kw) for s in range(40)]
    means = np.stack([t.signal() for t in runs])
    estimated = np.mean([t.variance_of_mean()[0] for t in runs], axis=0)
    empirical = means.var(axis=0, ddof=1)
    ratio = estimated.sum() / empirical.sum()
    assert 0.85 < ratio < 1.15, ratio


@pytest.mark.parametrize("max_depth, gain", [(1, 50.0), (3, 1.5)])
def test_qmc_beats_independent_sampling(max_depth, gain):
    """Scrambled nets against independent uniforms, 64 spp on the corner, 12 seeds each: the variance of
    the pixel means over seeds falls by more than ``gain`` (measured 527× direct-only, 3.4× with 3
    vertices at this size; the thresholds leave room for the ≈ 40 % sampling error of 12 seeds)."""
    scene, cam, kw = corner_setup(16, 12)

    def spread(sampler):
        means = np.stack([trace(scene, cam, [LED()], spp=64, max_depth=max_depth, seed=200 + s,
                                sampler=sampler, **kw).signal() for s in range(12)])
        return means.var(axis=0, ddof=1).sum()

    assert spread("independent") / spread("sobol") > gain


def test_progressive_passes_accumulate_to_the_full_trace():
    scene, cam, kw = corner_setup(16, 12)
    counts = [int(t.sample_count[0]) for t in tofcore.trace_progressive(scene, cam, [LED()], spp=10, **kw)]
    assert counts == [1, 2, 4, 8, 10]
    assert pass_schedule(40) == [1, 1, 2, 4, 8, 16, 8]


def test_first_hit_shadow_skip_changes_nothing():
    """An LED at the centre of a pinhole sees every first hit: skipping those shadow rays is exact."""
    scene, cam, kw = corner_setup(24, 18)
    at_lens = trace(scene, cam, [LED()], spp=2, max_depth=2, seed=4, **kw)
    assert at_lens.stats.skipped_shadow_rays > 0
    nudged = trace(scene, cam, [LED(position_m=(0, 0, 1e-12))], spp=2, max_depth=2, seed=4, **kw)
    assert nudged.stats.skipped_shadow_rays == 0
    np.testing.assert_allclose(at_lens.signal_sum, nudged.signal_sum, rtol=1e-9)


@pytest.mark.parametrize("kwargs, match", [
    (dict(spp=0), "spp must be an integer >= 1, got 0"),
    (dict(max_depth=0), "max_depth must be an integer >= 1, got 0"),
    (dict(world_from_sensor=np.diag([2.0, 1, 1, 1])), "rigid transform"),
    (dict(world_from_sensor=np.eye(3)), r"4x4 matrix, got shape \(3, 3\)"),
    (dict(correlations=[1.0]), r"correlations\[0\] must be callable"),
    (dict(transient_bin_m=0.1), "transient_max_m"),
    (dict(seed=-1), "seed must be a non-negative integer"),
])
def test_bad_trace_arguments(kwargs, match):
    with pytest.raises((ConfigError, ValueError), match=match):
        trace(lambert_plane(), small_camera(4, 4), [LED()], **kwargs)


def test_trace_requires_leds():
    with pytest.raises(ConfigError, match="leds must be a non-empty sequence"):
        trace(lambert_plane(), small_camera(4, 4), [])


def test_two_leds_add_linearly():
    """Light from several LEDs adds: the trace with both equals the sum of the traces with each (next-event
    estimates sample by sample; the light vertices pick one LED per sample, so they add in expectation,
    checked in tests/tofcore/test_light_paths.py)."""
    scene, cam, kw = corner_setup(24, 18)
    a, b = LED(position_m=(0.03, 0, 0)), LED(position_m=(-0.03, 0.01, 0), kind="lambertian", intensity_w_sr=2.0)
    g = [lambda tau: np.cos(2 * np.pi * 30e6 * tau)]
    kw = dict(kw, correlations=g, spp=2, max_depth=3, seed=9, light_paths=False)
    both = trace(scene, cam, [a, b], **kw)
    ta = trace(scene, cam, [a], **kw)
    tb = trace(scene, cam, [b], **kw)
    np.testing.assert_allclose(both.signal_sum, ta.signal_sum + tb.signal_sum, rtol=1e-12)
    np.testing.assert_allclose(both.correlation_sum, ta.correlation_sum + tb.correlation_sum, rtol=1e-9, atol=1e-18)


def textured_plane(material: Material) -> Scene:
    s = 4.0
    v = np.array([[-s, -s, D], [s, -s, D], [s, s, D], [-s, s, D]], np.float32)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)  # sensor x → u, sensor y (down) → v decreasing
    return Scene.from_arrays(v, [[0, 2, 1], [0, 3, 2]], materials=[material], uvs=uv)


def test_reflectance_texture_scales_the_direct_signal():
    """Left half of the texture ρ = 0.2, right half ρ = 0.8: the direct signal of the two halves differs 4×."""
    tex = tofcore.Texture(np.repeat([[0.2] * 32 + [0.8] * 32], 4, axis=0), name="halves")  # texel 12.5 cm
    cam = small_camera(20, 10, f=10.0)  # pixels 20 cm wide on the plane; columns 8 and 11 end 20 cm from x = 0
    kw = dict(spp=1, max_depth=1)
    plain = trace(lambert_plane(), cam, [LED()], **kw).signal()
    textured = trace(textured_plane(Material(reflectance_texture=tex, roughness=0.0, ior=1.0)), cam, [LED()],
                     **kw).signal()
    ratio = textured / plain * RHO
    np.testing.assert_allclose(ratio[:, :9], 0.2, rtol=1e-6)   # image left = texture left (u < 0.5)
    np.testing.assert_allclose(ratio[:, 11:], 0.8, rtol=1e-6)


def test_normal_map_tilts_the_shading_normal():
    """A flat normal map (0.5, 0.5, 1) changes nothing; one tilted by 60° scales Lambertian light by ≈ cos 60°."""
    cam = small_camera(8, 6, f=400.0)  # near the axis: the LED direction is the plane normal to < 1°
    base = dict(roughness=0.0, ior=1.0, reflectance=RHO)
    plain = trace(lambert_plane(), cam, [LED()], spp=1, max_depth=1).signal()
    flat = tofcore.Texture(np.full((2, 2, 3), [0.5, 0.5, 1.0]), name="flat")
    tilt = np.array([np.sin(np.pi / 3), 0.0, np.cos(np.pi / 3)])
    tilted = tofcore.Texture(np.full((2, 2, 3), (tilt + 1) / 2), name="tilted")
    s_flat = trace(textured_plane(Material(normal_texture=flat, **base)), cam, [LED()], spp=1, max_depth=1).signal()
    s_tilt = trace(textured_plane(Material(normal_texture=tilted, **base)), cam, [LED()], spp=1, max_depth=1).signal()
    np.testing.assert_allclose(s_flat, plain, rtol=1e-9)
    np.testing.assert_allclose(s_tilt / plain, 0.5, rtol=0.02)


def test_memory_is_bounded_by_chunk_size_not_spp():
    """Peak traced memory of the path state does not grow with spp (chunks hold whole pixels × one pass)."""
    import tracemalloc

    scene, cam, kw = corner_setup(64, 48)  # 3072 pixels: every pass fills several chunks of 4096 rays
    scene.bvh  # build outside the measurement
    peaks = []
    for spp in (8, 64):
        tracemalloc.start()
        trace(scene, cam, [LED()], spp=spp, max_depth=3, chunk_size=4096, **kw)
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    assert peaks[1] < 1.5 * peaks[0], f"peak memory grew with spp: {peaks}"
