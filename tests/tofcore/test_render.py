"""render(): raw images, decoding, ground truth, per-k decomposition, stop rules, plan skips."""

import dataclasses

import numpy as np
import pytest

import tofcore
from tofcore import Ambient, Camera, ConfigError
from tofcore.sensor.modulation import Modulation
from tofcore.sensor.presets import load_preset
from tofcore.render import render
from tofcore.sensor.config import Noise, Scattering


def small(sensor, w=32, h=24, hfov=60.0, **changes):
    """The sensor at a small resolution (tests run in seconds), with optional field changes."""
    return dataclasses.replace(sensor, camera=Camera.from_fov(w, h, hfov), **changes)


def clean(sensor):
    """Noise and scattering off."""
    return dataclasses.replace(sensor, noise=Noise(model="none"), scattering=Scattering(model="none"))


SINE_16 = Modulation(kind="cw_sine", frequencies_hz=(16e6,), exposure_s=(8e-3,))  # unambiguous to 9.4 m


def test_plane_direct_distance_equals_ground_truth_for_a_sine_sensor():
    """No multipath (a plane), no noise, sine modulation (no systematic error): decoded = first-hit distance."""
    # A narrow field of view: the distance varies by < 1 mm across a pixel's footprint, so the decoded
    # (footprint-averaged) distance must match the pixel-centre ground truth to 1 mm. The LED sits at the
    # lens: an LED offset b changes the half round trip by about b·sinθ/2 (1 mm for 2.5 cm at 5°).
    sensor = small(clean(load_preset("kinect_v2")), hfov=10.0, modulation=SINE_16, range_m=(0.1, 9.0),
                   leds=(tofcore.LED(intensity_w_sr=1.0),))
    frame = render(tofcore.demo_scene("plane"), sensor, spp=4, max_depth=2, seed=0)
    assert frame.valid.all()
    np.testing.assert_allclose(frame.distance, frame.gt_distance, atol=1e-3)
    np.testing.assert_allclose(frame.direct_distance, frame.gt_distance, atol=1e-3)


def test_frame_fields_and_depth_output():
    sensor = small(load_preset("kinect_v2"), depth_output="z")
    frame = render(tofcore.demo_scene("corner"), sensor, spp=2, max_depth=3, seed=1)
    h, w = 24, 32
    for name in ("depth", "distance", "amplitude", "intensity", "offset", "gt_distance", "gt_depth",
                 "direct_distance", "confidence"):
        assert getattr(frame, name).shape == (h, w), name
    assert frame.raw.shape == (9, h, w) and len(frame.raw_labels) == 9
    assert frame.distance_per_k.shape == (3, h, w)
    np.testing.assert_allclose(frame.depth, frame.distance * frame.ray_directions[..., 2], rtol=1e-6)
    np.testing.assert_allclose(frame.gt_depth, frame.gt_distance * frame.ray_directions[..., 2], rtol=1e-6)
    assert np.isnan(frame.depth[~frame.valid]).all() and np.isfinite(frame.depth[frame.valid]).all()
    pts = frame.points()
    assert pts.shape == (frame.valid.sum(), 3)
    stats = frame.stats
    assert stats["spp"] == 2 and stats["plan"]["bounces"] and len(stats["convergence"]) == 1  # one pass of 2


def test_multipath_in_the_corner_makes_depth_too_far():
    """Interreflections arrive later: the full distance exceeds the direct-only one (thesis §6.3)."""
    sensor = small(clean(load_preset("kinect_v2")), modulation=SINE_16, range_m=(0.1, 9.0))
    frame = render(tofcore.demo_scene("corner"), sensor, spp=16, max_depth=4, seed=2)
    mpi = frame.distance - frame.direct_distance
    assert np.nanmedian(mpi) > 0.005
    # Partial sums over k grow towards the full result.
    per_k = np.nanmedian(frame.distance_per_k - frame.direct_distance, axis=(1, 2))
    assert per_k[0] == 0 and (np.diff(per_k) >= 0).all()


def test_target_error_stops_early_and_is_met():
    sensor = small(load_preset("kinect_v2"))
    frame = render(tofcore.demo_scene("corner"), sensor, spp=256, max_depth=3, target_error_m=0.02, seed=0)
    log = frame.stats["convergence"]
    assert frame.stats["spp"] < 256
    assert log[-1]["est_depth_error_m"] <= 0.02
    assert all(r["est_depth_error_m"] > 0.02 for r in log[:-1] if r["est_depth_error_m"] is not None)


