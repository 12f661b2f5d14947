"""Add-on registration, "Add ToF Camera", "Render ToF" (background mode), the live preview and the reports.

Runs in the PyPI ``bpy`` module: timers never fire and there is no window
event loop, so the modal path is exercised through its parts (the worker
thread's :class:`RenderJob`, :func:`_apply_pass`) and the live preview
through its handler and scheduling functions.
"""

from __future__ import annotations

import math
import os
import re
import sys
import time
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository root: `import addon`

import tofcore  # noqa: E402

import addon  # noqa: E402
from addon_helpers import Reports  # noqa: E402
from addon import images, mapping, operators, sensors  # noqa: E402

#: Every file write_frame produces with all formats.
EXPECTED_FILES = {"frame.exr", "depth.exr", "depth_mm.png", "ir.png", "depth.png", "intensity.png", "error.png",
                  "reason.png", "convergence.png", "points.ply", "camera_opencv.yml", "camera_info.yaml",
                  "camera.json", "frame.json"}
BLENDER_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


# --------------------------------------------------------------------------- fixtures and helpers

@pytest.fixture
def tof(clean_bpy):
    """The add-on registered into a factory-empty scene; unregistered afterwards."""
    addon.register()
    yield clean_bpy
    addon.unregister()


def _link(obj):
    bpy.context.scene.collection.objects.link(obj)
    return obj


def add_mesh(name: str, vertices, faces, location=(0.0, 0.0, 0.0)):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(vertices, [], faces)
    mesh.update()
    obj = _link(bpy.data.objects.new(name, mesh))
    obj.location = location
    return obj


def add_plane_and_cube():
    """A 4 m floor and a 0.5 m cube standing on it at the origin."""
    add_mesh("Floor", [(-2, -2, 0), (2, -2, 0), (2, 2, 0), (-2, 2, 0)], [(0, 1, 2, 3)])
    h = 0.25
    corners = [(x, y, z) for z in (-h, h) for y in (-h, h) for x in (-h, h)]
    faces = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    return add_mesh("Cube", corners, faces, location=(0.0, 0.0, h))


def add_tof_camera(preset: str = "kinect_v2", *, width: int = 32, height: int = 24, spp: int = 2,
                   max_depth: int = 2, output_dir: str = ""):
    """"Add ToF Camera" 2 m in front of the origin, looking at it from 1.2 m up; small, fast settings."""
    assert bpy.ops.tof.add_camera(preset=preset, location=(0.0, -2.0, 1.2),
                                  rotation=(math.radians(60.0), 0.0, 0.0)) == {'FINISHED'}
    camera = bpy.context.scene.camera
    settings = camera.data.tof
    settings.use_resolution = True
    settings.width, settings.height = width, height
    settings.spp, settings.max_depth = spp, max_depth
    settings.output_dir = output_dir
    return camera


def snapshot() -> dict[str, np.ndarray]:
    """Pixels of the four ToF images (row 0 at the top)."""
    return {name: images.read_pixels(bpy.data.images[name]).copy() for name in images.IMAGE_NAMES.values()}




# --------------------------------------------------------------------------- registration

def _menu_draws(menu) -> list:
    return [getattr(f, "__name__", "") for f in menu._dyn_ui_initialize()]


def test_register_unregister_twice(clean_bpy):
    for _ in range(2):
        addon.register()
        assert hasattr(bpy.types.Camera, "tof") and hasattr(bpy.types.Material, "tof")
        assert all(cls.is_registered for cls in addon.classes)
        assert hasattr(bpy.ops.tof, "render") and bpy.ops.tof.render.get_rna_type() is not None
        assert _menu_draws(bpy.types.VIEW3D_MT_add).count("draw_add_menu") == 1
        assert operators._on_load_post in bpy.app.handlers.load_post
        addon.unregister()
        assert not hasattr(bpy.types.Camera, "tof") and not hasattr(bpy.types.Material, "tof")
        assert not any(cls.is_registered for cls in addon.classes)
        assert "draw_add_menu" not in _menu_draws(bpy.types.VIEW3D_MT_add)
        assert operators._on_load_post not in bpy.app.handlers.load_post
        assert not operators.preview_handler_registered()


def test_register_when_registered_starts_over(clean_bpy):
    addon.register()
    addon.register()
    assert _menu_draws(bpy.types.VIEW3D_MT_add).count("draw_add_menu") == 1
    assert sum(h is operators._on_load_post for h in bpy.app.handlers.load_post) == 1
    addon.unregister()
    assert not hasattr(bpy.types.Camera, "tof")


# --------------------------------------------------------------------------- Add ToF Camera

