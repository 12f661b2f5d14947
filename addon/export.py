"""Blender scene → :class:`tofcore.Scene`, :class:`tofcore.Ambient` and the sensor pose.

:func:`export_scene` reads an *evaluated* depsgraph, so what it exports is
what Blender shows: modifiers and geometry nodes applied, collection and
geometry-nodes instances expanded (``depsgraph.object_instances`` with each
instance's ``matrix_world``), world transforms applied. Geometry is read with
``foreach_get`` into preallocated NumPy arrays, never vertex by vertex.

What is exported
----------------
* Objects whose evaluated geometry converts to a mesh (meshes, curves with
  bevel or extrusion, surfaces, text, metaballs) and has faces. Hair curves,
  point clouds, volumes and grease pencil are skipped with a warning that
  counts them.
* Only objects visible to the render: ``hide_render`` on the object, on the
  instancer, or on every collection that holds it (the camera icon in the
  outliner) hides it. The depsgraph passed in decides the rest: the viewport
  depsgraph (``context.evaluated_depsgraph_get()``) leaves out objects hidden
  in the viewport and excluded collections, and evaluates modifiers with their
  viewport settings; the export warns about objects hidden in the viewport
  that would render and about modifiers set differently for the render.
* One vertex per face corner (Blender "loop"), so split normals and UV seams
  survive: ``vertices`` and ``normals`` (``mesh.corner_normals``: smooth,
  flat and custom normals as Blender shades them) and ``uvs`` of the active
  UV map. Mirrored instances (negative determinant) get their winding flipped.
* ``object_ids``: one id per Blender object by default (all instances of an
  object share it), or one per instance with ``object_ids="instance"``.
* Materials from each face's slot, deduplicated by Blender material, mapped
  as documented in :mod:`addon.mapping` (the table there); faces without a
  material get Blender's default surface (grey 0.8, roughness 0.5).
* Ambient light from the world (see :mod:`addon.mapping`): a world colour is
  not a near-IR radiance, so ``ambient_scale`` (default 1.0) converts it;
  no world or a black one gives no ambient light.
* The sensor pose of ``camera_obj``: ``world_from_sensor = matrix_world @
  diag(1, −1, −1, 1)`` (:func:`tofcore.scene.pose.from_blender_matrix_world`), with
  any object scale removed as Blender's own projection does.

Example
-------
>>> result = export_scene(bpy.context.evaluated_depsgraph_get(), bpy.context.scene.camera)
>>> frame = tofcore.render(result.scene, sensor, result.world_from_sensor, ambient=result.ambient)
"""

from __future__ import annotations

import os
import time
from collections import defaultdict
from dataclasses import dataclass, field

import bpy
import numpy as np

import tofcore

from . import mapping

#: Object types whose evaluated geometry ``Object.to_mesh()`` turns into a mesh.
MESH_LIKE_TYPES = frozenset({"MESH", "CURVE", "SURFACE", "FONT", "META"})
#: Renderable object types the simulator cannot trace (skipped with a warning).
UNSUPPORTED_TYPES = {"CURVES": "hair curves", "POINTCLOUD": "point clouds", "VOLUME": "volumes",
                     "GREASEPENCIL": "grease pencil", "GPENCIL": "grease pencil"}
OBJECT_ID_MODES = ("object", "instance")


@dataclass
class ExportResult:
    """What :func:`export_scene` returns.

    Attributes
    ----------
    scene : the triangles, materials and object ids, metres, Blender's world frame.
    world_from_sensor : 4×4 pose of the camera's sensor (OpenCV axes), or None without a camera.
    ambient : background light, or None when the world is missing or black.
    warnings : one sentence per problem the user should know about (skipped objects, missing files…).
    object_names : the name of each object id (``scene.object_ids`` indexes it).
    stats : counts and timing: ``objects``, ``instances``, ``triangles``, ``materials``, ``seconds``.
    """

    scene: tofcore.Scene
    world_from_sensor: np.ndarray | None
    ambient: tofcore.Ambient | None
    warnings: list[str] = field(default_factory=list)
    object_names: tuple[str, ...] = ()
    stats: dict = field(default_factory=dict)