def test_estimated_error_matches_the_spread_between_seeds():
    """The Monte Carlo standard error estimate agrees with the actual spread of independent renders."""
    sensor = small(clean(load_preset("kinect_v2")), modulation=SINE_16, range_m=(0.1, 9.0))
    scene = tofcore.demo_scene("corner")
    frames = [render(scene, sensor, spp=16, max_depth=3, seed=s) for s in range(6)]
    spread = np.nanstd(np.stack([f.distance for f in frames]), axis=0, ddof=1)
    estimate = frames[0].stats["convergence"][-1]["est_depth_error_m"]
    actual = float(np.sqrt(np.nanmean(spread**2)))
    # Six renders estimate a standard deviation to about ±30 %; the delta method is first order.
    assert 0.6 < estimate / actual < 1.6, (estimate, actual)


def test_reference_error_is_logged():
    sensor = small(clean(load_preset("kinect_v2")))
    scene = tofcore.demo_scene("corner")
    reference = render(scene, sensor, spp=8, max_depth=3, seed=9).distance
    frame = render(scene, sensor, spp=4, max_depth=3, seed=1, reference_distance=reference)
    assert all("rms_error_m" in r for r in frame.stats["convergence"])
    with pytest.raises(ConfigError, match="reference_distance must have shape"):
        render(scene, sensor, spp=1, reference_distance=np.zeros((3, 3)))


def test_same_seed_same_frame():
    sensor = small(load_preset("kinect_v2"))
    scene = tofcore.demo_scene("box_on_wall")
    a, b = (render(scene, sensor, spp=2, max_depth=2, seed=4) for _ in range(2))
    np.testing.assert_array_equal(a.raw, b.raw)
    np.testing.assert_array_equal(a.depth, b.depth)


@pytest.mark.parametrize("preset", ["kinect_v2", "o3d303", "xtion2"])
def test_every_preset_renders(preset):
    sensor = small(load_preset(preset))
    frame = render(tofcore.demo_scene("box_on_wall"), sensor, spp=2, max_depth=2, seed=0)
    assert frame.valid.mean() > 0.8, np.bincount(frame.reason.ravel())
    err = np.abs(frame.depth - frame.gt_depth)[frame.valid]
    assert np.median(err) < 0.2


# --- plan: every skip leaves the output unchanged ------------------------------------------------------

def test_skip_ambient_changes_nothing():
    sensor = small(clean(load_preset("kinect_v2")))
    scene = tofcore.demo_scene("corner")
    skipped = render(scene, sensor, spp=2, max_depth=2, seed=3, ambient=None)
    black = render(scene, sensor, spp=2, max_depth=2, seed=3, ambient=Ambient(radiance_w_m2_sr=0.0))
    assert not skipped.stats["plan"]["ambient"] and not black.stats["plan"]["ambient"]
    np.testing.assert_array_equal(skipped.raw, black.raw)


def test_skip_scattering_changes_nothing():
    """Strength 0 (skipped) equals an explicit identity PSF."""
    from tofcore.sensor import optics

    raw = np.random.default_rng(0).random((3, 10, 12))
    np.testing.assert_allclose(optics.apply_scattering(raw, optics.psf_kernel("airy", strength=0.0, radius_px=2.0)),
                               raw, rtol=0, atol=1e-12)
    sensor = small(load_preset("kinect_v2"), scattering=Scattering(model="airy", strength=0.0, radius_px=2.0))
    frame = render(tofcore.demo_scene("corner"), sensor, spp=1, max_depth=1)
    assert not frame.stats["plan"]["scattering"]


def test_skip_conductor_fresnel_changes_nothing():
    from tofcore.scene.bsdf import SurfaceParams, specular_fresnel
    from tofcore.scene.fresnel import fresnel_conductor, fresnel_dielectric

    cos = np.linspace(0, 1, 50)
    params = SurfaceParams(reflectance=0.5, roughness=0.3, metallic=np.zeros(50), ior=1.5, extinction=2.0)
    full = 1.0 * fresnel_dielectric(cos, 1.5) + 0.0 * fresnel_conductor(cos, 1.5, 2.0)
    np.testing.assert_array_equal(specular_fresnel(params, cos), full)
    metal = dataclasses.replace(params, metallic=np.ones(50))
    np.testing.assert_array_equal(specular_fresnel(metal, cos), fresnel_conductor(cos, 1.5, 2.0))