@pytest.mark.parametrize("preset", tofcore.list_presets())
def test_add_camera_matches_preset(tof, preset):
    sensor = tofcore.load_preset(preset)
    assert bpy.ops.tof.add_camera(preset=preset, location=(1.0, -2.0, 0.5),
                                  rotation=(1.2, 0.1, 0.4)) == {'FINISHED'}
    scene = bpy.context.scene
    camera = scene.camera
    assert camera is not None and camera.type == 'CAMERA'
    assert camera.data.tof.enabled and camera.data.tof.preset == preset
    render = scene.render
    assert (render.resolution_x, render.resolution_y, render.resolution_percentage) == \
        (sensor.camera.width, sensor.camera.height, 100)
    # Blender's camera reproduces the preset's pinhole intrinsics.
    cam = camera.data
    got = mapping.intrinsics_from_blender_camera(
        lens_mm=cam.lens, sensor_width_mm=cam.sensor_width, sensor_height_mm=cam.sensor_height,
        sensor_fit=cam.sensor_fit, shift_x=cam.shift_x, shift_y=cam.shift_y,
        resolution_x=render.resolution_x, resolution_y=render.resolution_y,
        pixel_aspect_x=render.pixel_aspect_x, pixel_aspect_y=render.pixel_aspect_y)
    for key in ("fx", "fy", "cx", "cy"):
        assert got[key] == pytest.approx(getattr(sensor.camera, key), rel=1e-5, abs=1e-4), key
    # ... and projects like it: world points seen through pixels land on the same pixels in Blender.
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    from addon import export
    bpy.context.view_layer.update()
    c = sensor.camera
    world_from_sensor = export.camera_pose(camera)
    rng = np.random.default_rng(1)
    u, v, z = rng.uniform(-0.5, c.width - 0.5, 50), rng.uniform(-0.5, c.height - 0.5, 50), rng.uniform(0.5, 9, 50)
    points = np.column_stack([(u - c.cx) / c.fx * z, (v - c.cy) / c.fy * z, z]) @ world_from_sensor[:3, :3].T \
        + world_from_sensor[:3, 3]
    ndc = np.array([tuple(world_to_camera_view(scene, camera, Vector(p))) for p in points])
    np.testing.assert_allclose(ndc[:, 0] * c.width - 0.5, u, atol=0.5)
    np.testing.assert_allclose((1.0 - ndc[:, 1]) * c.height - 0.5, v, atol=0.5)
    # One small sphere empty per LED, at matrix_world @ diag(1, -1, -1, 1) @ position.
    bpy.context.view_layer.update()
    leds = operators.led_empties(camera)
    assert [e.name for e in leds] == [f"LED {i}" for i in range(1, len(sensor.leds) + 1)]
    world_from_sensor = np.array(camera.matrix_world) @ BLENDER_FROM_OPENCV
    for empty, led in zip(leds, sensor.leds):
        assert empty.parent == camera and empty.type == 'EMPTY'
        assert empty.empty_display_type == 'SPHERE' and empty.empty_display_size <= 0.01
        expected = world_from_sensor @ np.array([*led.position_m, 1.0])
        np.testing.assert_allclose(np.array(empty.matrix_world.translation), expected[:3], atol=1e-6)


def test_changing_preset_and_led_override_update_camera(tof):
    add_tof_camera("kinect_v2")
    camera = bpy.context.scene.camera
    settings = camera.data.tof
    settings.use_resolution = False
    settings.preset = "o3d303"
    assert (bpy.context.scene.render.resolution_x, bpy.context.scene.render.resolution_y) == (352, 264)
    assert len(operators.led_empties(camera)) == 4
    settings.use_led_override = True
    settings.led_spread = 0.0
    settings.led_offset_m = (0.01, 0.02, 0.0)
    for empty in operators.led_empties(camera):  # Blender local frame: (x, -y, -z)
        np.testing.assert_allclose(np.array(empty.location), (0.01, -0.02, 0.0), atol=1e-7)
    settings.preset = "kinect_v2"
    assert len(operators.led_empties(camera)) == 1
    settings.enabled = False
    assert operators.led_empties(camera) == []


# --------------------------------------------------------------------------- settings → sensor

def test_sensor_from_settings_applies_overrides(tof):
    add_tof_camera("kinect_v2", width=128, height=106)
    settings = bpy.context.scene.camera.data.tof
    settings.noise_model = 'none'
    settings.use_scattering = False
    settings.depth_output = 'radial'
    settings.use_range_m = True
    settings.range_m = (0.2, 3.0)
    preset = tofcore.load_preset("kinect_v2")
    sensor = sensors.sensor_from_settings(settings)
    cam = sensor.camera
    assert (cam.width, cam.height) == (128, 106)
    assert cam.fx / cam.width == pytest.approx(preset.camera.fx / preset.camera.width)  # same field of view
    assert (cam.cx + 0.5) / cam.width == pytest.approx((preset.camera.cx + 0.5) / preset.camera.width)
    assert sensor.noise.model == "none" and sensor.scattering.model == "none"
    assert sensor.depth_output == "radial" and sensor.range_m == pytest.approx((0.2, 3.0))
    preview = sensors.sensor_from_settings(settings, scale=0.25)
    assert (preview.camera.width, preview.camera.height) == (32, 26)


def test_images_orientation_and_nan():
    depth = np.array([[1.0, np.nan], [2.0, 3.0], [4.0, 5.0]], dtype=np.float32)  # 3 rows, 2 columns
    rgba, limits = images.depth_rgba(depth)
    assert rgba.shape == (3, 2, 4) and limits == {"min_m": 1.0, "max_m": 5.0}
    assert rgba[0, 1].tolist() == [0.0, 0.0, 0.0, 0.0]          # NaN: transparent black
    assert (rgba[..., 3][np.isfinite(depth)] == 1.0).all()
    error, limits = images.error_rgba(depth, depth + 0.002)
    assert limits["limit_m"] == pytest.approx(0.002, rel=1e-4)
    np.testing.assert_allclose(error[1, 0, :3], images._BLUE, atol=1e-6)  # nearer than the truth: blue