# =========================================================================== entry point
def export_scene(depsgraph, camera_obj=None, *, ambient_scale: float = 1.0,
                 object_ids: str = "object") -> ExportResult:
    """Export the evaluated scene of ``depsgraph`` for the simulator.

    Parameters
    ----------
    depsgraph : bpy.types.Depsgraph
        Usually ``context.evaluated_depsgraph_get()``.
    camera_obj : bpy.types.Object, optional
        The ToF camera; its pose becomes ``world_from_sensor``.
    ambient_scale : float
        W m⁻² sr⁻¹ per unit of world luminance × strength (default 1.0).
    object_ids : "object" or "instance"
        One object id per Blender object, or one per instance.

    Raises
    ------
    tofcore.SceneError
        When nothing visible to the render has faces.
    tofcore.ConfigError
        For a camera object that is not a camera, or an invalid material override.
    """
    start = time.perf_counter()
    if object_ids not in OBJECT_ID_MODES:
        raise tofcore.ConfigError(f"export_scene: object_ids must be one of {list(OBJECT_ID_MODES)}, "
                                  f"got {object_ids!r}")
    if camera_obj is not None and camera_obj.type != "CAMERA":
        raise tofcore.ConfigError(f"export_scene: camera_obj must be a camera object, got {camera_obj.name!r} "
                                  f"of type {camera_obj.type}")
    bl_scene = depsgraph.scene
    warnings: list[str] = []
    builder = _SceneBuilder(warnings, object_ids, bl_scene.collection)
    builder.add_instances(depsgraph)
    _warn_viewport_differences(depsgraph, builder, warnings)

    if not builder.triangles:
        raise tofcore.SceneError(f"nothing visible to render: {builder.describe_nothing()}")
    pose = camera_pose(camera_obj, depsgraph) if camera_obj is not None else None
    metadata = {
        "source": "blender",
        "blender_version": bpy.app.version_string,
        "blend_file": bpy.data.filepath,
        "blender_scene": bl_scene.name,
        "frame": bl_scene.frame_current,
    }
    if pose is not None:          # tofcore.render uses it when no pose is passed
        metadata.update(world_from_sensor=pose.tolist(), camera=camera_obj.name)
    scene = builder.build(name=bl_scene.name, metadata=metadata)
    if scene.dropped_triangles:
        warnings.append(f"dropped {scene.dropped_triangles} degenerate (zero-area) triangles")
    ambient = ambient_from_world(bl_scene.world, ambient_scale=ambient_scale, warnings=warnings)
    stats = {
        "objects": len(builder.object_names),
        "instances": builder.instance_count,
        "triangles": scene.triangle_count,
        "vertices": len(scene.vertices),
        "materials": len(scene.materials),
        "seconds": time.perf_counter() - start,
    }
    return ExportResult(scene=scene, world_from_sensor=pose, ambient=ambient, warnings=warnings,
                        object_names=scene.object_names, stats=stats)


# =========================================================================== camera
def camera_pose(camera_obj, depsgraph=None) -> np.ndarray:
    """``world_from_sensor`` (4×4, OpenCV sensor axes) of a Blender camera object, scale removed."""
    obj = camera_obj.evaluated_get(depsgraph) if depsgraph is not None else camera_obj
    matrix = np.array(obj.matrix_world, dtype=np.float64)
    norms = np.linalg.norm(matrix[:3, :3], axis=0)
    if (norms < 1e-12).any():
        raise tofcore.ConfigError(f"camera {camera_obj.name!r}: matrix_world must not have a zero scale, "
                                  f"got column lengths {norms.tolist()}")
    matrix[:3, :3] /= norms
    return tofcore.scene.pose.from_blender_matrix_world(matrix)


def camera_intrinsics(camera_obj, scene) -> dict:
    """Pinhole intrinsics (``width``, ``height``, ``fx``, ``fy``, ``cx``, ``cy``; OpenCV convention).

    From the camera's lens, sensor and shift and the scene's render
    resolution, percentage and pixel aspect (:func:`mapping.intrinsics_from_blender_camera`).
    """
    cam = camera_obj.data
    if cam.type != "PERSP":
        raise tofcore.ConfigError(f"camera {camera_obj.name!r}: type must be 'PERSP' (perspective), "
                                  f"got {cam.type!r}")
    render = scene.render
    return mapping.intrinsics_from_blender_camera(
        lens_mm=cam.lens, sensor_width_mm=cam.sensor_width, sensor_height_mm=cam.sensor_height,
        sensor_fit=cam.sensor_fit, shift_x=cam.shift_x, shift_y=cam.shift_y,
        resolution_x=render.resolution_x, resolution_y=render.resolution_y,
        pixel_aspect_x=render.pixel_aspect_x, pixel_aspect_y=render.pixel_aspect_y,
        resolution_percentage=render.resolution_percentage)


def apply_camera_intrinsics(camera_obj, scene, *, width: int, height: int, fx: float, fy: float,
                            cx: float, cy: float) -> dict:
    """Set a camera's lens, sensor and shift and the scene's render size so they reproduce the intrinsics.

    Sets the resolution percentage to 100. Returns the settings applied
    (:func:`mapping.blender_camera_from_intrinsics`).
    """
    settings = mapping.blender_camera_from_intrinsics(width, height, fx, fy, cx, cy)
    cam = camera_obj.data
    cam.type = "PERSP"
    cam.sensor_fit = settings["sensor_fit"]
    cam.sensor_width = settings["sensor_width_mm"]
    cam.sensor_height = settings["sensor_height_mm"]
    cam.lens_unit = "MILLIMETERS"
    cam.lens = settings["lens_mm"]
    cam.shift_x = settings["shift_x"]
    cam.shift_y = settings["shift_y"]
    render = scene.render
    render.resolution_x = settings["resolution_x"]
    render.resolution_y = settings["resolution_y"]
    render.resolution_percentage = 100
    render.pixel_aspect_x = settings["pixel_aspect_x"]
    render.pixel_aspect_y = settings["pixel_aspect_y"]
    return settings


