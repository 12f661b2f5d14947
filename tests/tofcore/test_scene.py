"""Scene, Material, Texture: validation, degenerate triangles, save/load, demo scenes."""

import numpy as np
import pytest

import tofcore
from tofcore import ConfigError, Material, Scene, SceneError, Texture

QUAD_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
QUAD_T = np.array([[0, 1, 2], [0, 2, 3]])


def test_from_arrays_builds_flat_arrays():
    s = Scene.from_arrays(QUAD_V, QUAD_T)
    assert s.vertices.dtype == np.float32 and s.triangles.dtype == np.int32
    assert s.triangle_count == 2 and s.dropped_triangles == 0
    np.testing.assert_allclose(s.face_normals, [[0, 0, 1], [0, 0, 1]])
    assert s.material_ids.tolist() == [0, 0] and len(s.materials) == 1


def test_nan_vertex_names_array_and_index():
    v = QUAD_V.copy()
    v[2, 1] = np.nan
    with pytest.raises(SceneError, match=r"vertices must be finite.*at vertex 2"):
        Scene.from_arrays(v, QUAD_T)
    v[2, 1] = np.inf
    with pytest.raises(SceneError, match=r"at vertex 2"):
        Scene.from_arrays(v, QUAD_T)


def test_index_out_of_range_names_triangle():
    with pytest.raises(SceneError, match=r"triangles must index vertices in \[0, 4\), got \[0, 2, 4\] at triangle 1"):
        Scene.from_arrays(QUAD_V, [[0, 1, 2], [0, 2, 4]])
    with pytest.raises(SceneError, match=r"at triangle 0"):
        Scene.from_arrays(QUAD_V, [[-1, 1, 2]])


def test_empty_scene_is_an_error():
    with pytest.raises(SceneError, match="at least one triangle, got 0"):
        Scene.from_arrays(QUAD_V, np.zeros((0, 3), int))


def test_wrong_shapes_are_named():
    with pytest.raises(SceneError, match=r"vertices: must have shape \(N, 3\), got \(4, 2\)"):
        Scene.from_arrays(QUAD_V[:, :2], QUAD_T)
    with pytest.raises(SceneError, match=r"material_ids: must be in \[0, 1\), got 3 at triangle 1"):
        Scene.from_arrays(QUAD_V, QUAD_T, material_ids=[0, 3])
    with pytest.raises(SceneError, match=r"normals must be non-zero.*vertex 1"):
        Scene.from_arrays(QUAD_V, QUAD_T, normals=[[0, 0, 1], [0, 0, 0], [0, 0, 1], [0, 0, 1]])


def test_degenerate_triangles_dropped_and_counted():
    v = np.vstack([QUAD_V, [[2, 2, 0]]]).astype(np.float32)
    tris = [[0, 1, 2], [0, 0, 1], [0, 2, 4], [0, 2, 3]]  # repeated index; collinear (0, 2, 4)
    s = Scene.from_arrays(v, tris, material_ids=[0, 0, 0, 0], object_ids=[5, 6, 7, 8])
    assert s.dropped_triangles == 2
    assert s.triangles.tolist() == [[0, 1, 2], [0, 2, 3]]
    assert s.object_ids.tolist() == [5, 8]
    with pytest.raises(SceneError, match="all degenerate"):
        Scene.from_arrays(v, [[0, 0, 1]])


def test_textured_material_needs_uvs():
    tex = Texture(np.ones((2, 2)), name="refl.png")
    with pytest.raises(SceneError, match="uvs are required"):
        Scene.from_arrays(QUAD_V, QUAD_T, materials=[Material(reflectance_texture=tex)])


def test_material_validation_names_field_and_value():
    with pytest.raises(ConfigError, match=r"Material 'paint': reflectance must be a number in \[0, 1\], got 1.5"):
        Material(name="paint", reflectance=1.5)
    with pytest.raises(ConfigError, match="roughness"):
        Material(roughness=-0.1)
    with pytest.raises(ConfigError, match="unknown key 'colour'"):
        Material.from_dict({"colour": 1.0})


def test_texture_bilinear_lookup_and_orientation():
    # Row 0 is the top of the image (v = 1).
    tex = Texture(np.array([[1.0, 2.0], [3.0, 4.0]]))
    uv = np.array([[0.25, 0.75], [0.75, 0.75], [0.25, 0.25], [0.75, 0.25], [0.5, 0.5]])
    np.testing.assert_allclose(tex.sample(uv), [1, 2, 3, 4, 2.5])
    with pytest.raises(ConfigError, match="finite"):
        Texture(np.array([[np.nan]]))


