"""Scenes from common mesh files: OBJ, PLY, glTF/GLB, STL → :class:`~tofcore.scene.Scene`.

The files are read by `trimesh <https://trimesh.org>`_ (the optional extra ``pip install trimesh``,
imported only here and only when a mesh file is loaded); tofcore's own BVH and tracer render them.
Every mesh of the file becomes one object, named as in the file (a glTF node; for an OBJ trimesh
groups the faces by material, so one object per material); ``frame.json`` lists them with their materials (``objects``).

Units and axes: lengths are metres (glTF's unit; OBJ, PLY and STL have none, and are read as
metres). tofcore's world is Blender's (Z up): glTF is Y up by its specification and OBJ by
convention (Blender's OBJ importer turns it the same way), so both are turned
(x, y, z) → (x, −z, y); PLY and STL are taken as Z up, as Blender imports them.

Materials, where the file has them (else the default):

=====================================  ===============  ==========================================
file                                   tofcore          mapping (as the add-on maps Blender's BSDF)
=====================================  ===============  ==========================================
glTF ``baseColorFactor`` (linear RGB)  ``reflectance``  luminance Y = 0.2126 R + 0.7152 G + 0.0722 B
OBJ MTL ``Kd`` (RGB)                   ``reflectance``  the same luminance
glTF ``roughnessFactor`` r             ``roughness``    σ = r²/√2 (Blender's mapping)
glTF ``metallicFactor``                ``metallic``     as is; a metal's extinction k gives normal
                                                        reflectance F0 = luminance at η = 1.5:
                                                        F0 = ((η − 1)² + k²) / ((η + 1)² + k²)
none (PLY, STL, no material)           default          reflectance 0.5, roughness 0.5, dielectric
                                                        η 1.52 (:class:`~tofcore.material.Material`)
=====================================  ===============  ==========================================

Textures are not read: a textured material takes its constant factor. The scene's suggested
pose looks at the centre of the bounding box from −Y (Blender's front view): for a sensor, framed for its
field of view and range (:func:`tofcore.suggested_pose` of the box stored as ``metadata["framing"]``,
:func:`~tofcore.scene.pose.framed_view`); without one (``metadata["world_from_sensor"]``), far enough that
the whole box is in a 60° field of view.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..errors import SceneError
from .material import Material
from .pose import look_at
from .scene import Scene

#: File suffixes this module reads, and whether the file's up axis is Y (turned to Z).
MESH_SUFFIXES = {".obj": True, ".gltf": True, ".glb": True, ".ply": False, ".stl": False}

#: Install hint for the optional mesh reader.
TRIMESH_HINT = "pip install trimesh"

_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
_Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
_DEFAULT = Material(name="default")


def is_mesh_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` has a suffix :func:`load_mesh` reads (case-insensitive)."""
    return Path(path).suffix.lower() in MESH_SUFFIXES


