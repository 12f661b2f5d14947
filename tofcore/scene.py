"""The scene: triangle meshes as flat NumPy arrays, in metres, Blender's world frame.

==================  ===========  =======  ==========================================================
array               shape        dtype    meaning
==================  ===========  =======  ==========================================================
``vertices``        (N, 3)       float32  positions, metres, scene frame = world frame − ``origin_m``
``triangles``       (M, 3)       int32    vertex indices, counter-clockwise seen from the front
``material_ids``    (M,)         int32    index into ``materials`` per triangle
``object_ids``      (M,)         int32    which object a triangle belongs to (ground-truth ids)
``normals``         (N, 3)       float32  optional vertex normals for smooth shading
``uvs``             (N, 2)       float32  optional texture coordinates
==================  ===========  =======  ==========================================================

The scene frame is the world frame (right-handed, Z up) shifted by ``origin_m`` (float64, metres): a
scene built from coordinates more than :data:`RECENTRE_BEYOND_M` from the world origin is stored about a
whole-metre point near its centre, because float32 vertices there would lose the sub-millimetre
resolution ToF needs (1e5 m from the origin, float32 steps are 7.8 mm). The tracer works in the scene
frame (poses are shifted by ``origin_m``); everything it returns is in world or sensor coordinates.

Surfaces are two-sided and opaque. :meth:`Scene.from_arrays` validates the
arrays (a :class:`~tofcore.errors.SceneError` names the array and the first
bad index) and drops degenerate triangles, counting them in
``dropped_triangles``. Scenes are saved as versioned ``.npz`` files.
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from .errors import SceneError
from .material import Material, Texture

FORMAT_VERSION = 1
"""Version of the ``.npz`` layout written by :meth:`Scene.save`."""

RECENTRE_BEYOND_M = 1000.0
"""Geometry whose bounding box reaches farther than this from the world origin is stored relative to
``origin_m`` (float32 resolution at 1 km: 61 µm)."""


def _first_bad(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask.reshape(len(mask), -1).any(axis=1))[0])


@dataclass(frozen=True, eq=False)
class Scene:
    """Triangle geometry plus materials; build it with :meth:`from_arrays`."""

    vertices: np.ndarray
    triangles: np.ndarray
    material_ids: np.ndarray
    object_ids: np.ndarray
    materials: tuple[Material, ...]
    normals: np.ndarray | None = None
    uvs: np.ndarray | None = None
    object_names: tuple[str, ...] = ()
    dropped_triangles: int = 0
    name: str = "scene"
    metadata: dict = field(default_factory=dict)
    origin_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # world position of the scene frame's origin

    # ------------------------------------------------------------------ build
    @classmethod
    def from_arrays(cls, vertices, triangles, material_ids=None, materials=None, *,
                    object_ids=None, normals=None, uvs=None, object_names=(), name: str = "scene",
                    metadata: dict | None = None, origin_m=None) -> Scene:
        """Validate arrays and build a scene.

        ``vertices`` are world coordinates, or scene-frame coordinates when ``origin_m`` is given (a saved
        scene). Without ``origin_m``, geometry reaching beyond :data:`RECENTRE_BEYOND_M` is recentred.

        Raises
        ------
        SceneError
            On NaN/inf values, out-of-range indices, mismatched shapes or an
            empty scene; the message names the array and the first bad index.
        """
        where = f"Scene {name!r}"
        vertices = _as_array(vertices, np.float64, (None, 3), f"{where}: vertices")
        triangles = _as_array(triangles, np.int64, (None, 3), f"{where}: triangles")
        n_vert, n_tri = len(vertices), len(triangles)
        if n_tri == 0:
            raise SceneError(f"{where}: triangles must hold at least one triangle, got 0")
        bad = ~np.isfinite(vertices)
        if bad.any():
            i = _first_bad(bad)
            raise SceneError(f"{where}: vertices must be finite, got {vertices[i].tolist()} at vertex {i}")
        bad = (triangles < 0) | (triangles >= n_vert)
        if bad.any():
            i = _first_bad(bad)
            raise SceneError(f"{where}: triangles must index vertices in [0, {n_vert}), "
                             f"got {triangles[i].tolist()} at triangle {i}")
        materials = tuple(materials) if materials else (Material(),)
        for i, m in enumerate(materials):
            if not isinstance(m, Material):
                raise SceneError(f"{where}: materials[{i}] must be a tofcore.Material, got {type(m).__name__}")
        material_ids = _per_triangle(material_ids, n_tri, len(materials), f"{where}: material_ids")
        object_ids = _per_triangle(object_ids, n_tri, None, f"{where}: object_ids")
        if normals is not None:
            normals = _as_array(normals, np.float32, (n_vert, 3), f"{where}: normals")
            if not np.isfinite(normals).all():
                raise SceneError(f"{where}: normals must be finite, got NaN/inf at vertex "
                                 f"{_first_bad(~np.isfinite(normals))}")
            length = np.linalg.norm(normals, axis=1)
            if (length < 1e-6).any():
                raise SceneError(f"{where}: normals must be non-zero, got a zero normal at vertex "
                                 f"{int(np.flatnonzero(length < 1e-6)[0])}")
            normals = (normals / length[:, None]).astype(np.float32)
        if uvs is not None:
            uvs = _as_array(uvs, np.float32, (n_vert, 2), f"{where}: uvs")
            if not np.isfinite(uvs).all():
                raise SceneError(f"{where}: uvs must be finite, got NaN/inf at vertex {_first_bad(~np.isfinite(uvs))}")
        needs_uv = [m.name for m in materials if m.textures]
        if needs_uv and uvs is None:
            raise SceneError(f"{where}: uvs are required by the textured materials {needs_uv}")

        origin = _origin(vertices, triangles, origin_m, where)
        vertices = (vertices if origin_m is not None else vertices - origin).astype(np.float32)
        keep = ~_degenerate(vertices, triangles)
        dropped = int(n_tri - keep.sum())
        if not keep.any():
            raise SceneError(f"{where}: triangles are all degenerate (zero area), {n_tri} dropped")
        return cls(vertices=vertices, triangles=triangles[keep].astype(np.int32),
                   material_ids=material_ids[keep], object_ids=object_ids[keep], materials=materials,
                   normals=normals, uvs=uvs, object_names=tuple(object_names), dropped_triangles=dropped,
                   name=name, metadata=dict(metadata or {}), origin_m=tuple(float(x) for x in origin))

    # ------------------------------------------------------- derived geometry
    @property
    def triangle_count(self) -> int:
        return len(self.triangles)

    @cached_property
    def face_normals(self) -> np.ndarray:
        """(M, 3) float32 unit geometric normals, right-hand rule on the vertex order."""
        v = self.vertices.astype(np.float64)
        t = self.triangles
        n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
        return (n / np.linalg.norm(n, axis=1, keepdims=True)).astype(np.float32)

    @cached_property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (lo, hi) of the referenced vertices, metres, scene frame (add ``origin_m``
        for world coordinates)."""
        used = self.vertices[np.unique(self.triangles)]
        return used.min(axis=0), used.max(axis=0)

    @cached_property
    def bvh(self):
        """The bounding volume hierarchy, built on first use."""
        from .bvh import BVH
        return BVH.build(self.vertices, self.triangles)

    # -------------------------------------------------------------------- I/O
    def save(self, path: str | os.PathLike) -> Path:
        """Write a versioned ``.npz`` atomically (temp file, then rename)."""
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_suffix(".npz")
        arrays = {
            "format_version": np.array(FORMAT_VERSION),
            "vertices": self.vertices, "triangles": self.triangles,
            "material_ids": self.material_ids, "object_ids": self.object_ids,
            "header": np.array(json.dumps({
                "name": self.name, "object_names": list(self.object_names),
                "materials": [m.to_dict() for m in self.materials],
                "dropped_triangles": self.dropped_triangles, "metadata": self.metadata,
                "origin_m": list(self.origin_m)})),
        }
        if self.normals is not None:
            arrays["normals"] = self.normals
        if self.uvs is not None:
            arrays["uvs"] = self.uvs
        for i, m in enumerate(self.materials):
            for key, tex in m.textures.items():
                arrays[f"texture/{i}/{key}"] = tex.data
                arrays[f"texture_name/{i}/{key}"] = np.array(tex.name)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez_compressed(f, **arrays)
            os.replace(tmp, path)
        except BaseException:
            os.unlink(tmp)
            raise
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> Scene:
        """Read a scene written by :meth:`save`; errors name the file."""
        path = Path(path)
        try:
            data = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise SceneError(f"{path}: not a readable tofcore scene (.npz): {exc}") from exc
        with data:
            version = int(data["format_version"]) if "format_version" in data else None
            if version != FORMAT_VERSION:
                raise SceneError(f"{path}: format_version must be {FORMAT_VERSION}, got {version!r}")
            header = json.loads(str(data["header"]))
            materials = []
            for i, md in enumerate(header["materials"]):
                textures = {key.split("/")[2]: Texture(data[key], name=str(data[f"texture_name/{i}/{key.split('/')[2]}"]))
                            for key in data.files if key.startswith(f"texture/{i}/")}
                materials.append(Material.from_dict(md, where=f"{path}: materials[{i}]", textures=textures))
            return cls.from_arrays(
                data["vertices"], data["triangles"], data["material_ids"], materials,
                object_ids=data["object_ids"],
                normals=data["normals"] if "normals" in data else None,
                uvs=data["uvs"] if "uvs" in data else None,
                object_names=header["object_names"], name=header["name"], metadata=header["metadata"],
                origin_m=header.get("origin_m", (0.0, 0.0, 0.0)))