def test_set_pixels_rows_bottom_up(tof):
    rgba = np.zeros((3, 2, 4), dtype=np.float32)
    rgba[0, 0] = (1.0, 0.0, 0.0, 1.0)   # top-left red
    rgba[2, 0] = (0.0, 0.0, 1.0, 1.0)   # bottom-left blue
    image = images._image("ToF Test", 2, 3)
    images.set_pixels(image, rgba)
    assert list(image.pixels[:4]) == [0.0, 0.0, 1.0, 1.0]   # Blender's first pixel is the bottom-left one
    np.testing.assert_array_equal(images.read_pixels(image), rgba)


# --------------------------------------------------------------------------- Render ToF

def test_render_background_writes_files_and_images(tof, tmp_path, monkeypatch):
    add_plane_and_cube()
    out = tmp_path / "tof"
    add_tof_camera("kinect_v2", spp=4, output_dir=str(out))
    passes = []
    original = operators._apply_pass

    def recording(frame):
        original(frame)
        passes.append((frame.stats["spp"], snapshot()))

    monkeypatch.setattr(operators, "_apply_pass", recording)
    assert bpy.ops.tof.render('INVOKE_DEFAULT') == {'FINISHED'}   # background: invoke runs execute()

    assert set(os.listdir(out)) == EXPECTED_FILES                  # and no temporary files
    # One image update per progressive pass (1, 2, 4 spp), the images change between passes.
    assert [spp for spp, _ in passes] == [1, 2, 4]
    for name in images.IMAGE_NAMES.values():
        image = bpy.data.images[name]
        assert tuple(image.size) == (32, 24)
        assert not np.array_equal(passes[0][1][name], passes[-1][1][name]), name
        np.testing.assert_array_equal(images.read_pixels(image), passes[-1][1][name])
    # The depth image is the written frame, the right way up: opaque exactly where the depth is valid.
    depth = tofcore.read_exr(out / "frame.exr")["depth"]
    alpha = images.read_pixels(bpy.data.images["ToF Depth"])[..., 3]
    assert 0 < np.isfinite(depth).sum() < depth.size
    np.testing.assert_array_equal(alpha == 1.0, np.isfinite(depth))
    result = operators.last_result
    assert result["state"] == "done" and result["files"] == len(EXPECTED_FILES) and result["spp"] == 4
    assert result["est_depth_error_m"] > 0 and result["seconds"] > 0
    assert operators.active_render_job() is None
    # The final frame's convergence plot, loaded from the written file.
    plot = bpy.data.images[images.CONVERGENCE_IMAGE]
    assert result["convergence_image"] == plot.name == "ToF Convergence"
    assert tuple(plot.size) == (640, 400) and os.path.samefile(plot.filepath, out / "convergence.png")
    pixels = images.read_pixels(plot)
    assert pixels[..., :3].min() < 0.5 < pixels[..., :3].max()     # drawn, not blank
    # A second render reloads the same image from its new file.
    assert bpy.ops.tof.render() == {'FINISHED'}
    assert [i.name for i in bpy.data.images].count("ToF Convergence") == 1


def test_progressive_update_step_directly(tof, tmp_path):
    add_plane_and_cube()
    add_tof_camera("kinect_v2", spp=8, output_dir=str(tmp_path))
    job = operators.prepare_render(bpy.context, Reports())
    before = None
    for frame in tofcore.render_progressive(job.scene, job.sensor, job.pose, **job.settings):
        operators._apply_pass(frame)
        now = snapshot()
        if before is not None:
            assert not np.array_equal(before["ToF IR"], now["ToF IR"])
        before = now
        assert operators.last_result["spp"] == frame.stats["spp"]


def test_cancel_after_first_pass_writes_nothing(tof, tmp_path, monkeypatch):
    add_plane_and_cube()
    out = tmp_path / "tof"
    add_tof_camera("kinect_v2", spp=8, output_dir=str(out))
    original = operators._apply_pass
    shown = []

    def cancel_after_first(frame):
        original(frame)
        shown.append(snapshot())
        operators.active_render_job().cancel()     # what Esc does in the modal operator

    monkeypatch.setattr(operators, "_apply_pass", cancel_after_first)
    assert bpy.ops.tof.render() == {'CANCELLED'}
    assert len(shown) == 1
    assert not out.exists() or not any(out.iterdir())
    assert operators.last_result["state"] == "cancelled" and operators.active_render_job() is None
    assert images.CONVERGENCE_IMAGE not in bpy.data.images and "convergence_image" not in operators.last_result
    np.testing.assert_array_equal(snapshot()["ToF Depth"], shown[0]["ToF Depth"])  # keeps the last pass


def _drain(job, timeout_s: float = 60.0):
    """Poll a worker job like the modal timer does; (passes seen, end message)."""
    seen, deadline = [], time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        newest, end = job.poll()
        if newest is not None:
            seen.append(newest)
        if end is not None:
            return seen, end
        time.sleep(0.01)
    raise AssertionError("worker did not finish")


