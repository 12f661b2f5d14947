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
    frame = tofcore.render(scene, sensor, spp=1, max_depth=1)
    h, w = frame.gt_distance.shape
    centre = frame.gt_distance[h // 2 - 1:h // 2 + 1, w // 2 - 1:w // 2 + 1]
    # The centre pixels look along +Y at height 1.5 m, above the red triangle (up to 1 m): the wall at y = 3,
    # radial distance 3 − y_cam within 2 cm (the pixels are about a degree off the axis).
    np.testing.assert_allclose(centre, 3 - pose[1, 3], atol=0.02)


def test_tofcore_render_takes_a_mesh_file(tmp_path):
    path = _glb(tmp_path / "crate.glb", {"baseColorFactor": [0.9, 0.9, 0.9, 1.0]})
    proc = subprocess.run([sys.executable, "-m", "tofcore", "render", "--scene", str(path), "--resolution-scale",
                           "0.0625", "--spp", "1", "--max-depth", "1", "--formats", "json",
                           "--out", str(tmp_path / "o"), "--quiet"], capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr
    import json

    document = json.loads((tmp_path / "o" / "frame.json").read_text())
    assert document["metadata"]["objects"] == [{"id": 0, "name": "crate", "materials": ["steel"]}]
