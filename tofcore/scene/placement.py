"""Objects placed on the upward surfaces of a scene without interpenetration: sample, test, reject.

:func:`place_objects` puts meshes (a library's objects, :mod:`tofcore.scene.primitives`) on a base
scene, one after the other, each by rejection sampling:

1. a support point, uniform by area over the base's *upward* triangles (face normal, the side the
   file's vertex order makes the front, :math:`n_z \\ge` ``min_up_cos``: a room's ceiling faces down);
2. the object scaled so its largest bounding-box side is the drawn ``size_m``, tilted about X by
   ``tilt`` and turned about Z by ``yaw`` (radians), its lowest vertex ``gap_m`` above the point;
3. rejected when it would interpenetrate anything:

   * an edge of the object crosses a base triangle (the base's BVH, any hit along the edge);
   * an edge of a base triangle near the object crosses an object triangle (the object's BVH);
   * a base vertex lies inside the object's bounding box (a base part swallowed whole);
   * it is inside a closed base object: the ray from the object's centre straight up first meets a
     surface from behind (:math:`n \\cdot \\hat z > 0`: the inside of a closed box);
   * its bounding box overlaps the bounding box of an object placed before (conservative: objects
     never touch each other).

Two triangles that intersect (not coplanar) always have an edge of one crossing the other, so the
first two tests find every crossing of surfaces; the last three find containment. After
``max_attempts`` rejections the object is left out (:attr:`Placed.skipped` counts them).

:func:`compose` merges the placed objects into one scene with the base: object ids follow the base's,
object names ``"<mesh name> #<i>"``, materials appended (named as in the mesh, one set per object).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from .bvh import BVH
from .scene import Scene


@dataclass(frozen=True)
class Placement:
    """One placed object: which mesh, its transform (object → world, 4×4) and what was drawn."""

    mesh: str
    world_from_object: np.ndarray
    size_m: float
    yaw_rad: float
    tilt_rad: float
    support_m: tuple[float, float, float]
    bounds_m: tuple[tuple[float, float, float], tuple[float, float, float]]  # world AABB (lo, hi)


@dataclass
class Placed:
    """What :func:`place_objects` placed, in order, and how many objects found no place."""

    placements: list[Placement] = field(default_factory=list)
    skipped: int = 0
    attempts: int = 0


def rotation(yaw_rad: float, tilt_rad: float) -> np.ndarray:
    """R = R_z(yaw) · R_x(tilt): tilt about the object's X axis, then turn about the world's Z axis."""
    cy, sy, ct, st = np.cos(yaw_rad), np.sin(yaw_rad), np.cos(tilt_rad), np.sin(tilt_rad)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, ct, -st], [0.0, st, ct]])
    return rz @ rx


def upward_triangles(scene: Scene, min_up_cos: float) -> np.ndarray:
    """Indices of the triangles whose face normal is within acos(``min_up_cos``) of +Z."""
    return np.flatnonzero(scene.face_normals[:, 2].astype(np.float64) >= min_up_cos)


def _area(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)


def _edges(v: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique edges as (start, end) points."""
    e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    e = np.unique(e, axis=0)
    return v[e[:, 0]], v[e[:, 1]]


def segments_cross(bvh: BVH, start: np.ndarray, end: np.ndarray) -> bool:
    """Whether any segment start→end hits a triangle of ``bvh`` strictly between its ends."""
    if not len(start):
        return False
    d = end - start
    length = np.linalg.norm(d, axis=1)
    keep = length > 1e-9
    d = d[keep] / length[keep, None]
    return bool(bvh.occluded(start[keep].astype(np.float32), d.astype(np.float32),
                             length[keep].astype(np.float32), workers=1).any())


def interpenetrates(base: Scene, base_bvh: BVH, vertices_m: np.ndarray, triangles: np.ndarray) -> bool:
    """Whether a mesh (scene-frame vertices) crosses or swallows part of ``base`` or sits inside a closed
    base object (the tests 3 of the module docstring, except the one between placed objects)."""
    lo, hi = vertices_m.min(axis=0), vertices_m.max(axis=0)
    start, end = _edges(vertices_m, triangles)
    if segments_cross(base_bvh, start, end):
        return True
    bv = base.vertices.astype(np.float64)
    if np.all((bv > lo) & (bv < hi), axis=1).any():
        return True
    bt = base.triangles
    tri_lo, tri_hi = bv[bt].min(axis=1), bv[bt].max(axis=1)
    near = np.all((tri_hi >= lo) & (tri_lo <= hi), axis=1)
    if near.any():
        obj_bvh = BVH.build(vertices_m.astype(np.float32), triangles)
        s, e = _edges(bv, bt[near])
        if segments_cross(obj_bvh, s, e):
            return True
    centre = 0.5 * (lo + hi)
    hit = base_bvh.intersect(centre[None].astype(np.float32), np.array([[0.0, 0.0, 1.0]], np.float32), workers=1)
    return bool(hit.prim[0] >= 0 and base.face_normals[hit.prim[0], 2] > 0)