def test_worker_thread_render_and_cancel(tof, tmp_path):
    add_plane_and_cube()
    add_tof_camera("o3d303", spp=4, output_dir=str(tmp_path / "done"))
    job = operators.prepare_render(bpy.context, Reports())
    job.start()
    seen, (kind, (frame, written)) = _drain(job)
    assert kind == "done" and seen and frame.stats["final"]
    assert {path.name for path in written.values()} == EXPECTED_FILES
    # Cancelled as soon as the first pass arrives: the thread ends, nothing is written.
    bpy.context.scene.camera.data.tof.output_dir = str(tmp_path / "cancelled")
    bpy.context.scene.camera.data.tof.spp = 256
    job = operators.prepare_render(bpy.context, Reports())
    job.start()
    while job.messages.empty():
        time.sleep(0.005)
    job.cancel()
    _, (kind, _) = _drain(job)
    job.join(5.0)
    assert kind == "cancelled" and not job.thread.is_alive()
    assert not (tmp_path / "cancelled").exists()


# --------------------------------------------------------------------------- reports

def test_error_no_active_camera(tof):
    add_plane_and_cube()
    assert bpy.context.scene.camera is None
    assert not bpy.ops.tof.render.poll()
    with pytest.raises(RuntimeError, match="No active camera"):
        bpy.ops.tof.render()
    reports = Reports()
    assert operators.prepare_render(bpy.context, reports) is None
    assert reports.of("ERROR") == [operators.render_target(bpy.context)[1]]


def test_error_camera_without_tof_settings(tof):
    add_plane_and_cube()
    plain = _link(bpy.data.objects.new("Plain Camera", bpy.data.cameras.new("Plain Camera")))
    bpy.context.scene.camera = plain
    with pytest.raises(RuntimeError, match="'Plain Camera' has no ToF settings"):
        bpy.ops.tof.render()
    empty = _link(bpy.data.objects.new("Not A Camera", None))
    bpy.context.scene.camera = empty
    reports = Reports()
    assert operators.prepare_render(bpy.context, reports) is None
    assert "'Not A Camera' has no ToF settings" in reports.of("ERROR")[0]


def test_error_nothing_visible(tof, tmp_path):
    cube = add_plane_and_cube()
    bpy.data.objects["Floor"].hide_render = True
    cube.hide_render = True
    add_tof_camera(output_dir=str(tmp_path))
    with pytest.raises(RuntimeError, match="Cannot render: nothing visible to render"):
        bpy.ops.tof.render()
    reports = Reports()
    assert operators.prepare_render(bpy.context, reports) is None
    assert reports.of("ERROR")[0].startswith("Cannot render: nothing visible to render")
    assert not any(tmp_path.iterdir())


def test_error_invalid_override_names_field(tof):
    add_plane_and_cube()
    add_tof_camera("o3d303")
    settings = bpy.context.scene.camera.data.tof
    settings.use_range_m = True
    settings.range_m = (0.3, 10.0)             # beyond the 30 MHz unambiguous range (5 m)
    with pytest.raises(RuntimeError, match=r"Range \(range_m\).*range_m must be within"):
        bpy.ops.tof.render()
    settings.use_range_m = False
    bpy.context.scene.camera.data.tof.preset = "xtion2"   # pulsed: eq. 2.43 noise does not apply
    settings.noise_model = 'li'
    reports = Reports()
    assert operators.prepare_render(bpy.context, reports) is None
    assert "Noise (noise_model)" in reports.of("ERROR")[0]


def test_error_bad_preset_file_and_limits_are_reports(tof, tmp_path, monkeypatch):
    """Issue 12: a hostile preset (huge camera, overflowing physics, not a file) or a render above a resource
    limit is an ERROR report naming the file, key and value; the operator is CANCELLED, nothing written."""
    add_plane_and_cube()
    add_tof_camera(output_dir=str(tmp_path / "out"))
    settings = bpy.context.scene.camera.data.tof
    kinect = (tofcore.sensor.presets.PRESETS_DIR / "kinect_v2.toml").read_text()
    huge = tmp_path / "huge.toml"
    huge.write_text(kinect.replace("width = 512", "width = 100000").replace("height = 424", "height = 100000"))
    hot = tmp_path / "hot.toml"
    hot.write_text(re.sub(r"^responsivity = .*$", "responsivity = 1e300", kinect, flags=re.M))
    settings.use_resolution = False
    settings.preset = sensors.CUSTOM
    for path, needle in ((huge, "[camera]: width x height must be at most 16,777,216 pixels"),
                         (hot, "[readout]: responsivity must be at most 1e+30"),
                         (tmp_path, "must be a preset .toml file, got a folder")):
        settings.preset_path = str(path)
        with pytest.raises(RuntimeError, match=re.escape(f"{path}")):
            bpy.ops.tof.render()
        reports = Reports()
        assert operators.prepare_render(bpy.context, reports) is None
        assert len(reports.of("ERROR")) == 1 and needle in reports.of("ERROR")[0]
    settings.preset = "kinect_v2"
    settings.use_resolution = True
    monkeypatch.setenv("TOFCORE_MAX_RENDER_BYTES", "1000")
    reports = Reports()
    assert operators.prepare_render(bpy.context, reports) is None
    assert "the estimated render memory" in reports.of("ERROR")[0] and "TOFCORE_MAX_RENDER_BYTES" in reports.of(
        "ERROR")[0]
    assert not (tmp_path / "out").exists()


def test_warning_non_mesh_objects_skipped(tof, tmp_path):
    add_plane_and_cube()
    for i in range(2):
        _link(bpy.data.objects.new(f"Points {i}", bpy.data.pointclouds.new(f"Points {i}")))
    add_tof_camera(output_dir=str(tmp_path))
    reports = Reports()
    assert operators.prepare_render(bpy.context, reports) is not None
    assert any(w.startswith("skipped 2 non-mesh objects") for w in reports.of("WARNING")), reports.items


