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
import math
import os
import tempfile
import zipfile
import zlib
from dataclasses import dataclass, field, fields
from functools import cached_property
from pathlib import Path

import numpy as np

from .. import limits
from ..errors import ConfigError, SceneError, TofError
from .material import Material, Texture
from .pose import rigid_problem

FORMAT_VERSION = 1
"""Version of the ``.npz`` layout written by :meth:`Scene.save`."""

RECENTRE_BEYOND_M = 1000.0
"""Geometry whose bounding box reaches farther than this from the world origin is stored relative to
``origin_m`` (float32 resolution at 1 km: 61 µm); also a saved scene whose stored vertices reach farther
than this from its ``origin_m`` (made elsewhere, or before ``origin_m`` existed) is recentred on load."""

FLOAT32_MAX_M = float(np.finfo(np.float32).max)
"""Largest coordinate (metres) a float32 holds: larger vertices or ``origin_m`` are refused, not turned into inf."""


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

        big = np.abs(vertices) > FLOAT32_MAX_M
        if big.any():
            i = _first_bad(big)
            raise SceneError(f"{where}: vertices must be within float32 range (|x| <= {FLOAT32_MAX_M:.3g} m), "
                             f"got {vertices[i].tolist()} at vertex {i}")
        origin = _origin(vertices, triangles, origin_m, where)
        vertices = vertices if origin_m is not None else vertices - origin
        # Stored about origin_m but still far from it (a file made elsewhere, an older file without the
        # header key, a header that says 0): recentre it too, whatever the header says.
        shift = _origin(vertices, triangles, None, where)
        origin, vertices = origin + shift, (vertices - shift).astype(np.float32)
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
        """The bounding volume hierarchy, built on first use, or shared with any scene of the same triangles
        built before (`BVH.cached`: a scene loaded or exported again for another camera builds nothing)."""
        from .bvh import BVH
        return BVH.cached(self.vertices, self.triangles)

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
        """Read a scene written by :meth:`save`.

        Everything is checked before it is used, and before an array is
        decompressed its size is checked against
        :data:`tofcore.limits.MAX_SCENE_BYTES` (from the zip directory and the
        ``.npy`` header, so a small file that would decompress to gigabytes is
        refused unread).

        Raises
        ------
        SceneError
            Naming the file and what is wrong with it: not a zip of ``.npy``
            arrays (empty, truncated, random bytes, a lone ``.npy``), a missing
            or malformed array, a header that is not the JSON object
            :meth:`save` writes, a texture without its name, a material or
            array that :meth:`from_arrays` rejects.
        LimitError
            An array or the whole file is larger than ``MAX_SCENE_BYTES``.
        """
        path = Path(path)
        where = str(path)
        arrays = _read_npz(path)
        version = arrays.get("format_version")
        if version is None or version.shape != () or version.dtype.kind not in "iu" or int(version) != FORMAT_VERSION:
            shown = (None if version is None else version.tolist() if version.size <= 8
                     else f"an array of shape {version.shape}")
            raise SceneError(f"{where}: format_version must be {FORMAT_VERSION}, got {shown!r}")
        for name in _REQUIRED_ARRAYS:
            if name not in arrays:
                raise SceneError(f"{where}: must hold the array {name!r} (a tofcore scene holds "
                                 f"{list(_REQUIRED_ARRAYS)}), got arrays {sorted(arrays)}")
        header = _header(arrays["header"], where)
        materials = []
        for i, md in enumerate(header["materials"]):
            if not isinstance(md, dict):
                raise SceneError(f"{where}: header materials[{i}] must be a JSON object of material "
                                 f"parameters, got {md!r}")
            textures = {}
            for key in _TEXTURE_FIELDS:
                tex_name = f"texture/{i}/{key}"
                if tex_name not in arrays:
                    continue
                label = f"texture_name/{i}/{key}"
                if label not in arrays:
                    raise SceneError(f"{where}: array {label!r} must be present (the name of the texture "
                                     f"array {tex_name!r}, as Scene.save writes), got no such array")
                label_value = arrays[label]
                if label_value.shape != () or label_value.dtype.kind not in "US":
                    raise SceneError(f"{where}: array {label!r} must be a single string, got dtype "
                                     f"{label_value.dtype} shape {label_value.shape}")
                try:
                    label_text = label_value.item()
                    if isinstance(label_text, bytes):
                        label_text = label_text.decode("utf-8", "replace")
                    textures[key] = Texture(arrays[tex_name], name=label_text)
                except (ConfigError, TypeError, ValueError) as err:
                    raise SceneError(f"{where}: array {tex_name!r}: {err}") from None
            try:
                materials.append(Material.from_dict(md, where=f"materials[{i}]", textures=textures))
            except (ConfigError, TypeError) as err:
                raise SceneError(f"{where}: materials[{i}]: {str(err).removeprefix(f'materials[{i}]: ')}") from None
        for name in arrays:
            if name.startswith("texture/"):
                parts = name.split("/")
                if (len(parts) != 3 or not parts[1].isdigit() or int(parts[1]) >= len(materials)
                        or parts[2] not in _TEXTURE_FIELDS):
                    raise SceneError(f"{where}: array {name!r} must be named texture/<material index < "
                                     f"{len(materials)}>/<one of {list(_TEXTURE_FIELDS)}>, got {name!r}")
        try:
            return cls.from_arrays(
                arrays["vertices"], arrays["triangles"], arrays["material_ids"], materials,
                object_ids=arrays["object_ids"], normals=arrays.get("normals"), uvs=arrays.get("uvs"),
                object_names=header["object_names"], name=header["name"], metadata=header["metadata"],
                origin_m=header.get("origin_m", (0.0, 0.0, 0.0)))
        except SceneError as err:
            raise SceneError(f"{where}: {err}") from None


