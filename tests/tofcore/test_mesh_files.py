"""Scenes from OBJ, PLY, glTF/GLB and STL files (through trimesh): geometry, axes, materials, errors, CLI."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

import tofcore
from tofcore.errors import SceneError
from tofcore.scene.mesh_files import front_view, load_mesh

trimesh = pytest.importorskip("trimesh")

OBJ = """mtllib wall.mtl
v -2 0 -3
v 2 0 -3
v 2 3 -3
v -2 3 -3
usemtl grey
f 1 2 3
f 1 3 4
v -0.5 0 -2
v 0.5 0 -2
v 0 1 -2
usemtl red
f 5 6 7
"""
MTL = "newmtl grey\nKd 0.5 0.5 0.5\nnewmtl red\nKd 0.8 0.1 0.1\n"


@pytest.fixture
def obj_file(tmp_path):
    (tmp_path / "wall.mtl").write_text(MTL)
    path = tmp_path / "wall.obj"
    path.write_text(OBJ)
    return path


def _glb(path, pbr: dict | None):
    box = trimesh.creation.box(extents=[1.0, 2.0, 0.5])
    if pbr is not None:
        box.visual = trimesh.visual.TextureVisuals(material=trimesh.visual.material.PBRMaterial(name="steel", **pbr))
    scene = trimesh.Scene()
    scene.add_geometry(box, node_name="crate")
    scene.export(str(path))
    return path


def test_obj_is_turned_y_up_to_z_up_with_mtl_materials(obj_file):
    scene = load_mesh(obj_file)
    lo, hi = scene.bounds + np.asarray(scene.origin_m)[None]
    # OBJ (x, y, z) → world (x, -z, y): the wall at z = -3 stands at y = 3, from z = 0 to 3.
    np.testing.assert_allclose(lo, [-2, 2, 0], atol=1e-6)
    np.testing.assert_allclose(hi, [2, 3, 3], atol=1e-6)
    by_name = {m.name: m for m in scene.materials}
    assert math.isclose(by_name["grey"].reflectance, 0.5, rel_tol=1e-6)               # luminance of Kd
    assert math.isclose(by_name["red"].reflectance, 0.2126 * 0.8 + 0.7152 * 0.1 + 0.0722 * 0.1, rel_tol=1e-6)
    assert sorted(scene.object_names) == ["grey", "red"] and scene.triangle_count == 3


def test_gltf_pbr_maps_like_the_addon(tmp_path):
    scene = load_mesh(_glb(tmp_path / "crate.glb", {"baseColorFactor": [0.8, 0.8, 0.8, 1.0], "metallicFactor": 1.0,
                                                      "roughnessFactor": 0.4}))
    (material,) = scene.materials
    assert scene.object_names == ("crate",) and material.name == "steel"
    assert abs(material.reflectance - 0.8) < 1 / 255                           # 8-bit factor in trimesh
    assert math.isclose(material.roughness, 0.4 ** 2 / math.sqrt(2), rel_tol=1e-6)
    eta, k = material.ior, material.extinction                               # F0 = luminance for a metal
    assert material.metallic == 1.0 and math.isclose(((eta - 1) ** 2 + k * k) / ((eta + 1) ** 2 + k * k),
                                                     material.reflectance, rel_tol=1e-6)
    # glTF is Y up: the box's 2 m side (its y) is the world's z.
    lo, hi = scene.bounds
    np.testing.assert_allclose(hi - lo, [1.0, 0.5, 2.0], atol=1e-6)


@pytest.mark.parametrize("suffix", [".stl", ".ply"])
def test_stl_and_ply_are_z_up_with_the_default_material(tmp_path, suffix):
    path = tmp_path / f"box{suffix}"
    trimesh.creation.box(extents=[1.0, 2.0, 0.5]).export(str(path))
    scene = load_mesh(path)
    lo, hi = scene.bounds
    np.testing.assert_allclose(hi - lo, [1.0, 2.0, 0.5], atol=1e-6)
    (material,) = scene.materials
    assert (material.name, material.reflectance, material.roughness, material.metallic) == ("default", 0.5, 0.5, 0.0)


def test_errors_name_the_file_and_the_fix(tmp_path, monkeypatch):
    with pytest.raises(SceneError, match=r"missing\.glb: file not found"):
        load_mesh(tmp_path / "missing.glb")
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"not a glb at all")
    with pytest.raises(SceneError, match=r"bad\.glb: cannot read the mesh file"):
        load_mesh(bad)
    with pytest.raises(SceneError, match=r"must end in one of"):
        load_mesh(tmp_path / "x.fbx")
    monkeypatch.setitem(sys.modules, "trimesh", None)
    with pytest.raises(SceneError, match=r"needs the trimesh package, which is not installed: pip install trimesh"):
        load_mesh(bad)


def test_the_suggested_front_view_sees_the_whole_box_and_renders_at_the_right_distance(obj_file):
    """The wall's centre (0, 3, 1.5) seen from −Y: bounding radius r = |(4, 1, 3)|/2, distance 2r (60°)."""
    scene = load_mesh(obj_file)
    pose = np.asarray(scene.metadata["world_from_sensor"])
    np.testing.assert_allclose(pose, front_view(np.array([-2, 2, 0]), np.array([2, 3, 3])), atol=1e-6)
    radius = math.sqrt(4 ** 2 + 1 + 3 ** 2) / 2
    np.testing.assert_allclose(pose[:3, 3], [0, 2.5 - 2 * radius, 1.5], atol=1e-6)
    sensor = tofcore.load_preset("kinect_v2").scaled(0.0625)
    frame = tofcore.render(scene, sensor, spp=1, max_depth=1)  # the view framed for this sensor (below)
    h, w = frame.gt_distance.shape
    centre = frame.gt_distance[h // 2 - 1:h // 2 + 1, w // 2 - 1:w // 2 + 1]
    # The centre pixels look along +Y at height 1.5 m, above the red triangle (up to 1 m): the wall at y = 3,
    # radial distance 3 − y_cam within 2 cm (the pixels are about a degree off the axis).
    np.testing.assert_allclose(centre, 3 - frame.world_from_sensor[1, 3], atol=0.02)


def test_tofcore_render_takes_a_mesh_file(tmp_path):
    path = _glb(tmp_path / "crate.glb", {"baseColorFactor": [0.9, 0.9, 0.9, 1.0]})
    proc = subprocess.run([sys.executable, "-m", "tofcore", "render", "--scene", str(path), "--resolution-scale",
                           "0.0625", "--spp", "1", "--max-depth", "1", "--formats", "json",
                           "--out", str(tmp_path / "o"), "--quiet"], capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr
    import json

    document = json.loads((tmp_path / "o" / "frame.json").read_text())
    assert document["metadata"]["objects"] == [{"id": 0, "name": "crate", "materials": ["steel"]}]


def _room(path):
    """A 4 m room as a user makes one with trimesh (Y up): floor, back and side wall, a box and a ball."""
    floor = trimesh.creation.box(extents=[4, 0.05, 4])
    floor.apply_translation([0, -0.025, 0])
    back = trimesh.creation.box(extents=[4, 2.5, 0.05])
    back.apply_translation([0, 1.25, -2])
    side = trimesh.creation.box(extents=[0.05, 2.5, 4])
    side.apply_translation([-2, 1.25, 0])
    box = trimesh.creation.box(extents=[0.8, 0.8, 0.8])
    box.apply_translation([0.5, 0.4, -0.5])
    ball = trimesh.creation.icosphere(radius=0.4)
    ball.apply_translation([-0.8, 0.4, 0.6])
    trimesh.Scene([floor, back, side, box, ball]).export(str(path))
    return path


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_a_room_is_framed_within_the_sensors_range(tmp_path, suffix):
    """Issue 36: the 60° sphere fit put a 4 m room 6.2 m from a Kinect (range 0.5–4.5 m): 2–4 % valid pixels.
    Framed for the sensor, the room's far side is within 90 % of the range and most pixels are valid."""
    scene = load_mesh(_room(tmp_path / f"room{suffix}"))
    sensor = tofcore.load_preset("kinect_v2").scaled(0.0625)
    old = tofcore.render(scene, sensor, np.asarray(scene.metadata["world_from_sensor"]), spp=1, max_depth=1)
    frame = tofcore.render(scene, sensor, spp=1, max_depth=1)
    far_side = scene.metadata["framing"]["hi"][1] - frame.world_from_sensor[1, 3]
    assert far_side <= 0.9 * sensor.range_m[1] + 1e-9
    assert old.valid.mean() < 0.10 < 0.5 < frame.valid.mean()
    assert np.nanmax(frame.gt_depth[frame.valid]) <= sensor.range_m[1]


def test_framed_view_fits_a_small_box_into_the_field_of_view_and_keeps_a_deep_one_in_range():
    from tofcore.scene.pose import FAR_MARGIN, framed_view

    sensor = tofcore.load_preset("kinect_v2")
    cam = sensor.camera
    tan_half = (min(cam.cx, cam.width - cam.cx) / cam.fx, min(cam.cy, cam.height - cam.cy) / cam.fy)
    lo, hi = np.array([-1.0, 1.0, 0.0]), np.array([1.0, 2.0, 1.6])  # d_fov 1.9 m: beyond the near limit
    pose = framed_view(lo, hi, tan_half_fov=tan_half, range_m=sensor.range_m)
    corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    in_sensor = (np.linalg.inv(pose) @ corners.T)[:3]
    u = cam.fx * in_sensor[0] / in_sensor[2] + cam.cx
    v = cam.fy * in_sensor[1] / in_sensor[2] + cam.cy
    assert np.all((u >= -1e-6) & (u <= cam.width + 1e-6) & (v >= -1e-6) & (v <= cam.height + 1e-6))
    assert np.isclose(max(np.abs(u - cam.cx).max() / (cam.width - cam.cx), np.abs(v - cam.cy).max() / cam.cy), 1.0)
    wide = framed_view([-5, 0, 0], [5, 3, 3], tan_half_fov=tan_half, range_m=sensor.range_m)
    assert np.isclose(3 - wide[1, 3], FAR_MARGIN * sensor.range_m[1])  # the far side at 90 % of the range
    deep = framed_view([-5, 0, 0], [5, 6, 3], tan_half_fov=tan_half, range_m=sensor.range_m)
    assert np.isclose(deep[1, 3], 0.0)  # deeper than the range: at its near side, never inside


def test_a_frame_with_few_valid_pixels_is_warned_about_with_the_likely_reason(tmp_path):
    from tofcore.output.coverage import low_coverage

    scene = load_mesh(_room(tmp_path / "room.obj"))
    sensor = tofcore.load_preset("kinect_v2").scaled(0.0625)
    far = tofcore.render(scene, sensor, np.asarray(scene.metadata["world_from_sensor"]), spp=1, max_depth=1)
    assert "see surfaces beyond the sensor's range (0.5-4.5 m; the farthest at 8." in low_coverage(far)
    assert low_coverage(far).startswith(f"only {100 * far.valid.mean():.1f} % of the pixels are valid")
    away = tofcore.render(scene, sensor, tofcore.look_at([0, -3, 1], [0, -6, 1]), spp=1, max_depth=1)
    assert low_coverage(away) == ("only 0.0 % of the pixels are valid (fewer than 10 %): 100 % see no surface, so "
                                  "no LED returns: aim the sensor at the scene")
    assert low_coverage(tofcore.render(scene, sensor, spp=1, max_depth=1)) is None


def test_tofcore_render_warns_and_prints_no_nan(tmp_path):
    """``tofcore render`` of a view that sees little: a warning line naming why, no "nan" in the summary."""
    from dataclasses import replace

    from tofcore.cli import summary

    room = _room(tmp_path / "room.obj")
    proc = subprocess.run([sys.executable, "-m", "tofcore", "render", "--scene", str(room), "--resolution-scale",
                           "0.0625", "--spp", "1", "--max-depth", "1", "--formats", "json", "--eye", "0,-3,1",
                           "--target", "0,-6,1", "--out", str(tmp_path / "o")], capture_output=True, text=True,
                          timeout=240)
    assert proc.returncode == 0, proc.stderr
    assert "warning: only 0.0 % of the pixels are valid (fewer than 10 %): 100 % see no surface" in proc.stderr
    assert "nan" not in proc.stdout.lower()
    assert "depth error vs ground truth: – (no valid pixel with a ground truth)" in proc.stdout
    # A valid pixel at an edge whose centre ray misses (no ground truth) made the RMS "nan mm".
    frame = tofcore.render(load_mesh(room), tofcore.load_preset("kinect_v2").scaled(0.0625), spp=1, max_depth=1)
    gt = frame.gt_depth.copy()
    gt[np.unravel_index(np.argmax(frame.valid), gt.shape)] = np.nan
    assert "nan" not in summary(replace(frame, gt_depth=gt)).lower()