def _as_array(values, dtype, shape, where: str) -> np.ndarray:
    try:
        arr = np.asarray(values)
    except (TypeError, ValueError) as exc:
        raise SceneError(f"{where}: must be a numeric array, got {type(values).__name__}") from exc
    if arr.dtype.kind not in "biuf":
        raise SceneError(f"{where}: must be a numeric array, got dtype {arr.dtype}")
    want = tuple(len(arr) if s is None else s for s in shape) if arr.ndim == len(shape) else shape
    if arr.shape != want:
        shown = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise SceneError(f"{where}: must have shape {shown}, got {arr.shape}")
    if dtype == np.int64 and arr.dtype.kind == "f":
        if not np.all(np.isfinite(arr)) or not np.all(arr == np.round(arr)):
            raise SceneError(f"{where}: must hold integers, got non-integer values")
    return arr.astype(dtype)


def _per_triangle(values, n_tri: int, n_valid: int | None, where: str) -> np.ndarray:
    if values is None:
        return np.zeros(n_tri, np.int32)
    arr = _as_array(values, np.int64, (n_tri,), where)
    hi = n_valid if n_valid is not None else np.iinfo(np.int32).max
    bad = (arr < 0) | (arr >= hi)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise SceneError(f"{where}: must be in [0, {hi}), got {int(arr[i])} at triangle {i}")
    return arr.astype(np.int32)