#: Arrays every scene file holds (:meth:`Scene.save`); ``normals``, ``uvs`` and textures are optional.
_REQUIRED_ARRAYS = ("format_version", "header", "vertices", "triangles", "material_ids", "object_ids")
#: Material fields that hold a texture (``texture/<i>/<field>`` and ``texture_name/<i>/<field>`` arrays).
_TEXTURE_FIELDS = tuple(f.name for f in fields(Material) if f.name.endswith("_texture"))
_NPY_MAGIC = b"\x93NUMPY"


def _not_a_scene(where: str, got: str) -> SceneError:
    return SceneError(f"{where}: must be a tofcore scene file (.npz: a zip archive of .npy arrays, as "
                      f"Scene.save writes), got {got}")


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz``, each checked against its zip entry and the size limit before it is read."""
    where = str(path)
    try:
        if not path.is_file():
            kind = "a folder" if path.is_dir() else "no such file" if not path.exists() else "a special file"
            raise SceneError(f"{where}: must be a scene file, got {kind}")
        size = path.stat().st_size
        with open(path, "rb") as fh:
            start = fh.read(8)
    except OSError as exc:
        raise SceneError(f"{where}: cannot read the scene file ({exc.strerror or exc})") from None
    if size == 0:
        raise _not_a_scene(where, "an empty file")
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, ValueError, OSError, NotImplementedError) as exc:
        got = ("a single .npy array (numpy.save), not an archive of arrays" if start.startswith(_NPY_MAGIC)
               else f"a damaged or truncated zip archive ({exc})" if start.startswith(b"PK")
               else f"a file that is not a zip archive (it starts with {start!r})")
        raise _not_a_scene(where, got) from None
    limit = limits.MAX_SCENE_BYTES
    arrays: dict[str, np.ndarray] = {}
    with archive:
        infos = archive.infolist()
        if not infos:
            raise _not_a_scene(where, "an empty zip archive")
        total = 0
        entries = []
        for info in infos:
            if not info.filename.endswith(".npy") or info.is_dir():
                raise _not_a_scene(where, f"a zip archive holding {info.filename!r}, which is not a .npy array")
            name = info.filename[:-4]
            if name in (e[0] for e in entries):
                raise SceneError(f"{where}: array names must be unique, got {name!r} twice")
            if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
                raise SceneError(f"{where}: array {name!r} must be stored or deflate-compressed (as numpy.savez "
                                 f"writes), got zip compression method {info.compress_type}")
            total += info.file_size
            limit.check(info.file_size, where, f"array {name!r} (uncompressed size from the zip directory)",
                        f"{info.file_size:,} bytes")
            entries.append((name, info))
        limit.check(total, where, "the arrays together (uncompressed size from the zip directory)",
                    f"{total:,} bytes")
        for name, info in entries:
            try:
                with archive.open(info) as fh:
                    shape, fortran, dtype, header_bytes = _npy_header(fh, where, name)
                    count = math.prod(shape)
                    nbytes = count * dtype.itemsize
                    limit.check(nbytes, where, f"array {name!r} (shape {shape} x {dtype} from its .npy header)",
                                f"{nbytes:,} bytes")
                    if nbytes != info.file_size - header_bytes:
                        raise SceneError(f"{where}: array {name!r} must hold the {nbytes:,} bytes its .npy header "
                                         f"declares (shape {shape}, dtype {dtype}), got "
                                         f"{info.file_size - header_bytes:,} bytes")
                    if not _wanted(name):
                        continue
                    arrays[name] = _read_data(fh, count, dtype).reshape(shape, order="F" if fortran else "C")
            except TofError:  # SceneError, LimitError: already say what is wrong
                raise
            except (zipfile.BadZipFile, zlib.error, EOFError, ValueError, OSError, RuntimeError,
                    NotImplementedError) as exc:
                raise SceneError(f"{where}: array {name!r} cannot be read: the file is damaged or truncated "
                                 f"({exc})") from None
    return arrays


def _read_data(fh, count: int, dtype: np.dtype) -> np.ndarray:
    """``count`` items of ``dtype`` read in 16 MiB pieces straight into the array (no second copy in memory)."""
    out = np.empty(count, dtype=dtype)
    view = memoryview(out.view(np.uint8).reshape(-1)) if out.nbytes else memoryview(b"")
    done = 0
    while done < out.nbytes:
        chunk = fh.read(min(1 << 24, out.nbytes - done))
        if not chunk:
            raise EOFError(f"{done:,} of {out.nbytes:,} bytes")
        view[done:done + len(chunk)] = chunk
        done += len(chunk)
    return out


def _wanted(name: str) -> bool:
    """Arrays :meth:`Scene.load` uses (others are checked for size, then skipped)."""
    return name in _REQUIRED_ARRAYS or name in ("normals", "uvs") or name.startswith(("texture/", "texture_name/"))


def _npy_header(fh, where: str, name: str) -> tuple[tuple[int, ...], bool, np.dtype, int]:
    """(shape, Fortran order, dtype, bytes before the data) of a ``.npy`` stream; SceneError unless the dtype is
    plain numbers or strings."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(fh)
        if version == (1, 0):
            shape, fortran, dtype = fmt.read_array_header_1_0(fh)
        elif version == (2, 0):
            shape, fortran, dtype = fmt.read_array_header_2_0(fh)
        else:
            shape, fortran, dtype = fmt._read_array_header(fh, version)
    except (ValueError, EOFError, SyntaxError, TypeError, KeyError) as exc:
        raise SceneError(f"{where}: array {name!r} must be a .npy array, got an unreadable header ({exc})") from None
    if dtype.hasobject or dtype.kind not in "biufcUS" or dtype.fields is not None:
        raise SceneError(f"{where}: array {name!r} must be a numeric or string array (no Python objects), "
                         f"got dtype {dtype}")
    return tuple(int(n) for n in shape), bool(fortran), dtype, fh.tell()


