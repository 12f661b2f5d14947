"""addon/export.py: evaluated Blender scene → tofcore.Scene, materials, world light, camera pose.

Needs the ``bpy`` module (skipped without it). Each test starts from a
factory-empty scene (``clean_bpy``) and builds its meshes with bmesh.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
import bmesh  # noqa: E402  (part of bpy)
import mathutils  # noqa: E402
from bpy_extras.object_utils import world_to_camera_view  # noqa: E402

import tofcore  # noqa: E402
from addon import export, mapping  # noqa: E402

pytestmark = pytest.mark.bpy


# =========================================================================== helpers
def add_cube(name, location=(0, 0, 0), collection=None, size=1.0):
    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=size)
    bm.to_mesh(mesh)
    bm.free()
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    (collection or bpy.context.scene.collection).objects.link(obj)
    return obj


def add_plane(name="Plane", size=10.0, location=(0, 0, 0)):
    mesh = bpy.data.meshes.new(name)
    h = size / 2
    mesh.from_pydata([(-h, -h, 0), (h, -h, 0), (h, h, 0), (-h, h, 0)], [], [(0, 1, 2, 3)])
    mesh.uv_layers.new(name="UVMap")
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    bpy.context.scene.collection.objects.link(obj)
    return obj


def depsgraph():
    return bpy.context.evaluated_depsgraph_get()


def blender_triangles(obj, matrix_world=None):
    """World-space triangles (M, 3, 3) of an object's evaluated mesh: the independent reference."""
    obj_eval = obj.evaluated_get(depsgraph())
    mesh = obj_eval.to_mesh()
    mesh.calc_loop_triangles()
    matrix = matrix_world if matrix_world is not None else obj.matrix_world
    tris = np.array([[tuple(matrix @ mesh.vertices[i].co) for i in lt.vertices] for lt in mesh.loop_triangles])
    obj_eval.to_mesh_clear()
    return tris.reshape(-1, 3, 3)


def exported_triangles(scene, object_name=None, names=None):
    tris = scene.triangles
    if object_name is not None:
        tris = tris[scene.object_ids == list(names).index(object_name)]
    return scene.vertices[tris].astype(np.float64)


def assert_same_triangles(got, want, atol=1e-5):
    """Same set of triangles (any order, any vertex rotation)."""
    assert got.shape == want.shape, (got.shape, want.shape)
    c_got, c_want = got.mean(axis=1), want.mean(axis=1)
    dist = np.linalg.norm(c_want[:, None, :] - c_got[None, :, :], axis=2)
    match = dist.argmin(axis=1)
    assert dist[np.arange(len(want)), match].max() < atol
    assert len(np.unique(match)) == len(match), "two reference triangles matched the same exported one"
    corner = np.linalg.norm(want[:, :, None, :] - got[match][:, None, :, :], axis=3).min(axis=2)
    assert corner.max() < atol


def principled(material):
    return next(n for n in material.node_tree.nodes if n.type == "BSDF_PRINCIPLED")


def new_material(name, **inputs):
    material = bpy.data.materials.new(name)
    if material.node_tree is None or not any(n.type == "BSDF_PRINCIPLED" for n in material.node_tree.nodes):
        material.use_nodes = True            # Blender < 5.0 only; 5.0 creates the node tree itself
    bsdf = principled(material)
    for key, value in inputs.items():
        bsdf.inputs[key].default_value = value
    return material


def new_image(name, pixels_bottom_up, *, float_buffer=True, colorspace=None):
    h, w, c = pixels_bottom_up.shape
    image = bpy.data.images.new(name, width=w, height=h, alpha=(c == 4), float_buffer=float_buffer)
    if colorspace is not None:
        image.colorspace_settings.name = colorspace
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :c] = pixels_bottom_up
    image.pixels.foreach_set(rgba.ravel())
    image.update()
    return image


def link_image(material, image, socket_name, output="Color"):
    tree = material.node_tree
    node = tree.nodes.new("ShaderNodeTexImage")
    node.image = image
    tree.links.new(node.outputs[output], principled(material).inputs[socket_name])
    return node


