"""Where the scene and sensor sit must not change the light transport (issue 12, class 4).

Before: a room 1e5 m from the world origin lost its geometry to float32 (7.8 mm steps) and its
multipath to a ray offset of 1.7 m (the offset scaled with the distance from the origin); a camera and
LED mounted flush with a wall left 48 % of the pixels without signal (shadow rays to an LED in the
wall plane hit the wall, the lens's own wall was hit at t = 0, light vertices at distance 0 gave
non-finite raw images). Now the scene is stored about its own origin (``Scene.origin_m``), and rays
leaving the lens or an LED, and shadow rays, are measured from where they start.
"""

import numpy as np
import pytest

import tofcore
from tofcore import LED, Camera, Scene
from tofcore.sensor.modulation import phasor_correlations
from tofcore.scene.pose import look_at
from tofcore.scene.scene import RECENTRE_BEYOND_M

ROOM = tofcore.demo_scene("room", detail=2)
CAMERA = Camera.from_fov(48, 40, 70.0, 60.0)
LEDS = [LED(position_m=(-0.025, 0.0, 0.0), kind="lambertian")]
POSE = look_at((0.0, -1.8, 1.6), (0.0, 1.0, 0.8))


def moved(scene: Scene, scale: float, offset) -> Scene:
    return Scene.from_arrays(scene.vertices.astype(np.float64) * scale + offset, scene.triangles,
                             scene.material_ids, scene.materials, object_ids=scene.object_ids)


def per_bounce(scene, pose, leds=LEDS, **kw):
    t = tofcore.trace(scene, CAMERA, leds, world_from_sensor=pose, spp=4, max_depth=3, workers=1, seed=3,
                      correlations=phasor_correlations([80e6]), **kw)
    return t, t.signal_per_bounce().reshape(3, -1).sum(axis=1)


@pytest.mark.parametrize("offset_m", [1e3, 1e4, 1e5, 1e6, -3e5])
def test_far_from_the_origin_the_room_renders_as_at_the_origin(offset_m):
    """Direct light, 2nd and 3rd bounce and the first-hit distances agree with the room at the origin
    to 1e-4 (same samples; only float rounding of the recentred vertices differs)."""
    offset = np.array([offset_m, -0.5 * offset_m, 0.25 * offset_m])
    far = moved(ROOM, 1.0, offset)
    assert np.abs(np.asarray(far.origin_m) - offset).max() < 3.0  # stored about a point near its centre
    pose = POSE.copy()
    pose[:3, 3] += offset
    t0, near_sums = per_bounce(ROOM, POSE)
    t1, far_sums = per_bounce(far, pose)
    np.testing.assert_allclose(far_sums, near_sums, rtol=1e-4)
    assert near_sums[1:].sum() / near_sums.sum() > 0.2  # there is multipath to lose
    np.testing.assert_allclose(t1.first_hit.distance_m, t0.first_hit.distance_m, rtol=0, atol=1e-6)
    # World positions come back in the world frame.
    np.testing.assert_allclose(t1.first_hit.position_m - offset, t0.first_hit.position_m, atol=0.05)


def test_recentring_only_beyond_the_threshold_and_saved_with_the_scene(tmp_path):
    assert ROOM.origin_m == (0.0, 0.0, 0.0)
    near = moved(ROOM, 1.0, np.array([0.5 * RECENTRE_BEYOND_M, 0.0, 0.0]))
    assert near.origin_m == (0.0, 0.0, 0.0)
    far = moved(ROOM, 1.0, np.array([2e5, 1e5, 0.0]))
    assert far.origin_m[0] == 2e5 and far.origin_m[1] == 1e5
    assert np.abs(far.vertices).max() < 10.0  # float32 scene-frame coordinates, µm resolution
    again = Scene.load(far.save(tmp_path / "far.npz"))
    assert again.origin_m == far.origin_m
    np.testing.assert_array_equal(again.vertices, far.vertices)