def _header(value: np.ndarray, where: str) -> dict:
    """The JSON header of a scene file, checked: materials (list), name, object_names, metadata."""
    if value.shape != () or value.dtype.kind not in "US":
        raise SceneError(f"{where}: header must be a single JSON string, got dtype {value.dtype} shape {value.shape}")
    text = value.item()
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError:
            raise SceneError(f"{where}: header must be UTF-8 JSON text, got undecodable bytes") from None
    try:
        header = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise SceneError(f"{where}: header must be a JSON object (as Scene.save writes), got text that is not "
                         f"JSON ({exc}): {text[:60]!r}") from None
    if not isinstance(header, dict):
        raise SceneError(f"{where}: header must be a JSON object, got {type(header).__name__} {text[:60]!r}")
    if "materials" not in header:
        raise SceneError(f"{where}: header must have the key 'materials' (a list of material parameter objects), "
                         f"got keys {sorted(header)}")
    if not isinstance(header["materials"], list):
        raise SceneError(f"{where}: header materials must be a list of material objects, got {header['materials']!r}")
    name = header.setdefault("name", Path(where).stem)
    if not isinstance(name, str):
        raise SceneError(f"{where}: header name must be a string, got {name!r}")
    names = header.setdefault("object_names", [])
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise SceneError(f"{where}: header object_names must be a list of strings, got {names!r}")
    metadata = header.setdefault("metadata", {})
    if not isinstance(metadata, dict):
        raise SceneError(f"{where}: header metadata must be a JSON object, got {metadata!r}")
    pose = metadata.get("world_from_sensor")
    if pose is not None:
        try:
            matrix = np.asarray(pose, dtype=np.float64)
        except (TypeError, ValueError):
            matrix = None
        if matrix is None or matrix.shape != (4, 4) or not np.isfinite(matrix).all():
            raise SceneError(f"{where}: header metadata.world_from_sensor must be a 4x4 matrix of finite numbers, "
                             f"got {pose!r}")
        problem = rigid_problem(matrix)
        if problem is not None:
            raise SceneError(f"{where}: header metadata.world_from_sensor must be a rigid transform: {problem}")
    return header


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
        try:
            origin = np.asarray(origin_m, dtype=np.float64)
        except (TypeError, ValueError):
            origin = np.full(1, np.nan)
        if origin.shape != (3,) or not np.isfinite(origin).all() or np.abs(origin).max() > FLOAT32_MAX_M:
            raise SceneError(f"{where}: origin_m must be 3 finite numbers (metres) within float32 range "
                             f"(|x| <= {FLOAT32_MAX_M:.3g}: world-frame outputs are float32), got {origin_m!r}")
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