def gn_instance_on_points(obj, realize=False):
    """Geometry nodes on ``obj``: a cone instanced on every vertex (optionally realized)."""
    tree = bpy.data.node_groups.new("cones", "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    group_in, group_out = tree.nodes.new("NodeGroupInput"), tree.nodes.new("NodeGroupOutput")
    on_points, cone = tree.nodes.new("GeometryNodeInstanceOnPoints"), tree.nodes.new("GeometryNodeMeshCone")
    cone.inputs["Radius Bottom"].default_value = 0.2
    cone.inputs["Depth"].default_value = 0.5
    tree.links.new(group_in.outputs[0], on_points.inputs["Points"])
    tree.links.new(cone.outputs["Mesh"], on_points.inputs["Instance"])
    last = on_points.outputs[0]
    if realize:
        real = tree.nodes.new("GeometryNodeRealizeInstances")
        tree.links.new(last, real.inputs[0])
        last = real.outputs[0]
    tree.links.new(last, group_out.inputs[0])
    obj.modifiers.new("GeometryNodes", "NODES").node_group = tree


# =========================================================================== geometry
def test_export_matches_blender_evaluation(clean_bpy):
    """Subdivision, a collection instance, hidden objects: triangles and world positions as Blender evaluates."""
    scene = bpy.context.scene
    source = bpy.data.collections.new("Source")
    scene.collection.children.link(source)
    cube = add_cube("Cube", location=(0.3, -0.2, 1.0), collection=source)
    cube.rotation_euler = (0.3, 0.1, 0.7)
    cube.scale = (1.0, 2.0, 0.5)
    cube.modifiers.new("Subdivision", "SUBSURF").levels = 2
    source.instance_offset = (0.1, 0.0, 0.0)
    instancer = bpy.data.objects.new("Instancer", None)
    instancer.instance_type = "COLLECTION"
    instancer.instance_collection = source
    instancer.location = (0.0, 5.0, 0.0)
    instancer.rotation_euler = (0.0, 0.0, math.radians(30))
    scene.collection.objects.link(instancer)
    hidden = add_cube("Hidden", location=(9.0, 0.0, 0.0))
    hidden.hide_render = True
    off = bpy.data.collections.new("NotRendered")
    scene.collection.children.link(off)
    off.hide_render = True
    add_cube("InHiddenCollection", location=(-9.0, 0.0, 0.0), collection=off)
    bpy.context.view_layer.update()

    result = export.export_scene(depsgraph())
    names = result.object_names
    assert set(names) == {"Cube"}, "hidden objects must be absent"
    direct = blender_triangles(cube)
    instance_matrix = instancer.matrix_world @ mathutils.Matrix.Translation(-source.instance_offset) @ cube.matrix_world
    instanced = blender_triangles(cube, instance_matrix)
    assert len(direct) == 6 * 16 * 2                         # subdivision level 2 applied
    assert result.scene.triangle_count == 2 * len(direct)    # the instance is present: twice
    assert_same_triangles(exported_triangles(result.scene), np.concatenate([direct, instanced]))
    assert result.stats["instances"] == 2
    assert (np.abs(result.scene.vertices[:, 0]) < 8).all()   # nothing of the hidden cubes at x = ±9


def test_geometry_nodes_instances_are_expanded(clean_bpy):
    base = add_cube("Scatter", location=(1.0, 2.0, 0.5))
    base.rotation_euler = (0.0, 0.4, 0.2)
    gn_instance_on_points(base)
    reference = add_cube("Reference", location=(1.0, 2.0, 0.5))
    reference.rotation_euler = (0.0, 0.4, 0.2)
    gn_instance_on_points(reference, realize=True)
    reference.hide_render = True                              # only an independent evaluation of the same thing
    bpy.context.view_layer.update()

    result = export.export_scene(depsgraph())
    assert result.object_names == ("Scatter",)
    want = blender_triangles(reference)
    assert len(want) > 8
    assert_same_triangles(exported_triangles(result.scene), want)
    assert result.stats["instances"] == 8                    # one cone per cube corner


def test_geometry_nodes_materials_follow_the_instanced_geometry(clean_bpy):
    base = add_cube("Scatter")
    base.data.materials.append(new_material("BaseMaterial"))     # on the points only: not rendered
    gn_instance_on_points(base)
    red = new_material("Red", **{"Base Color": (1.0, 0.0, 0.0, 1.0)})
    tree = base.modifiers[0].node_group
    set_material = tree.nodes.new("GeometryNodeSetMaterial")
    set_material.inputs["Material"].default_value = red
    cone = next(n for n in tree.nodes if n.type == "MESH_PRIMITIVE_CONE")
    on_points = next(n for n in tree.nodes if n.type == "INSTANCE_ON_POINTS")
    tree.links.new(cone.outputs["Mesh"], set_material.inputs["Geometry"])
    tree.links.new(set_material.outputs[0], on_points.inputs["Instance"])
    bpy.context.view_layer.update()
    scene = export.export_scene(depsgraph()).scene
    assert [m.name for m in scene.materials] == ["Red"]


def test_object_ids_per_object_or_per_instance(clean_bpy):
    base = add_cube("Scatter")
    gn_instance_on_points(base)
    add_plane("Floor", location=(0, 0, -2))
    bpy.context.view_layer.update()
    per_object = export.export_scene(depsgraph())
    assert sorted(per_object.object_names) == ["Floor", "Scatter"]
    per_instance = export.export_scene(depsgraph(), object_ids="instance")
    assert len(per_instance.object_names) == 9
    assert len(set(per_instance.object_names)) == 9
    assert len(np.unique(per_instance.scene.object_ids)) == 9
    with pytest.raises(tofcore.ConfigError, match="object_ids must be one of"):
        export.export_scene(depsgraph(), object_ids="face")


def test_mirrored_instance_keeps_normals_consistent_with_winding(clean_bpy):
    cube = add_cube("Mirrored")
    cube.scale = (-1.0, 1.0, 1.0)
    bpy.context.view_layer.update()
    scene = export.export_scene(depsgraph()).scene
    shading = scene.normals[scene.triangles].mean(axis=1)
    assert (np.einsum("ij,ij->i", shading, scene.face_normals) > 0.99).all()
    # Flat cube faces point away from the centre.
    centroids = scene.vertices[scene.triangles].mean(axis=1)
    assert (np.einsum("ij,ij->i", centroids, scene.face_normals) > 0).all()


def test_nothing_visible_raises_scene_error(clean_bpy):
    add_cube("Hidden").hide_render = True
    empty_mesh = bpy.data.meshes.new("Points")
    empty_mesh.from_pydata([(0, 0, 0)], [], [])
    bpy.context.scene.collection.objects.link(bpy.data.objects.new("Points", empty_mesh))
    bpy.context.view_layer.update()
    with pytest.raises(tofcore.SceneError, match=r"nothing visible to render: .*1 objects hidden for render.*"
                                                 r"1 objects without faces \('Points'\)"):
        export.export_scene(depsgraph())


def test_empty_scene_raises_scene_error(clean_bpy):
    with pytest.raises(tofcore.SceneError, match="nothing visible to render"):
        export.export_scene(depsgraph())


def test_non_mesh_objects_are_skipped_with_a_warning(clean_bpy):
    add_plane()
    for i in range(3):
        curves = bpy.data.hair_curves.new(f"Hair{i}")
        curves.add_curves([2])
        bpy.context.scene.collection.objects.link(bpy.data.objects.new(f"Hair{i}", curves))
    bpy.context.view_layer.update()
    result = export.export_scene(depsgraph())
    assert result.object_names == ("Plane",)
    assert any(w.startswith("skipped 3 non-mesh objects (hair curves)") for w in result.warnings), result.warnings


def test_curves_with_bevel_and_text_are_exported_as_meshes(clean_bpy):
    text = bpy.data.curves.new("Label", "FONT")
    text.body = "ToF"
    text.extrude = 0.05
    bpy.context.scene.collection.objects.link(bpy.data.objects.new("Label", text))
    bpy.context.view_layer.update()
    result = export.export_scene(depsgraph())
    assert result.object_names == ("Label",)
    assert result.scene.triangle_count > 20


def test_viewport_hidden_objects_are_reported(clean_bpy):
    add_plane()
    add_cube("EyeHidden").hide_set(True)
    bpy.context.view_layer.update()
    result = export.export_scene(depsgraph())
    assert any("hidden in the viewport" in w and "'EyeHidden'" in w for w in result.warnings), result.warnings


def test_viewport_render_modifier_differences_are_reported(clean_bpy):
    cube = add_cube("Smooth")
    modifier = cube.modifiers.new("Subdivision", "SUBSURF")
    modifier.levels, modifier.render_levels = 1, 3
    bpy.context.view_layer.update()
    result = export.export_scene(depsgraph())
    assert result.scene.triangle_count == 6 * 4 * 2                 # viewport level 1
    assert any("set differently for viewport and render" in w and "'Smooth'" in w for w in result.warnings)


def test_corner_normals_and_uvs_are_exported(clean_bpy):
    plane = add_plane(size=2.0)
    plane.rotation_euler = (math.radians(90), 0, 0)           # normal +Z → −Y
    material = new_material("Textured")
    link_image(material, new_image("tex", np.full((2, 2, 3), 0.5, np.float32)), "Base Color")
    plane.data.materials.append(material)
    bpy.context.view_layer.update()
    scene = export.export_scene(depsgraph()).scene
    np.testing.assert_allclose(scene.normals, np.tile([0.0, -1.0, 0.0], (len(scene.normals), 1)), atol=1e-6)
    assert scene.uvs is not None and scene.uvs.shape == (len(scene.vertices), 2)
    assert set(map(tuple, np.round(scene.uvs, 6))) == {(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)}


def add_grid(n: int):
    """An n × n grid of quads (2 n² triangles) in the scene, built through foreach_set."""
    xs, ys = np.meshgrid(np.arange(n + 1, dtype=np.float32), np.arange(n + 1, dtype=np.float32))
    co = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size, np.float32)])
    i = np.arange(n)[None, :] + (n + 1) * np.arange(n)[:, None]
    quads = np.stack([i, i + 1, i + n + 2, i + n + 1], axis=-1).reshape(-1, 4).astype(np.int32)
    mesh = bpy.data.meshes.new("Grid")
    mesh.vertices.add(len(co))
    mesh.vertices.foreach_set("co", co.ravel())
    mesh.loops.add(quads.size)
    mesh.loops.foreach_set("vertex_index", quads.ravel())
    mesh.polygons.add(len(quads))
    mesh.polygons.foreach_set("loop_start", np.arange(0, quads.size, 4, dtype=np.int32))
    mesh.update()
    obj = bpy.data.objects.new("Grid", mesh)
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.view_layer.update()
    return obj