def load_mesh(path: str | os.PathLike) -> Scene:
    """A :class:`Scene` from an OBJ, PLY, glTF/GLB or STL file (see the module docstring).

    Raises SceneError naming the file when trimesh is missing, the file cannot be read or holds no triangles.
    """
    path = Path(path)
    where = str(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise SceneError(f"{where}: a mesh file must end in one of {sorted(MESH_SUFFIXES)}, got {suffix!r}")
    try:
        import trimesh
    except ImportError:
        raise SceneError(f"{where}: reading {suffix} files needs the trimesh package, which is not installed: "
                         f"{TRIMESH_HINT}") from None
    if not path.is_file():
        raise SceneError(f"{where}: file not found")
    try:
        loaded = trimesh.load(str(path), force="scene", process=False)
    except Exception as exc:  # trimesh raises many kinds for a damaged file
        raise SceneError(f"{where}: cannot read the mesh file ({type(exc).__name__}: {exc})") from None
    vertices, triangles, material_ids, object_ids, names, materials = [], [], [], [], [], []
    material_index: dict[int, int] = {}
    offset = 0
    for node in loaded.graph.nodes_geometry:
        transform, geometry_name = loaded.graph[node]
        mesh = loaded.geometry[geometry_name]
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            continue
        points = trimesh.transformations.transform_points(np.asarray(mesh.vertices, np.float64), transform)
        key = id(getattr(mesh.visual, "material", None))
        if key not in material_index:
            material_index[key] = len(materials)
            materials.append(_material(getattr(mesh.visual, "material", None), len(materials)))
        vertices.append(points)
        triangles.append(np.asarray(mesh.faces, np.int64) + offset)
        material_ids.append(np.full(len(mesh.faces), material_index[key]))
        object_ids.append(np.full(len(mesh.faces), len(names)))
        names.append(str(node))
        offset += len(points)
    if not triangles:
        raise SceneError(f"{where}: the file holds no triangle mesh")
    points = np.concatenate(vertices)
    if MESH_SUFFIXES[suffix]:
        points = points @ _Y_UP_TO_Z_UP.T
    scene = Scene.from_arrays(points, np.concatenate(triangles), np.concatenate(material_ids), materials,
                              object_ids=np.concatenate(object_ids), object_names=names, name=path.stem)
    scene.metadata["world_from_sensor"] = front_view(points.min(axis=0), points.max(axis=0)).tolist()
    scene.metadata["framing"] = {"lo": points.min(axis=0).tolist(), "hi": points.max(axis=0).tolist()}
    scene.metadata["source"] = {"file": path.name, "reader": f"trimesh {trimesh.__version__}"}
    return scene


def front_view(lo: np.ndarray, hi: np.ndarray, fov_deg: float = 60.0) -> np.ndarray:
    """4×4 ``world_from_sensor`` looking at the box [lo, hi]'s centre along +Y from where the whole box
    (its bounding sphere) fits a ``fov_deg`` field of view."""
    centre = (np.asarray(lo, float) + np.asarray(hi, float)) / 2
    radius = max(float(np.linalg.norm(np.asarray(hi, float) - lo)) / 2, 1e-3)
    distance = radius / math.sin(math.radians(fov_deg) / 2)
    return look_at(centre - np.array([0.0, distance, 0.0]), centre)


_METAL_IOR = 1.5          # Blender's default IOR, which the add-on's mapping uses for metals too
_F0_MAX = 0.99            # addon/mapping.py: F0 below 1 keeps k finite


def _extinction(f0: float) -> float:
    """Conductor extinction k with normal reflectance ``f0`` at η = 1.5 (addon/mapping.py's equation, solved
    for k): k² = (F0 (η + 1)² − (η − 1)²) / (1 − F0), F0 clipped to [((η − 1)/(η + 1))², 0.99]."""
    eta = _METAL_IOR
    f0 = min(max(f0, ((eta - 1) / (eta + 1)) ** 2), _F0_MAX)
    return math.sqrt(max((f0 * (eta + 1) ** 2 - (eta - 1) ** 2) / (1 - f0), 0.0))


def _material(source, index: int) -> Material:
    """The tofcore material of a trimesh material (PBR or simple/MTL), or the default."""
    if source is None:
        return _DEFAULT
    name = str(getattr(source, "name", None) or f"material {index}")
    base = getattr(source, "baseColorFactor", None)
    if base is not None:  # glTF PBR (trimesh keeps the factor as 8-bit RGBA)
        rgb = np.asarray(base, np.float64)[:3] / 255.0
        roughness = getattr(source, "roughnessFactor", None)
        metallic = getattr(source, "metallicFactor", None)
        reflectance = float(np.clip(rgb @ _LUMINANCE, 0.0, 1.0))
        metallic = 0.0 if metallic is None else float(np.clip(metallic, 0.0, 1.0))
        return Material(name=name, reflectance=reflectance, metallic=metallic, ior=_METAL_IOR,
                        extinction=_extinction(reflectance) if metallic > 0 else 0.0,
                        roughness=_DEFAULT.roughness if roughness is None else float(roughness) ** 2 / math.sqrt(2))
    kd = (getattr(source, "kwargs", None) or {}).get("kd")   # an MTL's Kd (trimesh lower-cases the keys)
    if kd is not None:
        rgb = np.asarray(kd, np.float64).reshape(-1)[:3]
        return Material(name=name, reflectance=float(np.clip(rgb @ _LUMINANCE, 0.0, 1.0)))
    return Material(name=name)
