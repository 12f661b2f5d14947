"""What a ray finds where it hits: position, normals, shading frame and material parameters.

:func:`surface_at` turns the BVH's (triangle, barycentrics) into the local
geometry the integrator needs. Conventions:

* positions in float64 (path lengths are summed from them, DESIGN.md): the
  float64 ray is intersected again with the plane of the triangle the BVH
  found, so a hit point lies on its ray to float64 precision, not to the
  float32 precision of the BVH's barycentrics;
* the geometric normal is flipped to face the incoming ray (surfaces are
  two-sided), the shading normal (interpolated vertex normals, then the
  normal map) is flipped to the same side;
* the shading frame is an orthonormal basis (tangent, bitangent, normal) with
  the shading normal as z, built branch-free (Duff et al. 2017, "Building an
  orthonormal basis, revisited").
"""

from __future__ import annotations

from dataclasses import dataclass

import functools

import numpy as np

from ..backend import device_copy
from ..scene.bsdf import SurfaceParams
from ..scene.material import PARAMETER_NAMES, TEXTURE_SLOTS
from ..scene.scene import Scene


@dataclass(frozen=True)
class Surface:
    """Local geometry at N hit points (world frame)."""

    position: np.ndarray          # (N, 3) float64, metres
    geometric_normal: np.ndarray  # (N, 3) float64, unit, facing the incoming ray
    tangent: np.ndarray           # (N, 3) float64, shading frame x
    bitangent: np.ndarray         # (N, 3) float64, shading frame y
    shading_normal: np.ndarray    # (N, 3) float64, shading frame z, same side as geometric_normal
    params: SurfaceParams         # reflection model parameters per point

    def to_local(self, w: np.ndarray) -> np.ndarray:
        """World directions (N, 3) into the shading frame."""
        return np.stack([dot(w, self.tangent), dot(w, self.bitangent), dot(w, self.shading_normal)], axis=1)

    def take(self, index: np.ndarray) -> Surface:
        """The hit points ``index`` (integer array) as a Surface of their own."""
        return Surface(position=self.position[index], geometric_normal=self.geometric_normal[index],
                       tangent=self.tangent[index], bitangent=self.bitangent[index],
                       shading_normal=self.shading_normal[index], params=self.params.take(index))

    def to_world(self, w: np.ndarray) -> np.ndarray:
        """Shading-frame directions (N, 3) into the world frame."""
        return (w[:, 0:1] * self.tangent + w[:, 1:2] * self.bitangent + w[:, 2:3] * self.shading_normal)


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products of (N, 3) arrays, summed in a fixed order on every backend.

    Not ``einsum``: CuPy runs ``einsum("ij,ij->i")`` as N batched 1×3 matrix products (cuBLAS), which
    measured ~1 ms per call on the Kinect frame's 3.5 M paths — the largest cost of the GPU trace.
    """
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def rotate(v: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """``v @ rotation.T`` for (N, 3) vectors and a 3 × 3 rotation, without BLAS.

    A BLAS matrix product of N × 3 by 3 × 3 wakes every BLAS thread of the process for a product that
    gains nothing from threads; three broadcast products keep the tracer free of BLAS altogether.
    """
    return v[:, 0:1] * rotation[:, 0] + v[:, 1:2] * rotation[:, 1] + v[:, 2:3] * rotation[:, 2]


SPAWN_RELATIVE = 2.0**-16
"""Ray offsets from a surface, relative to the float32 error bound of the hit point (:func:`spawn_offset`).