def lines_run(function) -> tuple[object, int]:
    """(result, number of Python lines of addon/ and tofcore/ that ``function()`` executed), by sys.settrace."""
    folders = tuple(str(Path(module.__file__).resolve().parent) for module in (export, tofcore))
    count = 0

    def tracer(frame, event, arg):
        nonlocal count
        if not frame.f_code.co_filename.startswith(folders):
            return None
        count += event == "line"
        return tracer

    previous = sys.gettrace()
    sys.settrace(tracer)
    try:
        result = function()
    finally:
        sys.settrace(previous)
    return result, count


def test_large_mesh_export_is_vectorized(clean_bpy):
    """No Python line runs per triangle: exporting 20,000 triangles executes as many lines of addon/ and tofcore/
    as exporting 200 (array code only; counted, not timed)."""
    runs = []
    for n in (10, 10, 100):                       # the first export warms up (imports, caches)
        bpy.ops.wm.read_factory_settings(use_empty=True)
        add_grid(n)
        result, lines = lines_run(lambda: export.export_scene(depsgraph()))
        assert result.scene.triangle_count == 2 * n * n
        runs.append(lines)
    assert runs[1] == runs[2] and runs[2] > 50, runs


# =========================================================================== materials
def test_principled_inputs_map_to_tofcore_fields(clean_bpy):
    plane = add_plane()
    material = new_material("Paint", **{"Base Color": (0.5, 0.2, 0.1, 1.0), "Roughness": 0.6, "Metallic": 0.0,
                                        "IOR": 1.45})
    plane.data.materials.append(material)
    bpy.context.view_layer.update()
    result = export.export_scene(depsgraph())
    (m,) = result.scene.materials
    assert m.name == "Paint"
    assert m.reflectance == pytest.approx(0.2126 * 0.5 + 0.7152 * 0.2 + 0.0722 * 0.1, rel=1e-5)
    assert m.roughness == pytest.approx(0.36 / math.sqrt(2), rel=1e-5)
    assert m.metallic == 0.0 and m.extinction == 0.0
    assert m.ior == pytest.approx(1.45, rel=1e-6)
    assert not result.warnings