def test_warning_missing_texture_names_file(tof, tmp_path):
    add_plane_and_cube()
    material = bpy.data.materials.new("Painted")
    if bpy.app.version < (5, 0, 0):   # always on (and deprecated) from 5.0
        material.use_nodes = True
    tree = material.node_tree
    bsdf = next(n for n in tree.nodes if n.type == 'BSDF_PRINCIPLED')
    texture = tree.nodes.new("ShaderNodeTexImage")
    missing = tmp_path / "no_such_texture.png"
    texture.image = bpy.data.images.new("no_such_texture", 4, 4)
    texture.image.filepath = str(missing)
    texture.image.source = 'FILE'
    tree.links.new(texture.outputs["Color"], bsdf.inputs["Base Color"])
    bpy.data.objects["Cube"].data.materials.append(material)
    add_tof_camera(output_dir=str(tmp_path))
    reports = Reports()
    assert operators.prepare_render(bpy.context, reports) is not None
    assert any("missing texture file" in w and "no_such_texture.png" in w for w in reports.of("WARNING")), \
        reports.items


# --------------------------------------------------------------------------- live preview

def test_live_preview_handler_and_render(tof, tmp_path):
    add_plane_and_cube()
    camera = add_tof_camera("kinect_v2", width=64, height=48, output_dir=str(tmp_path))
    settings = camera.data.tof
    settings.preview_scale = 0.5
    settings.preview_spp = 2
    assert not operators.preview_handler_registered()
    settings.live_preview = True
    assert operators.preview_handler_registered()
    assert bpy.app.timers.is_registered(operators._preview_timer)   # scheduled (never fires headless)

    # A scene change re-schedules (debounced: the deadline moves).
    deadline = operators._preview.deadline
    bpy.data.objects["Cube"].location.x += 0.1
    bpy.context.view_layer.update()                                  # runs depsgraph_update_post
    assert operators._preview.deadline > deadline

    # What the timer would run: a low-resolution job in a worker thread, polled into the images.
    job = operators.start_live_preview(bpy.context)
    assert job is not None and job.kind == "preview" and job.out_dir is None
    assert (job.sensor.camera.width, job.sensor.camera.height) == (32, 24)
    assert job.settings["preview_denoise"] is True                    # the preview filter (Denoise Preview)
    assert "preview_denoise" not in operators.prepare_render(bpy.context, Reports()).settings   # never Render ToF
    job.join(60.0)
    assert operators.poll_live_preview() is False and operators.active_preview_job() is None
    assert tuple(bpy.data.images["ToF Depth"].size) == (32, 24)
    assert operators.last_result["kind"] == "preview" and operators.last_result["state"] == "done"
    assert not any(tmp_path.iterdir())                               # previews write nothing

    # A camera move re-uses the scene's export (and so its BVH) with the new pose; a scene change exports anew.
    exported = job.exported
    camera.location.x += 0.25
    bpy.context.view_layer.update()
    assert not operators._preview.scene_changed
    moved = operators.start_live_preview(bpy.context)
    assert moved.exported is exported and moved.scene is job.scene
    assert not np.allclose(moved.pose, job.pose) and np.allclose(moved.pose[:3, 3] - job.pose[:3, 3], [0.25, 0, 0])
    moved.join(60.0)
    bpy.data.objects["Cube"].location.z += 0.1
    bpy.context.view_layer.update()
    assert operators._preview.scene_changed
    changed = operators.start_live_preview(bpy.context)
    assert changed.exported is not exported
    changed.join(60.0)
    operators.poll_live_preview()

    # A new preview cancels the running one.
    first = operators.start_live_preview(bpy.context)
    second = operators.start_live_preview(bpy.context)
    assert first.cancelled and not second.cancelled
    second.cancel()
    second.join(10.0)

    settings.live_preview = False
    assert not operators.preview_handler_registered()
    assert not bpy.app.timers.is_registered(operators._preview_timer)
    settings.live_preview = True
    addon.unregister()
    assert not operators.preview_handler_registered()
    addon.register()


# --------------------------------------------------------------------------- panels (without a window)

class RecordingLayout:
    """Stands in for ``UILayout``: checks every property and operator a panel draws exists."""

    def __init__(self, log: list) -> None:
        self.log = log

    def __getattr__(self, name):  # row(), column(), box(), label(), separator(), progress() …
        return lambda *args, **kwargs: self

    def __setattr__(self, name, value):  # use_property_split, active, scale_y …
        if name != "log":
            return
        object.__setattr__(self, name, value)

    def prop(self, data, name, **kwargs):
        assert name in data.bl_rna.properties, f"{type(data).__name__} has no property {name!r}"
        self.log.append(("prop", name))
        return self

    def operator(self, idname, **kwargs):
        module, _, op = idname.partition(".")
        assert hasattr(getattr(bpy.ops, module), op), f"no operator {idname!r}"
        self.log.append(("operator", idname))
        return self