@pytest.mark.parametrize("scale", [0.01, 100.0])
def test_scaled_rooms_keep_their_multipath_share(scale):
    """A room 100× smaller (5 cm) or larger (500 m), sensor and LED scaled with it: the share of light
    after one and two bounces is that of the room (irradiance scales as 1/scale², ratios do not)."""
    leds = [LED(position_m=tuple(scale * np.array(LEDS[0].position_m)), kind="lambertian")]
    pose = POSE.copy()
    pose[:3, 3] *= scale
    _, base = per_bounce(ROOM, POSE)
    _, sums = per_bounce(moved(ROOM, scale, 0.0), pose, leds=leds)
    np.testing.assert_allclose(sums / sums.sum(), base / base.sum(), rtol=1e-3)


@pytest.mark.parametrize("light_paths", [False, True])
def test_camera_and_led_flush_with_a_wall(light_paths):
    """Lens and LED exactly in the back wall's plane (y = −2 m) give the light of a sensor 0.1 mm in
    front of it: no pixel lost, nothing non-finite."""
    sums = {}
    for y in (-2.0, -1.9999):
        pose = look_at((0.0, y, 1.6), (0.0, 1.0, 1.6))
        t, sums[y] = per_bounce(ROOM, pose, light_paths=light_paths)
        assert np.isfinite(t.correlation_sum).all() and np.isfinite(t.replicate_sum).all()
        assert (t.signal().ravel() > 0).mean() > 0.99
    np.testing.assert_allclose(sums[-2.0], sums[-1.9999], rtol=2e-3)


def test_render_flush_with_a_wall_gives_a_finite_frame():
    """The whole pipeline (noise, decoding): before, the raw images were non-finite and render raised."""
    sensor = tofcore.load_preset("kinect_v2").replace(camera=CAMERA)
    frame = tofcore.render(ROOM, sensor, look_at((0.0, -2.0, 1.6), (0.0, 1.0, 1.6)), spp=4, max_depth=2,
                           workers=1, adaptive=False)
    assert np.isfinite(frame.raw).all()
    assert frame.valid.mean() > 0.5


@pytest.mark.parametrize("origin", [{"x": 1}, [1.0, 2.0], ["a", "b", "c"], [0.0, float("nan"), 0.0]])
def test_a_bad_origin_in_a_scene_file_is_named(tmp_path, origin):
    """A hand-edited header: one SceneError naming the file and origin_m, never a TypeError."""
    import json
    import zipfile

    path = ROOM.save(tmp_path / "room.npz")
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    header = json.loads(str(arrays["header"]))
    header["origin_m"] = origin
    arrays["header"] = np.array(json.dumps(header))
    np.savez(tmp_path / "bad.npz", **arrays)
    assert zipfile.is_zipfile(tmp_path / "bad.npz")
    with pytest.raises(tofcore.errors.SceneError, match=r"bad\.npz.*origin_m must be 3 finite numbers"):
        Scene.load(tmp_path / "bad.npz")


# --------------------------------------------------------------------------- issue 23, class 4

@pytest.mark.parametrize("offset_m", [1e5, 1e6])
def test_a_far_scene_file_stored_without_recentring_is_recentred_on_load(tmp_path, offset_m):
    """A file made elsewhere: world coordinates 1e5-1e6 m out and origin_m 0 (or no key): recentred anyway."""
    offset = np.array([offset_m, -0.5 * offset_m, 0.0])
    far = Scene.from_arrays(ROOM.vertices.astype(np.float64) + offset, ROOM.triangles, ROOM.material_ids,
                            ROOM.materials, origin_m=(0.0, 0.0, 0.0))
    assert np.abs(np.asarray(far.origin_m) - offset).max() < 3.0 and np.abs(far.vertices).max() < 10.0
    path = far.save(tmp_path / "far.npz")
    again = Scene.load(path)
    assert again.origin_m == far.origin_m and np.array_equal(again.vertices, far.vertices)