def test_principled_coat_maps_to_the_clear_coat(clean_bpy):
    """Blender's Coat Weight and Coat Roughness → tofcore's clear coat (mapping.material_fields)."""
    material = new_material("Lacquer", **{"Base Color": (0.2, 0.2, 0.2, 1.0), "Coat Weight": 0.8,
                                          "Coat Roughness": 0.2})
    m = export.material_from_blender(material)
    assert m.coat == pytest.approx(0.8, rel=1e-6)
    assert m.coat_roughness == pytest.approx(0.04 / math.sqrt(2), rel=1e-5)
    assert export.material_from_blender(new_material("Plain")).coat == 0.0


def test_metal_reflectance_sets_extinction(clean_bpy):
    material = new_material("Alu", **{"Base Color": (0.9, 0.9, 0.9, 1.0), "Metallic": 1.0, "IOR": 1.5})
    m = export.material_from_blender(material)
    assert m.metallic == 1.0
    assert mapping.f0_from_extinction(m.ior, m.extinction) == pytest.approx(0.9, abs=1e-5)


def test_slots_map_to_a_deduplicated_material_list(clean_bpy):
    red = new_material("Red", **{"Base Color": (1.0, 0.0, 0.0, 1.0)})
    green = new_material("Green", **{"Base Color": (0.0, 1.0, 0.0, 1.0)})
    a = add_cube("A")
    a.data.materials.append(red)
    a.data.materials.append(green)
    a.data.polygons.foreach_set("material_index", np.array([0, 1, 1, 0, 0, 0], np.int32))
    b = add_cube("B", location=(3, 0, 0))
    b.data.materials.append(green)
    add_cube("Bare", location=(-3, 0, 0))
    bpy.context.view_layer.update()
    scene = export.export_scene(depsgraph()).scene
    names = [m.name for m in scene.materials]
    assert sorted(names) == ["(no material)", "Green", "Red"]
    by_object = {name: scene.material_ids[scene.object_ids == i] for i, name in enumerate(scene.object_names)}
    assert np.sum(by_object["A"] == names.index("Green")) == 4      # 2 quads → 4 triangles
    assert np.sum(by_object["A"] == names.index("Red")) == 8
    assert (by_object["B"] == names.index("Green")).all()
    default = scene.materials[names.index("(no material)")]
    assert default.reflectance == pytest.approx(0.8, rel=1e-6)      # Blender's grey default surface