def test_skip_textures_changes_nothing():
    """A constant texture gives the same frame as the scalar material it replaces (lookups skipped)."""
    from tofcore import Material, Scene, Texture

    v = np.array([[-4, 2, -3], [4, 2, -3], [4, 2, 3], [-4, 2, 3]], np.float32)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    tris = [[0, 1, 2], [0, 2, 3]]
    plain = Scene.from_arrays(v, tris, materials=[Material(reflectance=0.6)], uvs=uv)
    textured = Scene.from_arrays(v, tris, uvs=uv, materials=[
        Material(reflectance=0.1, reflectance_texture=Texture(np.full((4, 4), 0.6, np.float32)))])
    pose = tofcore.look_at((0, 0, 0), (0, 1, 0))
    sensor = small(clean(load_preset("kinect_v2")))
    a = render(plain, sensor, pose, spp=1, max_depth=1)
    b = render(textured, sensor, pose, spp=1, max_depth=1)
    assert not a.stats["plan"]["textures"] and b.stats["plan"]["textures"]
    np.testing.assert_allclose(a.raw, b.raw, rtol=1e-6)


def test_bad_render_settings():
    sensor = small(load_preset("kinect_v2"))
    scene = tofcore.demo_scene("plane")
    with pytest.raises(ConfigError, match="spp must be an integer >= 1, got 0"):
        render(scene, sensor, spp=0)
    with pytest.raises(ConfigError, match="time_budget_s must be a number > 0, got -1"):
        render(scene, sensor, time_budget_s=-1)
    with pytest.raises(ConfigError, match="target_error_m must be a number > 0"):
        render(scene, sensor, target_error_m=float("nan"))


def test_progressive_frames_and_cancel():
    sensor = small(load_preset("kinect_v2"))
    scene = tofcore.demo_scene("corner")
    frames = list(tofcore.render_progressive(scene, sensor, spp=4, max_depth=2, seed=0))
    assert [f.stats["spp"] for f in frames] == [1, 2, 4]
    assert [f.stats["final"] for f in frames] == [False, False, True]
    assert not np.array_equal(frames[0].raw, frames[-1].raw)
    np.testing.assert_array_equal(frames[-1].depth, render(scene, sensor, spp=4, max_depth=2, seed=0).depth)
    calls = []
    with pytest.raises(tofcore.Cancelled):
        render(scene, sensor, spp=64, max_depth=2, cancel=lambda: calls.append(1) or len(calls) > 3)


def test_preview_frames_skip_only_the_per_k_decodes(tmp_path):
    """preview_frames=True: the frames before the final one lack direct_distance and distance_per_k and are
    otherwise the same frames bit for bit; the final frame is complete; a preview frame is not written."""
    sensor = small(load_preset("kinect_v2"))
    scene = tofcore.demo_scene("corner")
    full = list(tofcore.render_progressive(scene, sensor, spp=4, max_depth=3, seed=2))
    preview = list(tofcore.render_progressive(scene, sensor, spp=4, max_depth=3, seed=2, preview_frames=True))
    assert len(full) == len(preview) == 3
    for a, b in zip(full, preview):
        final = b.stats["final"]
        assert (b.distance_per_k is None and b.direct_distance is None) == (not final)
        for name in ("depth", "distance", "amplitude", "offset", "intensity", "reason", "confidence", "raw",
                     "gt_depth", "render_error", "samples") + (("distance_per_k", "direct_distance") if final else ()):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert preview[-1].distance_per_k.shape == (3, sensor.camera.height, sensor.camera.width)
    with pytest.raises(ValueError, match="preview frame .* write the final frame"):
        tofcore.write_frame(preview[0], tmp_path / "out", "json")
    assert not (tmp_path / "out").exists()
    with pytest.raises(ConfigError, match="preview_frames must be True or False"):
        next(tofcore.render_progressive(scene, sensor, spp=1, preview_frames="yes"))


def test_estimated_error_includes_ambient_noise_for_pulsed_sensors():
    """Ambient light does not cancel in the 2-bucket ratio: its Monte Carlo noise must enter the estimate."""
    sensor = small(clean(load_preset("xtion2")), hfov=40.0)
    scene = tofcore.demo_scene("box_on_wall")
    env = np.ones((8, 16), np.float32) * np.linspace(0.2, 3.0, 8)[:, None].astype(np.float32)
    amb = Ambient(environment=env)
    frames = [render(scene, sensor, spp=16, max_depth=2, seed=s, ambient=amb) for s in range(6)]
    spread = np.nanstd(np.stack([f.distance for f in frames]), axis=0, ddof=1)
    estimate = frames[0].stats["convergence"][-1]["est_depth_error_m"]
    actual = float(np.sqrt(np.nanmean(spread**2)))
    assert 0.5 < estimate / actual < 2.0, (estimate, actual)


