"""The add-on in Blender's timeline and preset menu (issue 24, items 15-16), through the ``bpy`` module:
frame-numbered output folders, Render ToF Animation over the frame range, the Sensor Presets menu (add, apply,
remove), errors naming the UI label, where "//" goes for an unsaved file, the host check."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import tofcore  # noqa: E402

import addon  # noqa: E402
from addon import animation, operators, presets, sensors  # noqa: E402
from test_operators import EXPECTED_FILES, add_plane_and_cube, add_tof_camera  # noqa: E402


@pytest.fixture
def tof(clean_bpy):
    addon.register()
    yield clean_bpy
    addon.unregister()


@pytest.mark.parametrize("path, frame, numbered, expected", [
    ("/o/tof/####/", 7, False, "/o/tof/0007/"),
    ("/o/f_#_x##/", 12, False, "/o/f_12_x12/"),
    ("/o/tof/####", -3, False, "/o/tof/-003"),
    ("/o/tof/", 7, False, "/o/tof/"),
    ("/o/tof/", 7, True, os.path.join("/o/tof/", "0007")),
])
def test_frame_path(path, frame, numbered, expected):
    assert operators.frame_path(path, frame, numbered=numbered) == expected


def test_default_output_folder_is_frame_numbered(tof):
    camera = add_tof_camera(output_dir="//tof/####/")
    assert camera.data.tof.bl_rna.properties["output_dir"].default == "//tof/####/"
    bpy.context.scene.frame_set(5)
    assert operators.output_folder("//tof/####/", 5) == os.path.join(operators.unsaved_folder(), "tof/0005/")


def test_animation_renders_every_frame_into_its_folder(tof, tmp_path):
    """3 frames, the camera animated: 3 folders with every file, different depth, the scene back at its frame."""
    add_plane_and_cube()
    camera = add_tof_camera(spp=1, max_depth=1, output_dir=str(tmp_path / "anim" / "####"))
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end, scene.frame_current = 1, 3, 2
    for frame, y in ((1, -2.0), (3, -3.0)):
        camera.location.y = y
        camera.keyframe_insert("location", frame=frame)
    assert bpy.ops.tof.render_animation('INVOKE_DEFAULT') == {'FINISHED'}
    folders = sorted(os.listdir(tmp_path / "anim"))
    assert folders == ["0001", "0002", "0003"]
    for folder in folders:
        assert set(os.listdir(tmp_path / "anim" / folder)) == EXPECTED_FILES
    poses = [tofcore.exr.read_header(tmp_path / "anim" / f / "frame.exr")["world_from_sensor"] for f in folders]
    assert [round(float(p[1, 3]), 6) for p in poses] == [-2.0, -2.5, -3.0]        # the keyed camera, interpolated
    depth = [tofcore.read_exr(tmp_path / "anim" / f / "frame.exr", ["gt_depth"])["gt_depth"] for f in folders]
    assert not np.array_equal(depth[0], depth[2], equal_nan=True)
    assert scene.frame_current == 2 and operators.active_render_job() is None
    assert operators.last_result["state"] == "done" and operators.last_result["files"] == 3


def test_animation_without_hashes_gets_numbered_folders(tof, tmp_path):
    add_plane_and_cube()
    add_tof_camera(spp=1, max_depth=1, output_dir=str(tmp_path / "plain"))
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end, scene.frame_step = 4, 8, 2
    assert animation.frame_numbers(scene) == [4, 6, 8]
    assert bpy.ops.tof.render_animation() == {'FINISHED'}
    assert sorted(os.listdir(tmp_path / "plain")) == ["0004", "0006", "0008"]


def test_sensor_preset_add_apply_remove(tof, tmp_path):
    """A custom sensor (Kinect v2 at 64 x 53, LEDs spread 2x, no noise) saved as a Blender preset, applied to a
    second camera, removed."""
    camera = add_tof_camera()
    settings = camera.data.tof
    settings.width, settings.height = 64, 53
    settings.use_led_override, settings.led_spread = True, 2.0
    settings.noise_model = 'none'
    assert bpy.ops.tof.sensor_preset_add(name="Half Kinect") == {'FINISHED'}
    folder = Path(bpy.utils.user_resource('SCRIPTS', path=os.path.join("presets", presets.PRESET_SUBDIR)))
    saved = folder / "Half_Kinect.py"
    assert saved.is_file()
    text = saved.read_text()
    assert "tof.width = 64" in text and "tof.noise_model = 'none'" in text and "output_dir" not in text

    other = add_tof_camera("o3d303")
    assert other.data.tof.preset == "o3d303"
    bpy.ops.script.execute_preset(filepath=str(saved), menu_idname=presets.TOF_MT_sensor_presets.__name__)
    applied = other.data.tof
    assert (applied.preset, applied.width, applied.height, applied.led_spread, applied.noise_model) == \
        ("kinect_v2", 64, 53, 2.0, 'none')
    sensor = sensors.sensor_from_settings(applied)
    assert (sensor.camera.width, sensor.camera.height, sensor.noise.model) == (64, 53, "none")

    presets.TOF_MT_sensor_presets.bl_label = "Half Kinect"   # what choosing it in the menu does
    assert bpy.ops.tof.sensor_preset_add(name="", remove_active=True) == {'FINISHED'}
    assert not saved.exists()


def test_custom_preset_errors_name_the_ui_label(tof, tmp_path):
    camera = add_tof_camera()
    settings = camera.data.tof
    settings.preset = sensors.CUSTOM
    settings.preset_path = ""
    with pytest.raises(tofcore.ConfigError, match=r"^Preset File \(preset_path\) must name a \.toml file"):
        sensors.sensor_from_settings(settings)
    settings.preset_path = str(tmp_path / "missing.toml")
    with pytest.raises(tofcore.ConfigError, match=r"^Preset File \(preset_path\): .*missing\.toml"):
        sensors.sensor_from_settings(settings)


@pytest.mark.parametrize("blender, python, expected", [
    ((4, 1, 1), (3, 11, 7), "needs Blender 4.2.0 or newer (it is an extension), this is Blender 4.1.1"),
    ((4, 2, 0), (3, 10, 0), "needs Python 3.11 or newer in Blender, this Blender has Python 3.10"),
    ((4, 2, 0), (3, 11, 0), None), ((5, 2, 3), (3, 13, 1), None),
])
def test_host_problem(blender, python, expected):
    problem = addon.host_problem(blender, python)
    assert problem == (None if expected is None else f"ToF Camera Simulator {expected}")