# =========================================================================== geometry
@dataclass
class _Geometry:
    """One evaluated mesh in its object's local frame, one vertex per face corner."""

    positions: np.ndarray          # (L, 3) float32, local frame
    normals: np.ndarray            # (L, 3) float32, local frame
    uvs: np.ndarray | None         # (L, 2) float32 of the active UV map
    triangles: np.ndarray          # (M, 3) int32 corner indices
    material_ids: np.ndarray       # (M,) int32 into the global material list


class _SceneBuilder:
    """Collects transformed geometry instance by instance, then builds one tofcore.Scene."""

    def __init__(self, warnings: list[str], object_id_mode: str, scene_collection) -> None:
        self.warnings = warnings
        self.object_id_mode = object_id_mode
        self.materials = _MaterialTable(warnings)
        self.geometry_cache: dict[tuple[int, int], _Geometry | None] = {}
        self.visibility = _RenderVisibility(scene_collection)
        self.object_ids: dict[tuple, int] = {}
        self.instance_numbers: dict[tuple[str, str], int] = defaultdict(int)
        self.object_names: list[str] = []
        self.exported_originals: set[int] = set()
        self.instance_count = 0
        self.vertex_count = 0
        self.skipped_unsupported: dict[str, set[str]] = defaultdict(set)
        self.skipped_hidden: set[str] = set()
        self.skipped_empty: set[str] = set()
        self.failed: set[str] = set()
        self.without_uvs: set[str] = set()
        # Per exported instance, concatenated in build():
        self.positions: list[np.ndarray] = []
        self.normals: list[np.ndarray] = []
        self.uvs: list[np.ndarray | None] = []
        self.triangles: list[np.ndarray] = []
        self.material_ids: list[np.ndarray] = []
        self.instance_object_ids: list[int] = []

    # ---------------------------------------------------------------- traversal
    def add_instances(self, depsgraph) -> None:
        for inst in depsgraph.object_instances:
            obj = inst.object
            kind = obj.type
            if kind not in MESH_LIKE_TYPES:
                if kind in UNSUPPORTED_TYPES:
                    self.skipped_unsupported[UNSUPPORTED_TYPES[kind]].add(obj.original.name)
                continue
            parent = inst.parent if inst.is_instance else None
            if not self.visibility.renders(obj, parent):
                self.skipped_hidden.add(obj.original.name)
                continue
            if not inst.is_instance and obj.is_instancer and not obj.original.show_instancer_for_render:
                continue
            geometry = self._geometry(obj)
            if geometry is None:
                continue
            self._add(inst, obj, parent, geometry)

    def _geometry(self, obj) -> _Geometry | None:
        key = (obj.original.as_pointer(), obj.data.as_pointer() if obj.data is not None else 0)
        if key not in self.geometry_cache:
            self.geometry_cache[key] = self._read_geometry(obj)
        return self.geometry_cache[key]

    def _read_geometry(self, obj) -> _Geometry | None:
        name = obj.original.name
        try:
            mesh = obj.to_mesh()
        except RuntimeError as error:
            self.failed.add(f"{name} ({error})")
            return None
        try:
            if mesh is None or len(mesh.polygons) == 0:
                self.skipped_empty.add(name)
                return None
            return self._mesh_arrays(obj, mesh)
        finally:
            obj.to_mesh_clear()

    def _mesh_arrays(self, obj, mesh) -> _Geometry | None:
        mesh.calc_loop_triangles()
        n_tri, n_loop, n_vert = len(mesh.loop_triangles), len(mesh.loops), len(mesh.vertices)
        if n_tri == 0:
            self.skipped_empty.add(obj.original.name)
            return None
        co = np.empty(n_vert * 3, dtype=np.float32)
        mesh.vertices.foreach_get("co", co)
        loop_vertex = np.empty(n_loop, dtype=np.int32)
        mesh.loops.foreach_get("vertex_index", loop_vertex)
        corner_normals = np.empty(n_loop * 3, dtype=np.float32)
        mesh.corner_normals.foreach_get("vector", corner_normals)
        triangles = np.empty(n_tri * 3, dtype=np.int32)
        mesh.loop_triangles.foreach_get("loops", triangles)
        slot_index = np.empty(n_tri, dtype=np.int32)
        mesh.loop_triangles.foreach_get("material_index", slot_index)
        uvs = None
        if mesh.uv_layers.active is not None:
            uvs = np.empty(n_loop * 2, dtype=np.float32)
            mesh.uv_layers.active.uv.foreach_get("vector", uvs)
            uvs = uvs.reshape(n_loop, 2)
        n_slots = max(len(mesh.materials), len(obj.material_slots), 1)
        slot_index = np.clip(slot_index, 0, n_slots - 1)        # Blender clamps too
        slot_to_global = self._slot_materials(obj, mesh, np.unique(slot_index), n_slots)
        material_ids = slot_to_global[slot_index]
        if uvs is None and any(self.materials.textured[i] for i in np.unique(material_ids)):
            self.without_uvs.add(obj.original.name)
        return _Geometry(positions=co.reshape(n_vert, 3)[loop_vertex], normals=corner_normals.reshape(n_loop, 3),
                         uvs=uvs, triangles=triangles.reshape(n_tri, 3), material_ids=material_ids)

    def _slot_materials(self, obj, mesh, used_slots: np.ndarray, n_slots: int) -> np.ndarray:
        """Global material index of each used material slot (−1 for unused slots).

        Blender's rule: a slot linked to the object wins, else the evaluated
        mesh's own material list; an empty slot renders Blender's default surface.
        """
        slots = obj.material_slots
        out = np.full(n_slots, -1, dtype=np.int32)
        for i in used_slots.tolist():
            if i < len(slots) and slots[i].link == "OBJECT":
                material = slots[i].material
            else:
                material = mesh.materials[i] if i < len(mesh.materials) else None
            out[i] = self.materials.index(material)
        return out

    def _add(self, inst, obj, parent, geometry: _Geometry) -> None:
        matrix = np.array(inst.matrix_world, dtype=np.float64)
        linear = matrix[:3, :3]
        det = np.linalg.det(linear)
        if abs(det) < 1e-18:
            self.skipped_empty.add(obj.original.name)
            return
        positions = geometry.positions @ linear.T + matrix[:3, 3]
        normals = geometry.normals @ np.linalg.inv(linear)     # (A⁻ᵀ n) as rows: n · A⁻¹
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        bad = ~(length[:, 0] > 1e-12)
        if bad.any():                                          # zero normals of degenerate faces
            normals[bad], length[bad] = (0.0, 0.0, 1.0), 1.0
        normals /= length
        triangles = geometry.triangles if det > 0 else geometry.triangles[:, [0, 2, 1]]

        offset = self.vertex_count
        self.vertex_count += len(positions)
        self.positions.append(positions.astype(np.float32))
        self.normals.append(normals.astype(np.float32))
        self.uvs.append(geometry.uvs)
        self.triangles.append(triangles + offset)
        self.material_ids.append(geometry.material_ids)
        self.instance_object_ids.append(self._object_id(inst, obj, parent))
        self.exported_originals.add(obj.original.as_pointer())
        self.instance_count += 1

    def _object_id(self, inst, obj, parent) -> int:
        name = obj.original.name
        key: tuple = (obj.original.name_full,)              # name_full: unique across linked libraries
        if self.object_id_mode == "instance" and parent is not None:
            key = (obj.original.name_full, parent.original.name_full, tuple(inst.persistent_id))
            if key not in self.object_ids:
                self.instance_numbers[key[:2]] += 1
                name = f"{name} [{parent.original.name} #{self.instance_numbers[key[:2]]}]"
        if key not in self.object_ids:
            self.object_ids[key] = len(self.object_names)
            self.object_names.append(name)
        return self.object_ids[key]

    # ---------------------------------------------------------------- result
    def describe_nothing(self) -> str:
        parts = []
        if self.skipped_hidden:
            parts.append(f"{len(self.skipped_hidden)} objects hidden for render")
        if self.skipped_empty:
            parts.append(f"{len(self.skipped_empty)} objects without faces ({_names(self.skipped_empty)})")
        n_unsupported = sum(len(v) for v in self.skipped_unsupported.values())
        if n_unsupported:
            kinds = ", ".join(sorted(self.skipped_unsupported))
            parts.append(f"{n_unsupported} objects of unsupported types ({kinds})")
        if self.failed:
            parts.append(f"{len(self.failed)} objects that failed to convert")
        found = "; ".join(parts) if parts else "the view layer holds no mesh objects"
        return f"no mesh with faces is visible to the render ({found})"

    def build(self, *, name: str, metadata: dict) -> tofcore.Scene:
        self._flush_warnings()
        vertices = np.concatenate(self.positions)
        n_tri = [len(t) for t in self.triangles]
        object_ids = np.repeat(np.asarray(self.instance_object_ids, dtype=np.int32), n_tri)
        uvs = None
        if any(self.materials.textured) and any(u is not None for u in self.uvs):
            uvs = np.concatenate([u if u is not None else np.zeros((len(p), 2), np.float32)
                                  for u, p in zip(self.uvs, self.positions)])
        elif any(self.materials.textured):
            self.warnings.append("no mesh has a UV map: textures are sampled at UV (0, 0)")
            uvs = np.zeros((len(vertices), 2), np.float32)
        return tofcore.Scene.from_arrays(
            vertices, np.concatenate(self.triangles), np.concatenate(self.material_ids),
            self.materials.materials, object_ids=object_ids, normals=np.concatenate(self.normals), uvs=uvs,
            object_names=self.object_names, name=name, metadata=metadata)

    def _flush_warnings(self) -> None:
        for label, names in sorted(self.skipped_unsupported.items()):
            self.warnings.append(f"skipped {len(names)} non-mesh objects ({label}): {_names(names)}")
        if self.failed:
            self.warnings.append(f"could not convert {len(self.failed)} objects to meshes: {_names(self.failed)}")
        if self.without_uvs:
            self.warnings.append(f"{len(self.without_uvs)} objects use image textures but have no UV map "
                                 f"(textures sampled at UV (0, 0)): {_names(self.without_uvs)}")