def _origin(vertices: np.ndarray, triangles: np.ndarray, origin_m, where: str) -> np.ndarray:
    """The scene frame's origin in world coordinates: ``origin_m`` when given, else a whole-metre point
    at the centre of geometry that reaches beyond :data:`RECENTRE_BEYOND_M`, else 0."""
    if origin_m is not None:
        origin = np.asarray(origin_m, dtype=np.float64)
        if origin.shape != (3,) or not np.isfinite(origin).all():
            raise SceneError(f"{where}: origin_m must be 3 finite numbers (metres), got {origin_m!r}")
        return origin
    used = vertices[np.unique(triangles)]
    lo, hi = used.min(axis=0), used.max(axis=0)
    if np.max(np.abs(np.concatenate([lo, hi]))) <= RECENTRE_BEYOND_M:
        return np.zeros(3)
    return np.round(0.5 * (lo + hi))


def _degenerate(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Triangles whose area is zero to float32 precision (repeated or collinear vertices)."""
    v = vertices.astype(np.float64)
    e1 = v[triangles[:, 1]] - v[triangles[:, 0]]
    e2 = v[triangles[:, 2]] - v[triangles[:, 0]]
    twice_area = np.linalg.norm(np.cross(e1, e2), axis=1)
    longest = np.maximum(np.linalg.norm(e1, axis=1), np.linalg.norm(e2, axis=1))
    # Relative to the longest edge squared: a sliver thinner than float32 resolution has no usable normal.
    return twice_area <= 1e-6 * longest**2 + np.finfo(np.float32).tiny