def test_base_color_texture_becomes_reflectance_texture_top_down(clean_bpy):
    pixels = np.zeros((2, 3, 3), np.float32)                  # Blender rows, bottom-up
    pixels[0] = (0.1, 0.1, 0.1)                               # bottom row
    pixels[1] = (0.9, 0.9, 0.9)                               # top row
    material = new_material("Checker")
    link_image(material, new_image("checker", pixels), "Base Color")
    m = export.material_from_blender(material)
    tex = m.reflectance_texture
    assert tex is not None and tex.data.shape == (2, 3)
    np.testing.assert_allclose(tex.data[0], 0.9, rtol=1e-5)   # row 0 = top
    np.testing.assert_allclose(tex.data[1], 0.1, rtol=1e-5)


def test_srgb_byte_images_are_decoded_to_linear(clean_bpy):
    material = new_material("Byte")
    link_image(material, new_image("byte", np.full((2, 2, 3), 0.5, np.float32), float_buffer=False,
                                   colorspace="sRGB"), "Base Color")
    m = export.material_from_blender(material)
    expected = float(mapping.srgb_to_linear(np.float32(128 / 255)))
    np.testing.assert_allclose(m.reflectance_texture.data, expected, rtol=1e-3)


def test_roughness_and_normal_map_textures(clean_bpy):
    material = new_material("Rough")
    rough = new_image("rough", np.full((2, 2, 3), 0.5, np.float32), colorspace="Non-Color")
    link_image(material, rough, "Roughness")
    tree = material.node_tree
    normal_map = tree.nodes.new("ShaderNodeNormalMap")
    normal_image = tree.nodes.new("ShaderNodeTexImage")
    normal_image.image = new_image("normal", np.tile(np.float32([0.5, 0.5, 1.0]), (4, 4, 1)))
    tree.links.new(normal_image.outputs["Color"], normal_map.inputs["Color"])
    tree.links.new(normal_map.outputs["Normal"], principled(material).inputs["Normal"])
    warnings = []
    m = export.material_from_blender(material, warnings=warnings)
    np.testing.assert_allclose(m.roughness_texture.data, 0.25 / math.sqrt(2), rtol=1e-5)
    assert m.normal_texture.data.shape == (4, 4, 3)
    np.testing.assert_allclose(m.normal_texture.data[0, 0], (0.5, 0.5, 1.0))
    assert not warnings