def test_save_load_round_trip(tmp_path):
    tex = Texture(np.linspace(0, 1, 12).reshape(3, 4), name="rough.png")
    normal_map = Texture(np.full((2, 2, 3), 0.5, np.float32) + [0, 0, 0.5], name="n.png")
    mats = [Material(name="a", reflectance=0.3), Material(name="b", roughness_texture=tex, normal_texture=normal_map)]
    uvs = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    s = Scene.from_arrays(QUAD_V, QUAD_T, [0, 1], mats, object_ids=[3, 4], uvs=uvs, normals=np.tile([0, 0, 1.0], (4, 1)),
                          object_names=["x"], name="q", metadata={"k": 1})
    path = s.save(tmp_path / "q.npz")
    r = Scene.load(path)
    for key in ("vertices", "triangles", "material_ids", "object_ids", "uvs", "normals"):
        np.testing.assert_array_equal(getattr(r, key), getattr(s, key))
    assert [m.to_dict() for m in r.materials] == [m.to_dict() for m in s.materials]
    np.testing.assert_array_equal(r.materials[1].roughness_texture.data, tex.data)
    assert r.materials[1].normal_texture.name == "n.png"
    assert r.name == "q" and r.metadata == {"k": 1} and r.object_names == ("x",)
    assert [p.name for p in tmp_path.iterdir()] == ["q.npz"]  # no temp file left behind


def test_load_errors_name_the_file(tmp_path):
    bad = tmp_path / "junk.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(SceneError, match="junk.npz"):
        Scene.load(bad)
    old = tmp_path / "old.npz"
    np.savez(old, format_version=np.array(99))
    with pytest.raises(SceneError, match=r"old.npz: format_version must be 1, got 99"):
        Scene.load(old)


@pytest.mark.parametrize("name", tofcore.scene.demo.NAMES)
def test_demo_scenes_build(name):
    s = tofcore.demo_scene(name)
    assert s.triangle_count > 0 and s.dropped_triangles == 0
    assert tofcore.suggested_pose(name and s).shape == (4, 4)
    assert len(tofcore.demo_scene(name, detail=8).triangles) > s.triangle_count


def test_demo_scene_rejects_unknown_name():
    with pytest.raises(ConfigError, match=r"name must be one of \['plane', 'corner', 'box_on_wall', 'room', "
                                          r"'textured_room'\], got 'cube'"):
        tofcore.demo_scene("cube")


def test_textured_room_is_the_room_open_to_its_sky():
    """The textured demo room: the room's geometry less its ceiling, every material textured, UVs in metres,
    a sky map whose sun is the brightest texel."""
    room, textured = tofcore.demo_scene("room", detail=2), tofcore.demo_scene("textured_room", detail=2)
    assert textured.triangle_count == room.triangle_count - 2 * 2 * 2
    assert all(m.textures for m in textured.materials) and textured.uvs.shape == (len(textured.vertices), 2)
    sky = tofcore.demo_ambient("textured_room").environment.data
    assert sky.shape == (32, 64) and sky.max() == 3.0 and np.isclose(sky.min(), 0.01)
    assert tofcore.demo_ambient("room") is None


def test_room_is_closed():
    """Rays from inside the room in every direction hit something."""
    s = tofcore.demo_scene("room")
    rng = np.random.default_rng(1)
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.tile([0.0, -1.0, 1.5], (2000, 1))
    hits = s.bvh.intersect(o.astype(np.float32), d.astype(np.float32))
    assert (hits.prim >= 0).all()


def test_look_at_frame():
    pose = tofcore.look_at((0, -2, 1), (0, 0, 1))
    np.testing.assert_allclose(pose[:3, 2], [0, 1, 0])   # z forward
    np.testing.assert_allclose(pose[:3, 0], [1, 0, 0])   # x right
    np.testing.assert_allclose(pose[:3, 1], [0, 0, -1])  # y down
    # Blender camera looking along +Y: rotation X by 90°; world_from_sensor = matrix_world @ diag(1,-1,-1,1).
    mw = np.array([[1, 0, 0, 0], [0, 0, -1, -2], [0, 1, 0, 1], [0, 0, 0, 1.0]])
    np.testing.assert_allclose(tofcore.from_blender_matrix_world(mw), pose, atol=1e-12)


def test_material_fields_follow_the_parameter_table():
    """Material's scalar fields, defaults, ranges and texture slots are the rows of material.PARAMETERS."""
    from dataclasses import fields

    from tofcore.scene.material import PARAMETER_NAMES, PARAMETERS, TEXTURE_SLOTS, Material

    scalars = [f for f in fields(Material) if f.name not in ("name",) and not f.name.endswith("_texture")]
    assert tuple(f.name for f in scalars) == PARAMETER_NAMES
    assert [f.default for f in scalars] == [p.default for p in PARAMETERS]
    assert tuple(f.name for f in fields(Material) if f.name.endswith("_texture")) == TEXTURE_SLOTS
    for p in PARAMETERS:
        with pytest.raises(ConfigError, match=rf"{p.name} must be a number in \[{p.low:g}, {p.high:g}\]"):
            Material(**{p.name: p.high + 1.0})