def test_panels_draw(tof, tmp_path):
    from types import SimpleNamespace

    from addon import panels

    add_plane_and_cube()
    camera = add_tof_camera(output_dir=str(tmp_path))
    assert bpy.ops.tof.render() == {'FINISHED'}
    material = bpy.data.materials.new("IR")
    context = SimpleNamespace(camera=camera.data, object=camera, material=material)
    log: list = []
    for panel in panels.classes:
        assert panel.poll(context) if hasattr(panel, "poll") else True
        fake = SimpleNamespace(layout=RecordingLayout(log))
        if hasattr(panel, "draw_header"):
            panel.draw_header(fake, context)
        panel.draw(fake, context)
    drawn = {name for kind, name in log}
    for name in ("enabled", "preset", "live_preview", "use_resolution", "width", "led_offset_m", "noise_model",
                 "use_scattering", "depth_output", "range_m", "spp", "time_budget_s", "target_error_mm",
                 "max_depth", "seed", "output_dir", "formats", "preview_scale", "use_override", "reflectance",
                 "roughness", "extinction"):
        assert name in drawn, name
    assert {operators.TOF_OT_render.bl_idname, operators.TOF_OT_apply_sensor.bl_idname} <= drawn
    menu = SimpleNamespace(layout=RecordingLayout(log))
    panels.draw_add_menu(menu, context)
    assert log[-1] == ("operator", operators.TOF_OT_add_camera.bl_idname)


# --------------------------------------------------------------------------- the modal path, driven by hand

def _modal_render(context, job):
    """What ``TOF_OT_render.invoke`` sets up, on a stand-in for the operator (bpy cannot make one
    without a window event loop): returns the stand-in, whose ``modal`` is the real method."""
    from types import SimpleNamespace

    op = SimpleNamespace(_job=job, report=Reports(), _end=operators.TOF_OT_render._end)
    for name in ("modal", "_finish", "_cleanup", "cancel"):
        setattr(op, name, getattr(operators.TOF_OT_render, name).__get__(op))
    operators._render_job = job
    operators._begin_result(job)
    op._timer = context.window_manager.event_timer_add(operators.POLL_INTERVAL_S, window=context.window)
    context.window_manager.progress_begin(0, 100)
    job.start()
    return op


def _run_modal(op, context, *, escape_after_first_pass: bool = False, timeout_s: float = 60.0):
    from types import SimpleNamespace

    timer, escape = SimpleNamespace(type='TIMER', value='NOTHING'), SimpleNamespace(type='ESC', value='PRESS')
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        result = op.modal(context, timer)
        if result != {'PASS_THROUGH'}:
            return result
        if escape_after_first_pass and operators.last_result.get("spp", 0) >= 1:
            assert op.modal(context, escape) == {'RUNNING_MODAL'} and op._job.cancelled
        time.sleep(0.01)
    raise AssertionError("the modal render did not end")


def test_modal_render_and_escape(tof, tmp_path):
    add_plane_and_cube()
    camera = add_tof_camera("kinect_v2", spp=4, output_dir=str(tmp_path / "done"))
    context = bpy.context
    op = _modal_render(context, operators.prepare_render(context, Reports()))
    assert _run_modal(op, context) == {'FINISHED'}
    assert set(os.listdir(tmp_path / "done")) == EXPECTED_FILES
    assert op.report.of("INFO") and f"{len(EXPECTED_FILES)} files written" in op.report.of("INFO")[0]
    assert operators.active_render_job() is None and operators.last_result["state"] == "done"
    assert tuple(bpy.data.images["ToF Depth"].size) == (32, 24)
    assert os.path.samefile(bpy.data.images["ToF Convergence"].filepath, tmp_path / "done" / "convergence.png")

    camera.data.tof.spp = 1024
    camera.data.tof.output_dir = str(tmp_path / "escaped")
    op = _modal_render(context, operators.prepare_render(context, Reports()))
    assert _run_modal(op, context, escape_after_first_pass=True) == {'CANCELLED'}
    assert "cancelled" in op.report.of("WARNING")[0]
    assert not (tmp_path / "escaped").exists()
    assert operators.active_render_job() is None and operators.last_result["state"] == "cancelled"
    op._job.join(5.0)
    assert not op._job.thread.is_alive()


# --------------------------------------------------------------------------- the render device (preferences)

from tests import fakecupy  # noqa: E402  (the CuPy stand-in)

from addon import gpu, preferences  # noqa: E402
from tofcore import backend  # noqa: E402

#: What tofcore raises for a GPU machine whose driver or device does not answer (no such machine here).
NO_DEVICE = ("GPU: CuPy 13.6.0 found no usable CUDA device (CUDARuntimeError: cudaErrorNoDevice: "
             "no CUDA-capable device is detected)")


@pytest.fixture
def prefs(tof, monkeypatch):
    """The add-on's real preferences: an add-on entry for the plain package, removed afterwards; the GPU
    status starts afresh."""
    monkeypatch.setattr(gpu, "_status", None)
    entry = bpy.context.preferences.addons.new()
    entry.module = "addon"
    assert preferences.get() == entry.preferences and entry.preferences.device == 'cpu'
    yield entry.preferences
    bpy.context.preferences.addons.remove(entry)


@pytest.fixture
def render_calls(monkeypatch):
    """Every ``tofcore.render_progressive`` call's ``device`` argument (the render itself runs as usual)."""
    calls = []
    original = tofcore.render_progressive

    def recording(*args, **kwargs):
        calls.append(kwargs.get("device"))
        return original(*args, **kwargs)

    monkeypatch.setattr(tofcore, "render_progressive", recording)
    return calls