def test_a_coloured_map_on_roughness_or_metallic_counts_its_luminance(clean_bpy):
    """Blender converts a colour linked to a number input by its luminance: a red-only roughness or metallic
    map is 0.2126 of its red, not its red (the exporter took the red channel before)."""
    material = new_material("Tinted")
    red = new_image("red", np.tile(np.float32([0.8, 0.0, 0.0]), (2, 2, 1)), colorspace="Non-Color")
    link_image(material, red, "Roughness")
    link_image(material, red, "Metallic")
    m = export.material_from_blender(material)
    grey = 0.2126 * 0.8
    np.testing.assert_allclose(m.roughness_texture.data, grey**2 / math.sqrt(2), rtol=1e-5)
    np.testing.assert_allclose(m.metallic_texture.data, grey, rtol=1e-5)


def test_missing_texture_file_warns_with_its_path(clean_bpy):
    plane = add_plane()
    material = new_material("Wall")
    image = bpy.data.images.new("wall", 4, 4)
    image.source = "FILE"
    image.filepath = "/nonexistent/textures/wall_albedo.png"
    link_image(material, image, "Base Color")
    plane.data.materials.append(material)
    bpy.context.view_layer.update()
    result = export.export_scene(depsgraph())
    assert "missing texture file /nonexistent/textures/wall_albedo.png on material 'Wall'" in result.warnings
    assert result.scene.materials[0].reflectance_texture is None


def _ensure_material_override_property():
    """Register a stand-in ``material.tof`` unless the add-on's is registered; returns a cleanup function."""
    if "tof" in bpy.types.Material.bl_rna.properties:
        return lambda: None

    class TofMaterialStandIn(bpy.types.PropertyGroup):
        use_override: bpy.props.BoolProperty()
        reflectance: bpy.props.FloatProperty(min=0.0, max=1.0)
        roughness: bpy.props.FloatProperty(min=0.0, max=math.pi / 2)
        extinction: bpy.props.FloatProperty(min=0.0)

    bpy.utils.register_class(TofMaterialStandIn)
    bpy.types.Material.tof = bpy.props.PointerProperty(type=TofMaterialStandIn)

    def cleanup():
        del bpy.types.Material.tof
        bpy.utils.unregister_class(TofMaterialStandIn)

    return cleanup


def test_ir_override_wins_over_principled_and_textures(clean_bpy):
    cleanup = _ensure_material_override_property()
    try:
        material = new_material("Leaf", **{"Base Color": (0.05, 0.3, 0.05, 1.0), "Roughness": 0.9,
                                           "Metallic": 1.0})
        link_image(material, new_image("leaf", np.full((2, 2, 3), 0.2, np.float32)), "Base Color")
        derived = export.material_from_blender(material)
        assert derived.reflectance_texture is not None
        material.tof.use_override = True
        material.tof.reflectance = 0.55
        material.tof.roughness = 0.3
        material.tof.extinction = 4.0
        m = export.material_from_blender(material)
        assert (m.reflectance, m.roughness, m.extinction) == pytest.approx((0.55, 0.3, 4.0))
        assert m.reflectance_texture is None
        material.tof.use_override = False
        assert export.material_from_blender(material).reflectance == pytest.approx(derived.reflectance)
    finally:
        cleanup()


def test_non_principled_surface_warns_and_uses_viewport_colour(clean_bpy):
    material = bpy.data.materials.new("Glow")
    if material.node_tree is None:
        material.use_nodes = True
    tree = material.node_tree
    for node in list(tree.nodes):
        if node.type == "BSDF_PRINCIPLED":
            tree.nodes.remove(node)
    emission = tree.nodes.new("ShaderNodeEmission")
    output = next(n for n in tree.nodes if n.type == "OUTPUT_MATERIAL")
    tree.links.new(emission.outputs[0], output.inputs["Surface"])
    material.diffuse_color = (0.2, 0.2, 0.2, 1.0)
    warnings = []
    m = export.material_from_blender(material, warnings=warnings)
    assert m.reflectance == pytest.approx(0.2, rel=1e-5)
    assert any("'Glow'" in w and "Emission" in w for w in warnings), warnings