@pytest.mark.parametrize("kwargs, needle", [
    ({"origin_m": (1e300, 0.0, 0.0)}, "origin_m must be 3 finite numbers (metres) within float32 range"),
    ({"vertex": 1e39}, "vertices must be within float32 range"),
])
def test_values_float32_cannot_hold_are_refused_naming_the_field(kwargs, needle):
    vertices = ROOM.vertices.astype(np.float64).copy()
    if "vertex" in kwargs:
        vertices[3, 0] = kwargs.pop("vertex")
    with pytest.raises(tofcore.SceneError) as exc:
        Scene.from_arrays(vertices, ROOM.triangles, ROOM.material_ids, ROOM.materials, **kwargs)
    assert needle in str(exc.value) and "\n" not in str(exc.value)


def _quad(x: tuple[float, float], y: tuple[float, float], z: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles spanning an axis-aligned rectangle (one of the three ranges is a single value)."""
    if x[0] == x[1]:
        corners = [(x[0], y[0], z[0]), (x[0], y[1], z[0]), (x[0], y[1], z[1]), (x[0], y[0], z[1])]
    elif y[0] == y[1]:
        corners = [(x[0], y[0], z[0]), (x[1], y[0], z[0]), (x[1], y[0], z[1]), (x[0], y[0], z[1])]
    else:
        corners = [(x[0], y[0], z[0]), (x[1], y[0], z[0]), (x[1], y[1], z[0]), (x[0], y[1], z[0])]
    return np.array(corners, np.float64), np.array([[0, 1, 2], [0, 2, 3]])


def _scene(*quads) -> Scene:
    vertices, triangles = [], []
    for v, t in quads:
        triangles.append(t + sum(len(x) for x in vertices))
        vertices.append(v)
    return Scene.from_arrays(np.concatenate(vertices), np.concatenate(triangles), name="quads")


@pytest.mark.parametrize("ground_m", [5e5, 2e6])
def test_a_huge_ground_plane_does_not_hide_a_wall_in_front_of_the_camera(ground_m):
    """A wall 2 m ahead and a ground plane 500-2000 km wide: the wall's first hits and direct light are those
    of the wall alone (before, the ray offset was 2^-16 of the scene's extent: 8-30 m, and the wall vanished).

    Within ~0.1 m of the ground the float32 triangle test of a 4000 km triangle cannot tell which of the two
    is closer (its t is off by ~0.1 m): those grazing pixels, one row here, are left out.
    """
    wall = _quad((-2.0, 2.0), (2.0, 2.0), (0.0, 2.0))
    ground = _quad((-ground_m, ground_m), (-ground_m, ground_m), (0.0, 0.0))
    pose = look_at((0.0, 0.0, 1.0), (0.0, 2.0, 1.0))
    alone, _ = per_bounce(_scene(wall), pose)
    both, _ = per_bounce(_scene(wall, ground), pose)
    on_wall = np.isfinite(alone.first_hit.distance_m) & (alone.first_hit.position_m[..., 2] > 0.25)
    assert on_wall.mean() > 0.3
    np.testing.assert_allclose(both.first_hit.distance_m[on_wall], alone.first_hit.distance_m[on_wall],
                               rtol=0, atol=1e-6)
    np.testing.assert_allclose(both.signal(max_k=1)[on_wall], alone.signal(max_k=1)[on_wall], rtol=1e-6)
    below = both.first_hit.position_m[..., 2] < 1e-3  # the pixels that see the ground, near and far
    assert below.sum() > 0 and np.isfinite(both.first_hit.distance_m[below]).all()


def test_a_camera_a_micrometre_in_front_of_a_wall_sees_it_at_every_pixel():
    """Lens and LED 1 µm from a wall 1 m from the scene frame's origin (the offset of rays leaving the lens
    is 4 float32 ulps of its coordinates: 0.48 µm here): every pixel's first hit is that wall, 1-2 µm away."""
    wall = _scene(_quad((-1.0, 1.0), (1.0, 1.0), (-1.0, 1.0)))
    t, _ = per_bounce(wall, look_at((0.0, 1.0 - 1e-6, 0.0), (0.0, 2.0, 0.0)), leds=[LED(position_m=(0.0, 0.0, 0.0))])
    distance = t.first_hit.distance_m
    assert np.isfinite(distance).all()
    assert distance.min() > 0.9e-6 and distance.max() < 2e-6