def run_execute(operator_class, context=None):
    """``operator_class.execute`` on a stand-in operator that collects its reports: (result, Reports)."""
    from types import SimpleNamespace

    op = SimpleNamespace(report=Reports())
    for name in ("execute", "_start"):
        setattr(op, name, getattr(operator_class, name).__get__(op))
    op._end = getattr(operator_class, "_end", None)
    return op.execute(context or bpy.context), op.report


def _gpu_usable() -> bool:
    return backend.select_device("auto").name == "gpu"


def test_render_default_device_is_cpu(prefs, tmp_path, render_calls):
    add_plane_and_cube()
    add_tof_camera(output_dir=str(tmp_path))
    result, reports = run_execute(operators.TOF_OT_render)
    assert result == {'FINISHED'} and render_calls == ["cpu"]
    assert not reports.of("WARNING") and not reports.of("ERROR")
    device = f"CPU (NumPy {np.__version__})"
    assert f" on {device}" in reports.of("INFO")[0]
    assert operators.last_result["device"] == device and operators.last_result["fallback_reason"] is None
    assert all(bpy.data.images[name][images.DEVICE_KEY] == device for name in images.IMAGE_NAMES.values())


@pytest.mark.parametrize("wanted", ["auto", "numpy"])
def test_render_reports_the_tracer(prefs, tmp_path, monkeypatch, wanted):
    """Which tracer ran, and why NumPy where it did, is in the summary, the panel's result and the numba box."""
    from addon import compiled

    monkeypatch.setenv("TOFCORE_TRACER", wanted)
    add_plane_and_cube()
    add_tof_camera(output_dir=str(tmp_path))
    result, reports = run_execute(operators.TOF_OT_render)
    assert result == {'FINISHED'}, reports.items
    transport = operators.last_result["transport"]
    expected = "compiled" if wanted == "auto" and compiled_importable() else "numpy"
    assert transport["tracer"] == expected
    text = compiled.tracer_text(transport)
    assert reports.of("INFO")[0].endswith(f"; {text}")
    if expected == "compiled":
        assert text.startswith("Tracer: compiled (numba, ") and text.endswith(" threads)")
        assert compiled.status_line(compiled.last_tracer())[1] == 'CHECKMARK'
    else:
        assert text == "Tracer: NumPy (TOFCORE_TRACER=numpy)" if wanted == "numpy" else text.startswith("Tracer: NumPy")
        assert compiled.last_tracer()["tracer"] == "numpy"
    from addon import panels

    class Layout(RecordingLayout):
        def label(self, text="", icon='NONE', **kwargs):
            self.log.append(("label", text, icon))
            return self

    log: list = []
    panels.draw_result(Layout(log))
    assert ("label", text, 'SETTINGS') in log


def test_the_result_box_says_the_tracer_compiles_before_the_first_pass(monkeypatch):
    """A render or live preview waiting for the background compile (tofcore.compiled.child_compile) says so."""
    from addon import panels
    from tofcore.compiled import child_compile

    class Layout(RecordingLayout):
        def label(self, text="", icon='NONE', **kwargs):
            self.log.append(("label", text, icon))
            return self

    def labels(compiling: bool, spp: int) -> list:
        monkeypatch.setattr(child_compile, "running", lambda: compiling)
        monkeypatch.setattr(operators, "last_result", {"camera": "Cam", "kind": "preview", "state": "running",
                                                      "spp": spp, "spp_max": 8})
        log: list = []
        panels.draw_result(Layout(log))
        return [entry for entry in log if entry[0] == "label" and entry[2] == 'SORTTIME']

    assert labels(True, 0) == [("label", "Compiling the tracer once, in the background (30 s to 3 min)…", 'SORTTIME')]
    assert labels(False, 0) == [] and labels(True, 4) == []


def compiled_importable() -> bool:
    from tofcore.compiled import numba_version

    return numba_version() is not None


def test_render_auto_without_gpu_falls_back_to_cpu(prefs, tmp_path, render_calls):
    """This machine has no CuPy/GPU: "auto" renders on the CPU and says why, as a WARNING."""
    if _gpu_usable():
        pytest.skip("a usable GPU: auto does not fall back here")
    add_plane_and_cube()
    add_tof_camera(output_dir=str(tmp_path))
    prefs.device = 'auto'
    result, reports = run_execute(operators.TOF_OT_render)
    assert result == {'FINISHED'} and render_calls == ["auto"]
    assert not reports.of("ERROR")
    warnings = reports.of("WARNING")
    assert len(warnings) == 1 and warnings[0].startswith("Rendered on the CPU: ")
    if not gpu.installed_cupy():   # then the warning says how to get CuPy in Blender, not with pip
        assert "Install CuPy for GPU rendering" in warnings[0]
    assert f"on CPU (NumPy {np.__version__})" in reports.of("INFO")[0]
    assert operators.last_result["device_name"] == "cpu" and operators.last_result["fallback_reason"]
    import json
    device = json.loads((tmp_path / "frame.json").read_text())["stats"]["device"]
    assert device["name"] == "cpu" and device["requested"] == "auto" and device["fallback_reason"]


def test_render_auto_names_the_gpu_failure(prefs, tmp_path, monkeypatch):
    def no_device():
        raise backend.GpuUnavailable(NO_DEVICE)

    monkeypatch.setattr(backend, "_gpu_module", no_device)
    monkeypatch.setattr(gpu, "installed_cupy", lambda: [("cupy-cuda12x", "13.6.0", str(tmp_path))])
    add_plane_and_cube()
    add_tof_camera(output_dir=str(tmp_path))
    prefs.device = 'auto'
    result, reports = run_execute(operators.TOF_OT_render)
    assert result == {'FINISHED'}
    assert reports.of("WARNING") == [f"Rendered on the CPU: {NO_DEVICE}"]
    assert gpu.status().problem == NO_DEVICE and gpu.status().device is None