def place_objects(base: Scene, meshes: Sequence[tuple[str, Scene]], count: int, rng: np.random.Generator, *,
                  draw_size: Callable[[np.random.Generator], float],
                  draw_yaw: Callable[[np.random.Generator], float],
                  draw_tilt: Callable[[np.random.Generator], float],
                  min_up_cos: float = 0.9, gap_m: float = 0.002, max_attempts: int = 50) -> Placed:
    """Place ``count`` objects drawn from ``meshes`` ((name, scene) pairs) on ``base``; see the module docstring.

    ``draw_size`` (m), ``draw_yaw`` and ``draw_tilt`` (rad) draw from ``rng``; everything drawn comes from
    ``rng`` in a fixed order, so the same stream places the same objects.
    """
    placed = Placed()
    support = upward_triangles(base, min_up_cos)
    if not len(support) or not meshes:
        placed.skipped = count
        return placed
    bv = base.vertices.astype(np.float64)
    st = base.triangles[support]
    weights = _area(bv, st)
    weights /= weights.sum()
    base_bvh = base.bvh
    origin = np.asarray(base.origin_m)
    boxes: list[tuple[np.ndarray, np.ndarray]] = []
    for _ in range(count):
        for _attempt in range(max_attempts):
            placed.attempts += 1
            name, mesh = meshes[int(rng.integers(len(meshes)))]
            size, yaw, tilt = float(draw_size(rng)), float(draw_yaw(rng)), float(draw_tilt(rng))
            tri = st[int(rng.choice(len(st), p=weights))]
            r1, r2 = rng.random(2)
            s1 = np.sqrt(r1)
            point = (1 - s1) * bv[tri[0]] + s1 * (1 - r2) * bv[tri[1]] + s1 * r2 * bv[tri[2]]
            mv = mesh.vertices.astype(np.float64) + np.asarray(mesh.origin_m)
            lo, hi = mv.min(axis=0), mv.max(axis=0)
            scale = size / float(np.max(hi - lo))
            local = (mv - 0.5 * (lo + hi)) * scale @ rotation(yaw, tilt).T
            offset = point + np.array([0.0, 0.0, gap_m - local[:, 2].min()])
            verts = local + offset  # scene frame
            v_lo, v_hi = verts.min(axis=0), verts.max(axis=0)
            if any(np.all(v_hi >= b_lo) and np.all(v_lo <= b_hi) for b_lo, b_hi in boxes):
                continue
            if interpenetrates(base, base_bvh, verts, mesh.triangles):
                continue
            boxes.append((v_lo, v_hi))
            m = np.eye(4)
            m[:3, :3] = rotation(yaw, tilt) * scale
            m[:3, 3] = offset + origin - m[:3, :3] @ (0.5 * (lo + hi))
            placed.placements.append(Placement(
                mesh=name, world_from_object=m, size_m=size, yaw_rad=yaw, tilt_rad=tilt,
                support_m=tuple((point + origin).tolist()),
                bounds_m=(tuple((v_lo + origin).tolist()), tuple((v_hi + origin).tolist()))))
            break
        else:
            placed.skipped += 1
    return placed


def compose(base: Scene, meshes: dict[str, Scene], placements: Sequence[Placement],
            materials: Callable[[str, int, tuple], tuple] | None = None) -> Scene:
    """The base scene with every placed object merged in (see the module docstring).

    ``materials(mesh name, object index, mesh materials)`` may replace an object's materials (same count).
    """
    origin = np.asarray(base.origin_m)
    verts = [base.vertices.astype(np.float64)]
    tris, mat_ids, obj_ids = [base.triangles], [base.material_ids], [base.object_ids]
    mats = list(base.materials)
    names = list(base.object_names) + [f"object {i}" for i in range(len(base.object_names),
                                                                     int(base.object_ids.max()) + 1)]
    uvs = [base.uvs] if base.uvs is not None else None
    n = len(verts[0])
    for i, p in enumerate(placements):
        mesh = meshes[p.mesh]
        mv = mesh.vertices.astype(np.float64) + np.asarray(mesh.origin_m)
        world = mv @ p.world_from_object[:3, :3].T + p.world_from_object[:3, 3]
        verts.append(world - origin)
        tris.append(mesh.triangles + n)
        own = tuple(materials(p.mesh, i, mesh.materials) if materials else mesh.materials)
        mat_ids.append(mesh.material_ids + len(mats))
        mats.extend(own)
        obj_ids.append(np.full(len(mesh.triangles), len(names), np.int32))
        names.append(f"{p.mesh} #{i}")
        if uvs is not None:
            uvs.append(mesh.uvs if mesh.uvs is not None else np.zeros((len(mv), 2), np.float32))
        n += len(mv)
    if uvs is None and any(m.textures for m in mats):
        uvs = [np.zeros((len(v), 2), np.float32) for v in verts]
    return Scene.from_arrays(np.concatenate(verts), np.concatenate(tris), np.concatenate(mat_ids), mats,
                             object_ids=np.concatenate(obj_ids), object_names=names, name=base.name,
                             uvs=None if uvs is None else np.concatenate(uvs), metadata=dict(base.metadata),
                             origin_m=base.origin_m)