def test_transient_histogram_changes_nothing_and_centres_on_the_round_trip():
    """The histogram is an extra output: the frame is the same bit for bit with and without it. Direct light only
    (max_depth 1), the LED at the lens, 1 cm bins: every path is lens → first hit → lens, so each pixel's
    radiance-weighted mean bin centre is 2 × the pixel's ray length within half a bin (the footprint of a
    narrow 10° pixel grid on the plane varies by < 1 mm) and the bins sum to the pixel's mean radiance."""
    sensor = small(clean(load_preset("kinect_v2")), hfov=10.0, leds=(tofcore.LED(intensity_w_sr=1.0),))
    scene = tofcore.demo_scene("plane")
    plain = render(scene, sensor, spp=2, max_depth=1, seed=3)
    frame = render(scene, sensor, spp=2, max_depth=1, seed=3, transient_bin_m=0.01, transient_max_m=8.0)
    for name in ("depth", "amplitude", "raw", "gt_distance"):
        np.testing.assert_array_equal(getattr(frame, name), getattr(plain, name))
    assert plain.transient is None and frame.transient.shape == (24, 32, 800) and frame.transient_bin_m == 0.01
    centres = (np.arange(800) + 0.5) * 0.01
    mean_length = (frame.transient * centres).sum(-1) / frame.transient.sum(-1)
    np.testing.assert_allclose(mean_length, 2 * frame.gt_distance, atol=0.005 + 0.001)


def test_the_object_table_names_every_object_id():
    scene = tofcore.demo_scene("room")
    frame = render(scene, small(load_preset("kinect_v2")), spp=1, max_depth=1)
    table = frame.metadata["objects"]
    assert [o["id"] for o in table] == list(range(len(scene.object_names)))
    assert [o["name"] for o in table] == list(scene.object_names)
    assert {m for o in table for m in o["materials"]} == {m.name for m in scene.materials}
    assert set(np.unique(frame.object_id[frame.object_id >= 0]).tolist()) <= {o["id"] for o in table}


def _lone_cube_kinect(snr: float | None = None):
    """Blender's default scene as the add-on exports it: a 2 m cube at the origin, nothing behind it, the
    default world's grey (0.0509) as ambient light; Kinect v2 at 128 × 106 from (2.6, −2.6, 2), 8 spp."""
    from tofcore.scene.demo import _Builder
    b = _Builder(1)
    b.box((-1, -1, -1), (1, 1, 1), 0, "Cube")
    scene = tofcore.Scene(vertices=np.concatenate(b.vertices), triangles=np.concatenate(b.triangles),
                          material_ids=np.concatenate(b.materials), object_ids=np.concatenate(b.objects),
                          materials=(tofcore.Material(),), object_names=tuple(b.object_names))
    sensor = load_preset("kinect_v2").resized(128, 106)
    if snr is not None:
        sensor = sensor.replace(**{"invalid.min_amplitude_snr": snr})
    pose = tofcore.look_at(np.array([2.6, -2.6, 2.0]), np.zeros(3))
    return sensor, render(scene, sensor, pose, spp=8, max_depth=3, seed=0, workers=1,
                          ambient=Ambient(radiance_w_m2_sr=0.0509))


def test_no_valid_speckles_where_no_surface_is():
    """Pixels whose rays hit nothing see only ambient light: their amplitude is noise, Rayleigh(σ_A), and
    the Kinect v2's 3 σ_A threshold passes exp(−4.5) = 1.1 % of them per frequency; libfreenect2 asks it of
    all three frequencies (1.4e-6), then the dealiasing, range and edge tests (issue 34: ≤ 0.01 % of the
    empty pixels; none here but a rim pixel that partly sees the cube). The cube stays valid (92 % here, the rest low amplitude at its dim faces and
    the edge filter at its rim)."""
    sensor, frame = _lone_cube_kinect()
    empty = ~np.isfinite(frame.gt_distance)
    assert 5000 < empty.sum() < 12000 and sensor.invalid.min_amplitude_snr == 3.0
    # none, bar a rim pixel whose centre misses but whose area sees the cube: within 0.3 m of a neighbour's
    rim = np.argwhere(frame.valid & empty)
    assert len(rim) <= 2
    for y, x in rim:
        around = frame.gt_depth[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2]
        assert np.nanmin(np.abs(around - frame.depth[y, x])) <= 0.3
    assert frame.valid[~empty].mean() >= 0.9
    _, fixed_only = _lone_cube_kinect(snr=0.0)  # the fixed 50 e- threshold alone lets speckles through
    assert fixed_only.valid[empty].mean() > 0.001