def test_render_gpu_without_cupy_is_a_clean_error(prefs, tmp_path, monkeypatch, render_calls):
    monkeypatch.setattr(gpu, "installed_cupy", lambda: [])
    add_plane_and_cube()
    add_tof_camera(output_dir=str(tmp_path / "out"))
    prefs.device = 'gpu'
    result, reports = run_execute(operators.TOF_OT_render)
    assert result == {'CANCELLED'} and render_calls == []
    (error,) = reports.of("ERROR")
    assert error == ("Device GPU needs CuPy in Blender's Python: Preferences > Add-ons > ToF Camera Simulator > "
                     "Install CuPy for GPU rendering (or set Device to CPU or Auto)")
    with pytest.raises(RuntimeError, match="Device GPU needs CuPy") as raised:
        bpy.ops.tof.render()
    assert "Traceback" not in str(raised.value)
    assert not (tmp_path / "out").exists() and operators.active_render_job() is None
    if not _gpu_usable():   # past the add-on's check, tofcore itself refuses "gpu" here with one line
        prefs.device = 'cpu'
        job = operators.prepare_render(bpy.context, Reports())
        job.device = "gpu"
        with pytest.raises(backend.GpuUnavailable, match="^GPU: ") as raised:
            job.run(lambda frame: None)
        assert "\n" not in str(raised.value) and operators.error_text(raised.value) == str(raised.value)


def test_render_gpu_unusable_is_a_clean_error(prefs, tmp_path, monkeypatch, render_calls):
    """CuPy installed, but tofcore finds no usable device: one-line ERROR, CANCELLED, nothing written."""
    def no_device():
        raise backend.GpuUnavailable(NO_DEVICE)

    monkeypatch.setattr(backend, "_gpu_module", no_device)
    monkeypatch.setattr(gpu, "installed_cupy", lambda: [("cupy-cuda12x", "13.6.0", str(tmp_path))])
    add_plane_and_cube()
    add_tof_camera(output_dir=str(tmp_path / "out"))
    prefs.device = 'gpu'
    result, reports = run_execute(operators.TOF_OT_render)
    assert result == {'CANCELLED'} and render_calls == ["gpu"]
    assert reports.of("ERROR") == [f"ToF render failed: {NO_DEVICE}"]
    assert operators.last_result["state"] == "error" and operators.active_render_job() is None
    with pytest.raises(RuntimeError, match="ToF render failed: GPU: CuPy 13.6.0 found no usable CUDA device") \
            as raised:
        bpy.ops.tof.render()
    assert "Traceback" not in str(raised.value)
    assert not (tmp_path / "out").exists()
    # The UI's worker thread posts the same one line (no exception type in front of tofcore's message).
    job = operators.prepare_render(bpy.context, Reports())
    assert job.device == "gpu"
    job.start()
    _, end = _drain(job)
    assert end == ("error", NO_DEVICE)


def test_render_on_gpu_stand_in(prefs, tmp_path, monkeypatch, render_calls):
    """device "gpu" end to end on tests/fakecupy.py (CuPy's rules, NumPy inside): the device is reported."""
    fakecupy.install(monkeypatch)
    monkeypatch.setattr(gpu, "installed_cupy", lambda: [("cupy-cuda12x", "fake", str(tmp_path))])
    add_plane_and_cube()
    add_tof_camera(output_dir=str(tmp_path))
    prefs.device = 'gpu'
    result, reports = run_execute(operators.TOF_OT_render)
    assert result == {'FINISHED'} and render_calls == ["gpu"], reports.items
    description = "fake GPU (NumPy behind CuPy's rules)"
    assert f" on {description}" in reports.of("INFO")[0] and not reports.of("WARNING")
    assert operators.last_result["device"] == description and operators.last_result["device_name"] == "gpu"
    assert bpy.data.images["ToF Depth"][images.DEVICE_KEY] == description
    assert gpu.status().device == description
    # The live preview runs on the same device.
    camera = bpy.context.scene.camera
    camera.data.tof.live_preview = True
    job = operators.start_live_preview(bpy.context)
    assert job is not None and job.device == "gpu"
    job.join(60.0)
    assert operators.poll_live_preview() is False
    assert operators.last_result["kind"] == "preview" and operators.last_result["device"] == description
    camera.data.tof.live_preview = False


def test_panel_shows_device_and_fallback(prefs, tmp_path):
    from addon import panels

    labels = []

    class Layout(RecordingLayout):
        def label(self, text="", **kwargs):
            labels.append(text)
            return self

    add_plane_and_cube()
    camera = add_tof_camera(output_dir=str(tmp_path))
    operators.last_result.update(camera=camera.name, kind="render", state="done", device="CPU (NumPy 1.26.4)",
                                 device_name="cpu", fallback_reason="GPU: CuPy is not installed")
    panels.draw_result(Layout([]), camera.name)
    assert "Device: CPU (NumPy 1.26.4)" in labels
    assert any(text.startswith("Rendered on the CPU") for text in labels)
    operators.last_result.clear()