2⁻¹⁶ is 128 float32 ulps (2⁻²³) of a coordinate: far above the rounding of a float32 hit point and of
the triangle test near it (so no self-hit on a neighbouring triangle), far below any feature a ToF pixel
resolves (15 µm at 1 m from the scene frame's origin).
"""

LEAVE_RELATIVE = 2.0**-21
"""Offsets of rays that start at the lens or an LED (:func:`leaving`), relative to that point's coordinates.

4 float32 ulps: enough that a wall through the lens (a camera mounted flush with it) is not hit at
t ≈ 0, small enough that a wall 1 µm in front of a lens 1.5 m from the origin is still seen (0.7 µm).
"""

OFFSET_FLOOR_M = 1e-3
"""Coordinates below a millimetre count as a millimetre in the offsets (points at the scene frame's origin)."""


def spawn_offset(position: np.ndarray, normal: np.ndarray, corners: np.ndarray) -> np.ndarray:
    r"""(N,) distances to move hit points along their geometric normals before a ray leaves them.

    After pbrt-v4 (``OffsetRayOrigin``, error bounds from the intersection) and Mitsuba 3 (ray epsilon
    scaled by the point's magnitude), never from the scene's extent: a 2000 km ground plane does not
    move the rays of a wall 2 m away.

    .. math::

        \delta = 2^{-16} \max\big(\lVert p \rVert_\infty,\; \textstyle\sum_k |n_k| \max_i |p_{i,k}|,
        \; 1\,\mathrm{mm}\big)

    The second term is pbrt's bound γ·Σᵢ|bᵢ pᵢ| of a point interpolated from the triangle's corners pᵢ,
    projected on the normal (barycentrics bᵢ ≤ 1): a large triangle far from the origin needs a large
    offset, an axis-aligned one (a ground plane z = 0) none along its normal.

    Parameters
    ----------
    position : (N, 3) hit points, scene frame, metres.
    normal : (N, 3) unit geometric normals.
    corners : (N, 3, 3) the corners of each hit triangle (corner, axis), metres.
    """
    own = np.abs(position).max(axis=1)
    local = dot(np.abs(normal), np.abs(corners).max(axis=1))
    return SPAWN_RELATIVE * np.maximum(np.maximum(own, local), OFFSET_FLOOR_M)


def point_offset(point: np.ndarray, relative: float = SPAWN_RELATIVE) -> np.ndarray:
    """(N,) ``relative`` × the largest coordinate of each point (at least :data:`OFFSET_FLOOR_M`)."""
    return relative * np.maximum(np.abs(point).max(axis=1), OFFSET_FLOOR_M)


def leaving(origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """float32 ray origins moved along their rays by :data:`LEAVE_RELATIVE` of their coordinates, for rays
    that start at the lens or an LED rather than on a surface: a camera or LED mounted flush with a wall
    does not hit that wall at t ≈ 0.

    Only the intersection query starts there: path lengths are measured from the true point, and
    :func:`surface_at` gets the true origin.
    """
    return (origin + point_offset(origin, LEAVE_RELATIVE)[:, None] * direction).astype(np.float32)


def shadow_ray(spawn: np.ndarray, target: np.ndarray, margin_m: np.ndarray):
    """float32 (origins, unit directions, t_max) of shadow rays from ``spawn`` that stop ``margin_m`` (per
    ray) short of ``target`` (an LED, or a light vertex on a surface).

    Aimed and measured from the spawn point itself, not from the surface point it was offset from: the
    surface at the target (an LED mounted flush with a wall, the light vertex's own triangle) then lies
    at t = |target − spawn|, a full margin beyond t_max whatever the angle of arrival.
    """
    to_target = target - spawn
    length = np.linalg.norm(to_target, axis=1)
    direction = to_target / np.where(length > 0, length, 1.0)[:, None]
    return spawn.astype(np.float32), direction.astype(np.float32), (length - margin_m).astype(np.float32)


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def orthonormal_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tangent and bitangent completing unit normals ``n`` (N, 3) to a right-handed frame (Duff et al. 2017)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    bt = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return t, bt


class MaterialTable:
    """The scene's arrays and per-material parameters on one device, for vectorised lookup by index.

    ``xp`` is the array module the tracer runs on (NumPy, or CuPy for the GPU): the scene's
    triangles, vertices, normals, UVs and ids are uploaded once (:func:`tofcore.backend.device_copy`).
    """

    def __init__(self, scene: Scene, xp=np):
        self.scene = scene
        self.xp = xp
        self.values = {k: xp.asarray(np.array([getattr(m, k) for m in scene.materials], np.float64))
                       for k in PARAMETER_NAMES}
        self.textured = [i for i, m in enumerate(scene.materials) if m.textures]
        on_device = functools.partial(device_copy, xp)
        self.triangles = on_device(scene.triangles)
        self.vertices = on_device(scene.vertices)
        self.face_normals = on_device(scene.face_normals)
        self.normals = None if scene.normals is None else on_device(scene.normals)
        self.uvs = None if scene.uvs is None else on_device(scene.uvs)
        self.material_ids = on_device(scene.material_ids)
        self.object_ids = on_device(scene.object_ids)

    def __getstate__(self) -> dict:
        """Pickle for CPU worker processes (tofcore.tracer.workers); the array module travels by name."""
        if self.xp is not np:
            raise TypeError("a MaterialTable on the GPU does not pickle: GPU renders run in one process")
        return {k: v for k, v in self.__dict__.items() if k != "xp"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state, xp=np)

    @property
    def has_textures(self) -> bool:
        return bool(self.textured)


def surface_geometry(table: MaterialTable, prim: np.ndarray, u: np.ndarray, v: np.ndarray,
                     ray_origin: np.ndarray, ray_direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(position (N, 3), geometric normal (N, 3) facing the ray) where rays (float64 origins, unit
    directions) hit triangles ``prim`` at barycentrics (u, v): float64 ray–plane intersection
    p = o + t d, t = (v₀ − o)·n_g / (d·n_g) — the BVH's float32 barycentrics only select the triangle —
    or the barycentric point where the ray grazes the plane (|d·n_g| ≤ 1e-9)."""
    tri = table.triangles[prim]
    w0 = (1.0 - u - v).astype(np.float64)[:, None]
    u64 = u.astype(np.float64)[:, None]
    v64 = v.astype(np.float64)[:, None]
    verts = table.vertices
    ng = table.face_normals[prim].astype(np.float64)
    cos_ray = dot(ray_direction, ng)
    steep = np.abs(cos_ray) > 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        t = dot(verts[tri[:, 0]].astype(np.float64) - ray_origin, ng) / cos_ray
    position = np.where(steep[:, None], ray_origin + t[:, None] * ray_direction,
                        w0 * verts[tri[:, 0]] + u64 * verts[tri[:, 1]] + v64 * verts[tri[:, 2]])
    facing = np.where(dot(ng, ray_direction) > 0, -1.0, 1.0)[:, None]
    return position, ng * facing


def surface_at(scene: Scene, table: MaterialTable, prim: np.ndarray, u: np.ndarray, v: np.ndarray,
               ray_origin: np.ndarray, ray_direction: np.ndarray) -> Surface:
    """Surface where rays (float64 origins, unit directions; world frame) hit triangles ``prim`` at barycentrics (u, v)."""
    position, ng = surface_geometry(table, prim, u, v, ray_origin, ray_direction)
    tri = table.triangles[prim]
    w0 = (1.0 - u - v).astype(np.float64)[:, None]
    u64 = u.astype(np.float64)[:, None]
    v64 = v.astype(np.float64)[:, None]
    if table.normals is not None:
        nrm = table.normals
        ns = _normalize(w0 * nrm[tri[:, 0]] + u64 * nrm[tri[:, 1]] + v64 * nrm[tri[:, 2]])
    else:
        ns = ng.copy()

    mat = table.material_ids[prim]
    values = {k: table.values[k][mat] for k in PARAMETER_NAMES}
    if table.has_textures:
        uv = w0 * table.uvs[tri[:, 0]] + u64 * table.uvs[tri[:, 1]] + v64 * table.uvs[tri[:, 2]]
        for i in table.textured:
            sel = np.flatnonzero(mat == i)
            if len(sel) == 0:
                continue
            m = scene.materials[i]
            for slot in TEXTURE_SLOTS[:-1]:
                tex = getattr(m, slot)
                if tex is not None:
                    values[slot.removesuffix("_texture")][sel] = tex.sample(uv[sel])
            if m.normal_texture is not None:
                ns[sel] = _perturb(table, prim[sel], ns[sel] * np.sign(dot(ns[sel], ng[sel]))[:, None],
                                   m.normal_texture.sample(uv[sel])[:, :3])
    ns = ns * np.where(dot(ns, ng) < 0, -1.0, 1.0)[:, None]
    tangent, bitangent = orthonormal_basis(ns)
    params = SurfaceParams(
        reflectance=np.clip(values["reflectance"], 0.0, 1.0), roughness=np.maximum(values["roughness"], 0.0),
        metallic=np.clip(values["metallic"], 0.0, 1.0), ior=values["ior"], extinction=values["extinction"],
        coat=values["coat"], coat_roughness=values["coat_roughness"])
    return Surface(position=position, geometric_normal=ng, tangent=tangent, bitangent=bitangent,
                   shading_normal=ns, params=params)


def _perturb(table: MaterialTable, prim: np.ndarray, n: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """Apply a tangent-space normal map (RGB in [0, 1]) to shading normals ``n``.

    The tangent follows increasing u on the triangle (dP/du from the UV
    parametrisation, Gram–Schmidt against n); the bitangent is n × t.
    """
    tri = table.triangles[prim]
    p = table.vertices.astype(np.float64)
    uv = table.uvs.astype(np.float64)
    e1, e2 = p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]]
    d1, d2 = uv[tri[:, 1]] - uv[tri[:, 0]], uv[tri[:, 2]] - uv[tri[:, 0]]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        dpdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / det[:, None]
    fallback, _ = orthonormal_basis(n)
    dpdu = np.where(np.isfinite(dpdu).all(axis=1, keepdims=True), dpdu, fallback)
    t = dpdu - dot(dpdu, n)[:, None] * n
    norm = np.linalg.norm(t, axis=1, keepdims=True)
    t = np.where(norm > 1e-12, t / np.maximum(norm, 1e-300), fallback)
    b = np.cross(n, t)
    m = 2.0 * rgb.astype(np.float64) - 1.0
    return _normalize(m[:, 0:1] * t + m[:, 1:2] * b + np.maximum(m[:, 2:3], 1e-3) * n)