def test_principled_inside_a_mix_shader_is_found(clean_bpy):
    material = new_material("Mixed", **{"Base Color": (0.3, 0.3, 0.3, 1.0)})
    tree = material.node_tree
    mix = tree.nodes.new("ShaderNodeMixShader")
    reroute = tree.nodes.new("NodeReroute")
    output = next(n for n in tree.nodes if n.type == "OUTPUT_MATERIAL")
    tree.links.new(principled(material).outputs[0], reroute.inputs[0])
    tree.links.new(reroute.outputs[0], mix.inputs[2])
    tree.links.new(mix.outputs[0], output.inputs["Surface"])
    warnings = []
    m = export.material_from_blender(material, warnings=warnings)
    assert m.reflectance == pytest.approx(0.3, rel=1e-5)
    assert any("Mix Shader" in w for w in warnings), warnings


class _WithOverride:
    """A Blender material seen through a different ``tof`` (values beyond the property limits)."""

    def __init__(self, material, **tof):
        self._material = material
        self.tof = type("Tof", (), tof)()

    def __getattr__(self, name):
        return getattr(self._material, name)


def test_invalid_override_names_the_material(clean_bpy):
    material = new_material("Bad")
    proxy = _WithOverride(material, use_override=True, reflectance=1.5, roughness=0.2, extinction=0.0)
    with pytest.raises(tofcore.ConfigError, match=r"material 'Bad' \(near-IR override\): .*reflectance"):
        export.material_from_blender(proxy)


# =========================================================================== world
def _world(color=(0.05, 0.05, 0.05, 1.0), strength=1.0):
    world = bpy.data.worlds.new("World")
    if world.node_tree is None:
        world.use_nodes = True                # Blender < 5.0
    background = next(n for n in world.node_tree.nodes if n.type == "BACKGROUND")
    background.inputs["Color"].default_value = color
    background.inputs["Strength"].default_value = strength
    bpy.context.scene.world = world
    return world, background


def test_world_colour_becomes_constant_ambient(clean_bpy):
    add_plane()
    _world(color=(0.2, 0.4, 0.6, 1.0), strength=2.0)
    result = export.export_scene(depsgraph(), ambient_scale=0.5)
    lum = 0.2126 * 0.2 + 0.7152 * 0.4 + 0.0722 * 0.6
    assert result.ambient.radiance_w_m2_sr == pytest.approx(lum * 2.0 * 0.5, rel=1e-5)
    assert result.ambient.environment is None


def test_no_world_or_black_world_gives_no_ambient(clean_bpy):
    add_plane()
    assert export.export_scene(depsgraph()).ambient is None
    _world(color=(0.0, 0.0, 0.0, 1.0))
    assert export.export_scene(depsgraph()).ambient is None
    _world(strength=0.0)
    assert export.export_scene(depsgraph()).ambient is None


def test_environment_texture_becomes_equirect_map_zenith_first(clean_bpy):
    add_plane()
    world, background = _world(strength=3.0)
    pixels = np.zeros((4, 8, 3), np.float32)                  # bottom-up: row 3 is the top (zenith)
    pixels[3] = 1.0
    env = world.node_tree.nodes.new("ShaderNodeTexEnvironment")
    env.image = new_image("sky", pixels)
    world.node_tree.links.new(env.outputs["Color"], background.inputs["Color"])
    ambient = export.export_scene(depsgraph()).ambient
    assert ambient.environment.data.shape == (4, 8)
    np.testing.assert_allclose(ambient.environment.data[0], 1.0, rtol=1e-5)
    np.testing.assert_allclose(ambient.environment.data[1:], 0.0)
    assert ambient.environment_strength == pytest.approx(3.0)
    up, down = ambient.radiance(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]))
    assert up == pytest.approx(3.0, rel=1e-4) and down == pytest.approx(0.0, abs=1e-6)


# =========================================================================== camera
def _add_camera(name="ToF"):
    cam = bpy.data.objects.new(name, bpy.data.cameras.new(name))
    bpy.context.scene.collection.objects.link(cam)
    return cam


def _random_points_in_view(world_from_sensor, camera, rng, n=300):
    """World points that project inside the image of ``camera`` (pinhole), 0.5–20 m away."""
    u = rng.uniform(-0.5, camera.width - 0.5, n)
    v = rng.uniform(-0.5, camera.height - 0.5, n)
    z = rng.uniform(0.5, 20.0, n)
    sensor = np.column_stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z])
    return sensor @ world_from_sensor[:3, :3].T + world_from_sensor[:3, 3]