def _names(names, limit: int = 5) -> str:
    names = sorted(names)
    shown = ", ".join(repr(n) for n in names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


class _RenderVisibility:
    """``hide_render`` of objects, instancers and (nested) collections."""

    def __init__(self, scene_collection) -> None:
        self.scene_collection = scene_collection
        self._hidden_in: dict[int, frozenset[int]] = {}

    def renders(self, obj, parent) -> bool:
        original = obj.original
        if original.hide_render:
            return False
        if parent is None:
            return original.as_pointer() not in self._hidden(self.scene_collection)
        if parent.original.hide_render:
            return False
        collection = parent.original.instance_collection if parent.original.instance_type == "COLLECTION" else None
        return collection is None or original.as_pointer() not in self._hidden(collection)

    def _hidden(self, collection) -> frozenset[int]:
        """Objects under ``collection`` that only sit in render-disabled collections."""
        if collection is None:
            return frozenset()
        key = collection.as_pointer()
        if key not in self._hidden_in:
            visible: set[int] = set()
            hidden: set[int] = set()

            def walk(coll, is_hidden: bool) -> None:
                is_hidden = is_hidden or coll.hide_render
                (hidden if is_hidden else visible).update(o.as_pointer() for o in coll.objects)
                for child in coll.children:
                    walk(child, is_hidden)

            walk(collection, False)
            self._hidden_in[key] = frozenset(hidden - visible)
        return self._hidden_in[key]


def _warn_viewport_differences(depsgraph, builder: _SceneBuilder, warnings: list[str]) -> None:
    """Warn where the viewport evaluation differs from what Blender would render.

    Objects hidden in the viewport but enabled for rendering are missing;
    modifiers switched differently for viewport and render, or subdivision
    levels that differ, are exported as the viewport shows them.
    """
    view_layer = depsgraph.view_layer
    missing, differing = [], []
    for obj in view_layer.objects:
        if obj.type not in MESH_LIKE_TYPES or obj.hide_render:
            continue
        if obj.as_pointer() in builder.exported_originals:
            if any(m.show_viewport != m.show_render
                   or getattr(m, "levels", None) != getattr(m, "render_levels", None) for m in obj.modifiers):
                differing.append(obj.name)
            continue
        if obj.name in builder.skipped_empty or obj.name in builder.skipped_hidden:
            continue
        if obj.hide_viewport or not obj.visible_get(view_layer=view_layer):
            if builder.visibility.renders(obj, None):
                missing.append(obj.name)
    if missing:
        warnings.append(f"{len(missing)} objects hidden in the viewport are enabled for rendering but were not "
                        f"exported (show them in the viewport to include them): {_names(missing)}")
    if differing:
        warnings.append(f"{len(differing)} objects have modifiers set differently for viewport and render; "
                        f"exported as the viewport shows them: {_names(differing)}")


# =========================================================================== materials
class _MaterialTable:
    """Blender materials → deduplicated tofcore materials; index 0.. in first-use order."""

    def __init__(self, warnings: list[str]) -> None:
        self.warnings = warnings
        self.materials: list[tofcore.Material] = []
        self.textured: list[bool] = []
        self._index: dict[int, int] = {}
        self._images = _ImageCache(warnings)

    def index(self, material) -> int:
        key = material.original.as_pointer() if material is not None else 0
        if key not in self._index:
            if material is None:
                converted = tofcore.Material(name="(no material)", **mapping.material_fields())
            else:
                converted = material_from_blender(material.original, warnings=self.warnings, images=self._images)
            self._index[key] = len(self.materials)
            self.materials.append(converted)
            self.textured.append(bool(converted.textures))
        return self._index[key]


def material_from_blender(material, *, warnings: list[str] | None = None, images=None) -> tofcore.Material:
    """A :class:`tofcore.Material` from a Blender material (mapping table in :mod:`addon.mapping`).

    Reads the Principled BSDF linked to the active material output's
    "Surface" (through reroutes; the first Principled BSDF inside mix/add
    shaders, with a warning), its inputs by name (Coat Weight and Coat Roughness too), image textures on
    "Base Color", "Roughness", "Metallic" and a Normal Map node on "Normal",
    and the IR override ``material.tof`` when it is switched on.
    """
    warnings = warnings if warnings is not None else []
    images = images if images is not None else _ImageCache(warnings)
    name = material.name
    inputs = {"base_color": mapping.BLENDER_DEFAULT_BASE_COLOR, "roughness": mapping.BLENDER_DEFAULT_ROUGHNESS,
              "metallic": 0.0, "ior": mapping.BLENDER_DEFAULT_IOR, "coat": 0.0,
              "coat_roughness": mapping.BLENDER_DEFAULT_COAT_ROUGHNESS}
    textures: dict[str, tofcore.Texture] = {}
    bsdf = _surface_bsdf(material, warnings)
    if bsdf is None:
        # Viewport display values: what Blender shows for a material without a usable node tree.
        inputs.update(base_color=tuple(material.diffuse_color), roughness=material.roughness,
                      metallic=material.metallic)
    else:
        for key, socket_name in (("base_color", "Base Color"), ("roughness", "Roughness"),
                                 ("metallic", "Metallic"), ("ior", "IOR")):
            value, image = _socket_value(bsdf, socket_name, name, warnings)
            if value is not None:
                inputs[key] = value
            if image is not None and key == "ior":
                warnings.append(f"material {name!r}: an image on 'IOR' is not supported; its unlinked value is used")
            elif image is not None:
                texture = images.texture(image, key, name)
                if texture is not None:
                    textures[_TEXTURE_FIELDS[key]] = texture
        for key, socket_names in (("coat", ("Coat Weight", "Clearcoat")),
                                  ("coat_roughness", ("Coat Roughness", "Clearcoat Roughness"))):
            socket_name = next((n for n in socket_names if bsdf.inputs.get(n) is not None), socket_names[0])
            value, image = _socket_value(bsdf, socket_name, name, warnings)
            if value is not None:
                inputs[key] = value
            if image is not None:
                warnings.append(f"material {name!r}: an image on {socket_name!r} is not supported; its unlinked "
                                f"value is used")
        normal = _normal_map_image(bsdf, name, warnings)
        if normal is not None:
            texture = images.texture(normal, "normal", name)
            if texture is not None:
                textures["normal_texture"] = texture

    override = {}
    tof = getattr(material, "tof", None)
    if tof is not None and getattr(tof, "use_override", False):
        override = {"override_reflectance": float(tof.reflectance), "override_roughness": float(tof.roughness),
                    "override_extinction": float(tof.extinction)}
        textures.pop("reflectance_texture", None)
        textures.pop("roughness_texture", None)
    fields = mapping.material_fields(**inputs, **override)
    try:
        return tofcore.Material(name=name, **fields, **textures)
    except tofcore.ConfigError as error:
        raise tofcore.ConfigError(f"material {name!r} (near-IR override): {error}") from None


_TEXTURE_FIELDS = {"base_color": "reflectance_texture", "roughness": "roughness_texture",
                   "metallic": "metallic_texture"}


def _linked_node(socket):
    """(node, output socket) feeding ``socket``, skipping reroutes; (None, None) when unlinked."""
    seen = 0
    while socket is not None and socket.is_linked and seen < 64:
        link = socket.links[0]
        if not link.is_valid or getattr(link, "is_muted", False):
            return None, None
        node = link.from_node
        if node.type == "REROUTE":
            socket = node.inputs[0]
            seen += 1
            continue
        return node, link.from_socket
    return None, None


def _active_output(tree, output_type: str):
    outputs = [n for n in tree.nodes if n.type == output_type]
    for node in outputs:
        if getattr(node, "is_active_output", False):
            return node
    return outputs[0] if outputs else None


def _surface_bsdf(material, warnings: list[str]):
    """The Principled BSDF behind the material output's "Surface", or None (then viewport values are used)."""
    name = material.name
    tree = material.node_tree
    if bpy.app.version < (5, 0, 0) and not material.use_nodes:   # use_nodes is deprecated from 5.0 on
        tree = None
    if tree is None:
        return None
    output = _active_output(tree, "OUTPUT_MATERIAL")
    if output is None:
        warnings.append(f"material {name!r} has no Material Output node; its viewport colour is used")
        return None
    node, _ = _linked_node(output.inputs.get("Surface"))
    if node is None:
        warnings.append(f"material {name!r}: nothing is linked to the output's Surface; its viewport colour is used")
        return None
    if node.type == "BSDF_PRINCIPLED":
        return node
    found = _find_principled(node, depth=0)
    if found is not None:
        warnings.append(f"material {name!r}: the surface is a {node.bl_label!r} node; exported from the "
                        f"Principled BSDF {found.name!r} inside it")
        return found
    warnings.append(f"material {name!r}: the surface is a {node.bl_label!r} node, not a Principled BSDF; "
                    f"its viewport colour is used")
    return None


def _find_principled(node, depth: int):
    if depth > 16:
        return None
    for socket in node.inputs:
        child, _ = _linked_node(socket)
        if child is None:
            continue
        if child.type == "BSDF_PRINCIPLED":
            return child
        found = _find_principled(child, depth + 1)
        if found is not None:
            return found
    return None


def _socket_value(node, socket_name: str, material_name: str, warnings: list[str]):
    """(value, image) of an input: its value, or the image of an Image Texture node linked to it."""
    socket = node.inputs.get(socket_name)
    if socket is None:
        return None, None
    value = socket.default_value
    value = tuple(value) if hasattr(value, "__len__") else float(value)
    source, out_socket = _linked_node(socket)
    if source is None:
        return value, None
    if source.type == "TEX_IMAGE":
        if source.image is None:
            warnings.append(f"material {material_name!r}: the Image Texture on {socket_name!r} has no image")
            return value, None
        _warn_texture_coordinates(source, material_name, warnings)
        return value, (source.image, out_socket.name)
    if source.type in ("RGB", "VALUE"):
        linked = out_socket.default_value
        return (tuple(linked) if hasattr(linked, "__len__") else float(linked)), None
    warnings.append(f"material {material_name!r}: {socket_name!r} is driven by a {source.bl_label!r} node, "
                    f"which the exporter does not evaluate; the input's own value is used")
    return value, None


def _normal_map_image(bsdf, material_name: str, warnings: list[str]):
    node, _ = _linked_node(bsdf.inputs.get("Normal"))
    if node is None:
        return None
    if node.type != "NORMAL_MAP":
        warnings.append(f"material {material_name!r}: 'Normal' is driven by a {node.bl_label!r} node; "
                        f"only Normal Map → Image Texture is exported")
        return None
    if node.space != "TANGENT":
        warnings.append(f"material {material_name!r}: the Normal Map is in {node.space!r} space; "
                        f"only tangent space is exported")
        return None
    strength = node.inputs.get("Strength")
    if strength is not None and (strength.is_linked or abs(strength.default_value - 1.0) > 1e-6):
        warnings.append(f"material {material_name!r}: Normal Map strength {strength.default_value:g} is "
                        f"exported as 1")
    image_node, out_socket = _linked_node(node.inputs.get("Color"))
    if image_node is None or image_node.type != "TEX_IMAGE" or image_node.image is None:
        warnings.append(f"material {material_name!r}: the Normal Map's Color is not an Image Texture with an "
                        f"image; normal map skipped")
        return None
    _warn_texture_coordinates(image_node, material_name, warnings)
    return image_node.image, out_socket.name


def _warn_texture_coordinates(image_node, material_name: str, warnings: list[str]) -> None:
    vector = image_node.inputs.get("Vector")
    if vector is not None and vector.is_linked:
        warnings.append(f"material {material_name!r}: the texture coordinates of image "
                        f"{image_node.image.name!r} (Vector input) are ignored; the active UV map is used")


class _ImageCache:
    """Reads each Blender image once; makes tofcore textures from it per use."""

    def __init__(self, warnings: list[str]) -> None:
        self.warnings = warnings
        self._pixels: dict[int, np.ndarray | None] = {}
        self._textures: dict[tuple[int, str, str], tofcore.Texture | None] = {}

    def texture(self, image_and_socket, role: str, material_name: str) -> tofcore.Texture | None:
        image, socket_name = image_and_socket
        key = (image.as_pointer(), socket_name, role)
        if key not in self._textures:
            pixels = self.pixels(image, material_name)
            self._textures[key] = None if pixels is None else _texture_for(pixels, role, socket_name, image.name)
        return self._textures[key]

    def pixels(self, image, material_name: str) -> np.ndarray | None:
        key = image.as_pointer()
        if key not in self._pixels:
            self._pixels[key] = read_image(image, material_name, self.warnings)
        return self._pixels[key]


def _texture_for(pixels: np.ndarray, role: str, socket_name: str, image_name: str) -> tofcore.Texture:
    """tofcore texture for a material field from linear (H, W, C) pixels, row 0 at the top."""
    channels = pixels.shape[2]
    if socket_name == "Alpha":
        single = pixels[..., 3] if channels == 4 else np.ones(pixels.shape[:2], np.float32)
    elif channels >= 3:
        single = None
    else:
        single = pixels[..., 0]
    # A colour linked to a number input is its luminance in Blender's shading (the implicit colour → float
    # conversion), so a tinted roughness or metallic map counts every channel, not its red one.
    grey = single if single is not None else (mapping.luminance(pixels[..., :3]) if role != "normal" else None)
    if role == "base_color":
        data = np.clip(grey, 0.0, 1.0)
    elif role == "roughness":
        data = mapping.sigma_from_blender_roughness(grey)
    elif role == "metallic":
        data = np.clip(grey, 0.0, 1.0)
    else:   # normal map: tangent-space RGB in [0, 1]
        data = pixels[..., :3] if channels >= 3 else np.repeat(pixels[..., :1], 3, axis=2)
    return tofcore.Texture(np.asarray(data, dtype=np.float32), name=f"{image_name} ({role})")


def read_image(image, material_name: str = "", warnings: list[str] | None = None) -> np.ndarray | None:
    """Pixels of a Blender image as linear float32 (H, W, C), row 0 at the top; None (with a warning) if missing.

    8-bit images in the sRGB colour space are decoded to linear values as
    Blender's shading sees them; float images are linear already.
    """
    warnings = warnings if warnings is not None else []
    where = f" on material {material_name!r}" if material_name else ""
    if image.source == "TILED":
        warnings.append(f"UDIM image {image.name!r}{where} is not supported; texture skipped")
        return None
    if image.source in ("FILE", "SEQUENCE") and image.packed_file is None:
        path = os.path.normpath(bpy.path.abspath(image.filepath, library=image.library))
        if not os.path.isfile(path):
            warnings.append(f"missing texture file {path}{where}")
            return None
    width, height = image.size
    channels = image.channels
    if width == 0 or height == 0 or channels == 0:
        warnings.append(f"image {image.name!r}{where} could not be loaded; texture skipped")
        return None
    flat = np.empty(width * height * channels, dtype=np.float32)
    image.pixels.foreach_get(flat)
    data = mapping.image_rows_top_down(flat, width, height, channels)
    if not image.is_float and image.colorspace_settings.name == "sRGB":
        data[..., :3] = mapping.srgb_to_linear(data[..., :3])
    if not np.isfinite(data).all():
        data = np.nan_to_num(data, nan=0.0, posinf=0.0, neginf=0.0)
    return data


# =========================================================================== world
def ambient_from_world(world, *, ambient_scale: float = 1.0, warnings: list[str] | None = None):
    """:class:`tofcore.Ambient` from a Blender world, or None for no world or a black one.

    See the world table in :mod:`addon.mapping`: the Background node's Color
    × Strength (or the world colour without nodes), or an equirectangular
    Environment Texture on the Background's Color as a luminance map with
    row 0 = zenith, all times ``ambient_scale``.
    """
    warnings = warnings if warnings is not None else []
    if world is None:
        return None
    if not (ambient_scale >= 0 and np.isfinite(ambient_scale)):
        raise tofcore.ConfigError(f"export: ambient_scale must be a finite number >= 0, got {ambient_scale!r}")
    color, strength, environment = tuple(world.color), 1.0, None
    tree = world.node_tree
    if bpy.app.version < (5, 0, 0) and not world.use_nodes:   # use_nodes is deprecated from 5.0 on
        tree = None
    if tree is not None:
        output = _active_output(tree, "OUTPUT_WORLD")
        node, _ = _linked_node(output.inputs.get("Surface")) if output is not None else (None, None)
        if node is None:
            return None                      # a world output with nothing linked renders black
        if node.type != "BACKGROUND":
            warnings.append(f"world {world.name!r}: the surface is a {node.bl_label!r} node, not a Background; "
                            f"the world colour is used for ambient light")
        else:
            strength_socket = node.inputs["Strength"]
            strength = float(strength_socket.default_value)
            if strength_socket.is_linked:
                warnings.append(f"world {world.name!r}: a linked Strength is not evaluated; "
                                f"its value {strength:g} is used")
            color_socket = node.inputs["Color"]
            color = tuple(color_socket.default_value)
            source, out_socket = _linked_node(color_socket)
            if source is not None and source.type == "TEX_ENVIRONMENT" and source.image is not None:
                environment = _environment_map(source, world.name, warnings)
            elif source is not None and source.type == "RGB":
                color = tuple(out_socket.default_value)
            elif source is not None:
                warnings.append(f"world {world.name!r}: the Background Color is driven by a {source.bl_label!r} "
                                f"node, which is not evaluated; its own value is used")
    if environment is not None:
        if strength * ambient_scale <= 0 or not environment.any():
            return None
        return tofcore.Ambient(environment=environment, environment_strength=strength * ambient_scale)
    radiance = max(mapping.luminance(color[:3]), 0.0) * strength * ambient_scale
    if not radiance > 0:
        return None
    return tofcore.Ambient(radiance_w_m2_sr=float(radiance))


def _environment_map(node, world_name: str, warnings: list[str]) -> np.ndarray | None:
    if node.projection != "EQUIRECTANGULAR":
        warnings.append(f"world {world_name!r}: only equirectangular environment textures are exported, "
                        f"got {node.projection!r}; the Background colour is used")
        return None
    if node.inputs["Vector"].is_linked:
        warnings.append(f"world {world_name!r}: the environment texture's Vector input (mapping/rotation) "
                        f"is ignored")
    pixels = read_image(node.image, warnings=warnings)
    if pixels is None:
        return None
    channels = pixels.shape[2]
    env = mapping.luminance(pixels[..., :3]) if channels >= 3 else pixels[..., 0]
    return np.maximum(np.asarray(env, dtype=np.float32), 0.0)