def _blender_pixels(scene, cam, world_points):
    """world_to_camera_view → OpenCV pixel coordinates (centre of column 0 at u = 0)."""
    w = scene.render.resolution_x * scene.render.resolution_percentage // 100
    h = scene.render.resolution_y * scene.render.resolution_percentage // 100
    ndc = np.array([tuple(world_to_camera_view(scene, cam, mathutils.Vector(p))) for p in world_points])
    return np.column_stack([ndc[:, 0] * w - 0.5, (1.0 - ndc[:, 1]) * h - 0.5])


@pytest.mark.parametrize("preset", tofcore.list_presets())
def test_camera_round_trip_matches_world_to_camera_view(clean_bpy, preset):
    """A world point projected by tofcore with the exported pose lands where Blender projects it."""
    scene = bpy.context.scene
    add_plane(size=100.0, location=(0, 0, -5))
    camera = tofcore.load_preset(preset).camera
    pinhole = tofcore.Camera(width=camera.width, height=camera.height, fx=camera.fx, fy=camera.fy,
                             cx=camera.cx, cy=camera.cy)          # Blender has no OpenCV distortion
    cam = _add_camera()
    export.apply_camera_intrinsics(cam, scene, width=camera.width, height=camera.height, fx=camera.fx,
                                   fy=camera.fy, cx=camera.cx, cy=camera.cy)
    cam.location = (1.5, -4.0, 2.2)
    cam.rotation_euler = (math.radians(70), math.radians(8), math.radians(25))
    cam.scale = (1.3, 1.3, 1.3)                                   # scale must not change the projection
    bpy.context.view_layer.update()

    intrinsics = export.camera_intrinsics(cam, scene)
    for key in ("width", "height", "fx", "fy", "cx", "cy"):
        assert intrinsics[key] == pytest.approx(getattr(camera, key), rel=1e-6), key

    result = export.export_scene(depsgraph(), cam)
    pose = result.world_from_sensor
    np.testing.assert_allclose(result.scene.metadata["world_from_sensor"], pose)
    np.testing.assert_allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-6)
    world = _random_points_in_view(pose, pinhole, np.random.default_rng(7))
    sensor_from_world = np.linalg.inv(pose)
    tof_px = pinhole.project(world @ sensor_from_world[:3, :3].T + sensor_from_world[:3, 3])
    blender_px = _blender_pixels(scene, cam, world)
    assert np.abs(tof_px - blender_px).max() < 1e-3


@pytest.mark.parametrize("fit, resolution, aspect, percentage", [
    ("AUTO", (300, 500), (1.0, 1.0), 100),
    ("AUTO", (640, 360), (2.0, 1.0), 50),
    ("VERTICAL", (400, 300), (1.0, 1.6), 100),
])
def test_intrinsics_of_any_blender_camera_match_world_to_camera_view(clean_bpy, fit, resolution, aspect,
                                                                     percentage):
    scene = bpy.context.scene
    cam = _add_camera()
    data = cam.data
    data.lens, data.sensor_width, data.sensor_height, data.sensor_fit = 35.0, 32.0, 20.0, fit
    data.shift_x, data.shift_y = -0.08, 0.12
    scene.render.resolution_x, scene.render.resolution_y = resolution
    scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = aspect
    scene.render.resolution_percentage = percentage
    cam.location = (0.5, 0.2, 1.0)
    cam.rotation_euler = (math.radians(80), 0.0, math.radians(-40))
    bpy.context.view_layer.update()
    k = export.camera_intrinsics(cam, scene)
    pinhole = tofcore.Camera(width=k["width"], height=k["height"], fx=k["fx"], fy=k["fy"], cx=k["cx"], cy=k["cy"])
    pose = export.camera_pose(cam)
    world = _random_points_in_view(pose, pinhole, np.random.default_rng(3), n=100)
    sensor_from_world = np.linalg.inv(pose)
    tof_px = pinhole.project(world @ sensor_from_world[:3, :3].T + sensor_from_world[:3, 3])
    assert np.abs(tof_px - _blender_pixels(scene, cam, world)).max() < 1e-3


def test_camera_errors(clean_bpy):
    add_plane()
    cam = _add_camera()
    cam.data.type = "ORTHO"
    with pytest.raises(tofcore.ConfigError, match="type must be 'PERSP'"):
        export.camera_intrinsics(cam, bpy.context.scene)
    with pytest.raises(tofcore.ConfigError, match="camera_obj must be a camera object, got 'Plane'"):
        export.export_scene(depsgraph(), bpy.data.objects["Plane"])
