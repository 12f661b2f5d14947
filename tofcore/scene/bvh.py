"""Ray-triangle bounding volume hierarchy in pure NumPy.

The scene is a triangle mesh in world space (metres, float32).  `BVH.build`
makes a binary tree with a binned surface area heuristic (SAH), built level by
level with array operations, and collapses it into a 4-wide tree whose child
boxes are stored as float32 structure-of-arrays.  `BVH.intersect` (closest hit)
and `BVH.occluded` (any hit, early exit per ray) traverse it breadth first over
flat arrays of (ray, node) pairs, `RAY_CHUNK` rays at a time, optionally on
two threads.  `intersect_brute` is the reference the tests compare against.

Conventions
-----------
* Rays are ``origin + t * direction`` with unit ``direction``; ``t`` is the
  distance in metres.  Only hits with ``0 < t < t_max`` count.
* A hit reports the triangle index into the ``triangles`` array given to
  `BVH.build` and barycentrics ``u, v`` such that the point is
  ``(1 - u - v) * v0 + u * v1 + v * v2``.  Triangles are two-sided.
* ``ignore_prim`` names, per ray, one triangle that never counts as hit (the
  triangle the ray leaves from; ``-1`` for none).  Neighbours of that
  triangle are not ignored: a ray leaving a surface exactly on a shared edge
  may still hit the neighbour at ``t`` of a few ulps.

Accuracy
--------
The triangle test is watertight (`_watertight`): a ray through an edge or a
vertex shared by triangles hits at least one of them.  Node boxes are padded
by `BOX_PAD` so that the tree never culls a triangle the test accepts (as long
as ray origins are within ~100 scene sizes of the scene); the BVH and the
brute force then agree exactly, up to the choice between triangles hit at the
same ``t`` (the brute force takes the lowest index, the BVH the first found).

Traversal
---------
Rays are sorted by octant (sign bits of the direction) and cut into chunks of
`RAY_CHUNK`.  For an octant, each axis' entry and exit planes are fixed rows
of the node records (the box minimum or maximum, by the sign), and the pairs
of one octant stay contiguous, so a slab test of four children is six gathers
of 4-float rows, six subtractions, six multiplications by the inverse
direction (components below ``1e-30`` replaced by ``±1e-30``) and elementwise
``minimum``/``maximum``.  Per-ray values are stored repeated four times, so
every arithmetic operation runs on contiguous arrays.  Leaves hold up to
``leaf_size`` triangles as one padded row (padding is NaN and never hits).
Leaves met at a level are tested before the next level is expanded, and the
box test clips each ray at its best hit so far; `occluded` drops a ray's
pairs as soon as it is occluded.
"""

from __future__ import annotations

import functools
import hashlib
import threading
import time
import warnings
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..backend import device_twin
from ..errors import ConfigError, SceneError

BOX_PAD = 2.0**-16
"""Relative padding of node boxes: times (largest |coordinate| + largest extent) of the box."""

WIDTH = 4
"""Children per node of the traversed tree."""

N_BINS = 32
"""SAH bins per axis and node."""

COMPILED_BUILD_MIN = 4096
"""Meshes with fewer triangles are built by the NumPy levels alone (:func:`_split_level`): milliseconds,
less than importing numba for the compiled levels (:mod:`tofcore.scene.bvh_build`)."""

COMPILE_PAYS_MIN = 1_000_000
"""Meshes of fewer triangles use the compiled build only where numba's cache holds it (``tofcore warmup``
compiles it; so does a first build of a bigger mesh): compiling it costs 4.1 s (a 10k-triangle room) to 6.3 s
(200k) once, more than the NumPy build of those meshes (0.06 s and 1.5 s; ≈ 6 µs a triangle, 3.1 s at 500k: 2
cores, 2026-12-02). So a fresh install's first render of the demo room does not wait for a compile that saves
it 55 ms."""


def _compiled_build_pays(m: int) -> bool:
    """Whether a mesh of ``m`` triangles is built in compiled loops (where numba runs): at least
    `COMPILED_BUILD_MIN` triangles, and the loops cached or the mesh big enough to pay for their compile
    (`COMPILE_PAYS_MIN`)."""
    if m < COMPILED_BUILD_MIN:
        return False
    from . import bvh_build  # imports numba: only for meshes that may need it

    return bvh_build.available() and (m >= COMPILE_PAYS_MIN or bvh_build.cached(m >= bvh_build.PARALLEL_LEVEL))


RAY_CHUNK = 8192
"""Rays traversed together; keeps the per-level temporaries in L2."""

_WIDTH_BITS = WIDTH.bit_length() - 1  # flat (pair, child) index >> this = pair
_NODE_ROWS = 7  # rows of a node record: box minimum x, y, z; maximum x, y, z; children
_LEAF_ROWS = 10  # rows of a leaf record: v0 xyz, v1 xyz, v2 xyz, triangle index
_RAY_BOX_ROWS = 7  # rows of a ray's box record: origin xyz, inverse direction xyz, best t
_RAY_LEAF_ROWS = 13  # rows of a ray's leaf record: origin xyz, frame b1, b2, d (xyz each), best t
_CHILD_ROW = 6  # row of the children in a node record
_PRIM_ROW = 9  # row of the triangle indices in a leaf record
_TINY_DIR = 1e-30  # direction components smaller than this are replaced (finite inverse)
_BUILD_BATCH = 16384  # nodes whose SAH bins are evaluated together (bounds build memory)


@dataclass(frozen=True)
class Hits:
    """Closest hits of a batch of rays.

    Attributes
    ----------
    t : (R,) float32 distance along the unit direction in metres; ``inf`` on a miss.
    prim : (R,) int32 triangle index; ``-1`` on a miss.
    u, v : (R,) float32 barycentrics of vertices 1 and 2; ``0`` on a miss.
    """

    t: np.ndarray
    prim: np.ndarray
    u: np.ndarray
    v: np.ndarray


# ----------------------------------------------------------------------------- triangle test


def _ray_frame(d):
    """Orthonormal frame ``(b1, b2)`` perpendicular to unit directions ``d`` (R, 3) float32.

    Duff et al. 2017, "Building an orthonormal basis, revisited" (branchless).
    Returns two (R, 3) float32 arrays.
    """
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    sign = np.where(z >= 0, np.float32(1.0), np.float32(-1.0))
    a = np.float32(-1.0) / (sign + z)
    b = x * y * a
    b1 = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], 1)
    b2 = np.stack([b, sign + y * y * a, -y], 1)
    return b1.astype(np.float32), b2.astype(np.float32)


def _watertight(o, b1, b2, d, v0, v1, v2, t_max):
    r"""Watertight ray-triangle test for broadcastable float32 arrays.

    ``o, b1, b2, d`` (ray origin and frame) and ``v0, v1, v2`` (vertices) are
    3-tuples of arrays (x, y, z); ``t_max`` is the exclusive upper bound of
    ``t``.  Returns ``(hit, t, u, v)``, meaningful where ``hit``.  NaN vertices
    never hit; the caller silences the floating point warnings this causes.
    The brute force and the BVH both call this function, so they round
    identically.

    Notes
    -----
    After Woop, Benthin & Wald 2013, "Watertight ray/triangle intersection",
    with a projection onto the ray's orthonormal frame instead of their
    shear.  The vertices relative to the origin, :math:`a = v_0 - o` etc., get
    frame coordinates :math:`(a \cdot b_1, a \cdot b_2, a \cdot d)`; in the
    plane of the first two the ray is the origin, and the edge functions

    .. math::

        U = c_1 b_2 - c_2 b_1,\quad V = a_1 c_2 - a_2 c_1,\quad W = b_1 a_2 - b_2 a_1

    must share one sign (zero counts as both).  Then
    :math:`t = (U a_3 + V b_3 + W c_3) / (U + V + W)`, :math:`u = V / (U + V + W)`,
    :math:`v = W / (U + V + W)`.  A vertex gets the same frame coordinates in
    every triangle that uses it, and an edge function changes only its sign
    between the two triangles of an edge, so a ray cannot pass between them.
    """

    def frame(v):
        rx, ry, rz = v[0] - o[0], v[1] - o[1], v[2] - o[2]
        return [(rx * f[0]) + (ry * f[1]) + (rz * f[2]) for f in (b1, b2, d)]

    a1, a2, a3 = frame(v0)
    p1, p2, p3 = frame(v1)
    c1, c2, c3 = frame(v2)
    w_u = c1 * p2 - c2 * p1
    w_v = a1 * c2 - a2 * c1
    w_w = p1 * a2 - p2 * a1
    lo = np.minimum(np.minimum(w_u, w_v), w_w)
    hi = np.maximum(np.maximum(w_u, w_v), w_w)
    hit = (lo >= 0) | (hi <= 0)
    det = w_u + w_v + w_w
    t = (w_u * a3 + w_v * p3 + w_w * c3) / det
    hit &= t > 0
    hit &= t < t_max
    return hit, t, w_v / det, w_w / det


def _as_rays(origins, directions, t_max, ignore_prim):
    """Validate and convert ray arrays to float32 (R,3), float32 (R,), int64 (R,)."""
    o = np.ascontiguousarray(origins, dtype=np.float32).reshape(-1, 3)
    d = np.ascontiguousarray(directions, dtype=np.float32).reshape(-1, 3)
    n = len(o)
    if len(d) != n:
        raise ValueError(f"BVH: directions must have the shape of origins {o.shape}, got {d.shape}")
    tm = np.full(n, np.inf, np.float32) if t_max is None else np.asarray(t_max, np.float32)
    tm = np.ascontiguousarray(np.broadcast_to(tm, (n,)))
    ig = np.full(n, -1, np.int64) if ignore_prim is None else np.asarray(ignore_prim, np.int64)
    ig = np.ascontiguousarray(np.broadcast_to(ig, (n,)))
    return o, d, tm, ig


def intersect_brute(vertices, triangles, origins, directions, t_max=None, ignore_prim=None, *,
                    chunk_elems: int = 1 << 20) -> Hits:
    """Closest hits by testing every ray against every triangle (reference).

    Same conventions and triangle test as `BVH.intersect`; ties in ``t`` go to
    the lowest triangle index.  Rays are processed in chunks of about
    ``chunk_elems`` ray-triangle pairs, so memory stays bounded.
    """
    v = np.asarray(vertices, np.float32)
    tri = np.asarray(triangles, np.int64)
    o, d, tm, ig = _as_rays(origins, directions, t_max, ignore_prim)
    n, m = len(o), len(tri)
    vc = [tuple(v[tri[:, i], k][None, :] for k in range(3)) for i in range(3)]  # (1, M) per vertex, axis
    b1, b2 = _ray_frame(d)
    out_t = np.full(n, np.inf, np.float32)
    out_p = np.full(n, -1, np.int32)
    out_u = np.zeros(n, np.float32)
    out_v = np.zeros(n, np.float32)
    step = max(1, chunk_elems // max(m, 1))
    for s in range(0, n if m else 0, step):
        e = min(n, s + step)
        oc, b1c, b2c, dc = (tuple(x[s:e, k][:, None] for k in range(3)) for x in (o, b1, b2, d))
        with np.errstate(divide="ignore", invalid="ignore"):
            hit, t, u, vv = _watertight(oc, b1c, b2c, dc, *vc, tm[s:e, None])
        hit &= np.arange(m)[None, :] != ig[s:e, None]
        t = np.where(hit, t, np.float32(np.inf))
        best = np.argmin(t, axis=1)
        rows = np.arange(e - s)
        ok = np.isfinite(t[rows, best])
        out_t[s:e] = np.where(ok, t[rows, best], np.inf)
        out_p[s:e] = np.where(ok, best, -1)
        out_u[s:e] = np.where(ok, u[rows, best], 0.0)
        out_v[s:e] = np.where(ok, vv[rows, best], 0.0)
    return Hits(t=out_t, prim=out_p, u=out_u, v=out_v)


# ----------------------------------------------------------------------------- build


def _sah_split(lo, hi, cen, seg, n_nodes, n_bins):
    """Best binned-SAH split of ``n_nodes`` nodes whose elements are grouped by ``seg``.

    ``lo, hi, cen`` are (3, E) float32 element boxes and centroids, ``seg`` the
    (E,) node of each element, sorted.  Each node's centroid bounds are cut
    into ``n_bins`` equal bins per axis; the cost of a cut between bins is
    ``area(left) * count(left) + area(right) * count(right)``.  Returns
    ``(go_left, ok)``: (E,) bool side of each element, (n_nodes,) bool whether
    a cut with both sides non-empty exists.
    """
    starts = np.flatnonzero(np.r_[True, seg[1:] != seg[:-1]])
    c_min = np.minimum.reduceat(cen, starts, axis=1)  # (3, K)
    c_max = np.maximum.reduceat(cen, starts, axis=1)
    extent = c_max - c_min
    with np.errstate(divide="ignore"):
        scale = np.where(extent > 0, n_bins * (1 - 1e-6) / extent, 0.0).astype(np.float32)
    best_cost = np.full(n_nodes, np.inf)
    best_axis = np.zeros(n_nodes, np.int64)
    best_cut = np.zeros(n_nodes, np.int64)
    bins = np.empty((3, len(seg)), np.int64)
    for axis in range(3):
        b = ((cen[axis] - c_min[axis][seg]) * scale[axis][seg]).astype(np.int64)
        np.clip(b, 0, n_bins - 1, out=b)
        bins[axis] = b
        key = b * n_nodes + seg  # bin-major, so the sweeps below run over contiguous rows of nodes
        count = np.bincount(key, minlength=n_bins * n_nodes).reshape(n_bins, n_nodes)
        b_lo = np.full((3, n_bins * n_nodes), np.inf, np.float32)
        b_hi = np.full((3, n_bins * n_nodes), -np.inf, np.float32)
        for k in range(3):
            np.minimum.at(b_lo[k], key, lo[k])
            np.maximum.at(b_hi[k], key, hi[k])
        b_lo = b_lo.reshape(3, n_bins, n_nodes)
        b_hi = b_hi.reshape(3, n_bins, n_nodes)
        n_left = np.cumsum(count, axis=0)[:-1]  # (n_bins - 1, n_nodes): cut after bin i
        n_right = n_left[-1:] + count[-1:] - n_left
        area_left = _half_area(*_sweep(b_lo, b_hi))
        area_right = _half_area(*_sweep(b_lo[:, ::-1], b_hi[:, ::-1]))[::-1]
        with np.errstate(invalid="ignore"):
            cost = area_left[:-1] * n_left + area_right[1:] * n_right
        cost[(n_left == 0) | (n_right == 0)] = np.inf
        cut = np.argmin(cost, axis=0)
        c = cost[cut, np.arange(n_nodes)]
        better = c < best_cost
        best_cost[better] = c[better]
        best_axis[better] = axis
        best_cut[better] = cut[better]
    elem_bin = bins[best_axis[seg], np.arange(len(seg))]
    return elem_bin <= best_cut[seg], np.isfinite(best_cost)


def _repeat_rows(values, width):
    """(n, k) values -> (n * k, width) rows of the same dtype, each value repeated ``width`` times."""
    flat = np.ascontiguousarray(values).reshape(-1)
    rows = np.empty((flat.size, width), flat.dtype)
    for j in range(width):  # column copies: far faster than a broadcast assignment
        rows[:, j] = flat
    return rows


def _sweep(lo, hi):
    """Running union of (3, B, K) bin boxes along the bins: box of bins 0..i at i (copies).

    A loop over the few bins, each step on contiguous rows of K nodes, is much
    faster than ``np.minimum.accumulate`` along that axis.
    """
    lo, hi = lo.copy(), hi.copy()
    for i in range(1, lo.shape[1]):
        np.minimum(lo[:, i - 1], lo[:, i], out=lo[:, i])
        np.maximum(hi[:, i - 1], hi[:, i], out=hi[:, i])
    return lo, hi


def _ray_records(o, d, t_max, width_leaf: int):
    """The rays' box records (origin, inverse direction, best t) and leaf records (origin, frame, direction,
    best t), each repeated per child slot; directions below ``_TINY_DIR`` get a finite inverse."""
    neg = d < 0
    safe_d = np.where(np.abs(d) < _TINY_DIR, np.where(neg, -_TINY_DIR, _TINY_DIR), d)
    columns = functools.partial(np.concatenate, axis=1, dtype=np.float32)
    ray_box = _repeat_rows(columns([o, 1.0 / safe_d, t_max[:, None]]), WIDTH)
    ray_leaf = _repeat_rows(columns([o, *_ray_frame(d), d, t_max[:, None]]), width_leaf)
    return ray_box, ray_leaf


def _slab_test(box_rows, segments, pair_node, first):
    """(t_in, t_out) of every (ray, node) pair's WIDTH child boxes (slab test, clipped to [0, best t])."""
    t_in, t_out = _gather_planes(segments, 0, pair_node), _gather_planes(segments, 3, pair_node)
    for a in range(3):
        o_a = box_rows[a].take(first, 0, None, "clip")
        inv_a = box_rows[3 + a].take(first, 0, None, "clip")
        near = t_in if a == 0 else _gather_planes(segments, a, pair_node)
        near -= o_a
        near *= inv_a
        far = t_out if a == 0 else _gather_planes(segments, 3 + a, pair_node)
        far -= o_a
        far *= inv_a
        if a:
            np.maximum(t_in, near, out=t_in)
            np.minimum(t_out, far, out=t_out)
    np.maximum(t_in, np.float32(0.0), out=t_in)
    np.minimum(t_out, box_rows[-1].take(first, 0, None, "clip"), out=t_out)
    return t_in, t_out


def _nearest_hits(best_t, r, t, u, v, tri):
    """Of several hits of one ray (rays ``r``, sorted), keep the nearest, the first of equals in traversal order."""
    nearest = best_t.copy()
    np.minimum.at(nearest, r, t)
    w = (t == nearest[r]).nonzero()[0]
    w = w[np.r_[True, r[w[1:]] != r[w[:-1]]]]
    return r[w], t[w], u[w], v[w], tri[w]


def _gather_planes(segments, k, node):
    """(P, WIDTH) plane ``k`` of the nodes of P pairs; ``segments`` are (rows per plane, start, stop).

    Pairs of one octant are contiguous and read that octant's rows; one
    segment is a plain gather.
    """
    if len(segments) == 1:
        return segments[0][0][k].take(node, 0, None, "clip")
    out = np.empty((len(node), WIDTH), np.float32)
    for rows, start, stop in segments:
        rows[k].take(node[start:stop], 0, out[start:stop], "clip")
    return out


def _half_area(lo, hi):
    """Half the surface area of (3, ...) boxes, in their dtype (0 for empty boxes)."""
    ext = np.maximum(hi - lo, 0)
    return ext[0] * ext[1] + ext[1] * ext[2] + ext[2] * ext[0]


def _split_level(lo, hi, cen, order, lvl_start, lvl_count, leaf_size, n_bins, *, out=None):
    """Split every node of one level in NumPy (the reference of :func:`tofcore.scene.bvh_build.split_level`).

    Node ``k`` holds triangles ``order[lvl_start[k]:lvl_start[k] + lvl_count[k]]``; ``order`` is
    partitioned in place (lefts first, each side in its previous order). Returns ``(node_lo, node_hi,
    n_left)``: (K, 3) float32 node boxes and (K,) int64 triangles sent left (0 for a leaf). Nodes are
    split in batches of `_BUILD_BATCH` to bound the memory. ``out``: two (K, 3) float32 arrays for the boxes.
    """
    k = lvl_count.size
    node_lo, node_hi = (np.empty((k, 3), np.float32), np.empty((k, 3), np.float32)) if out is None else out
    split = lvl_count > leaf_size
    n_left = np.zeros(k, np.int64)
    for b0 in range(0, k, _BUILD_BATCH):
        b1 = min(k, b0 + _BUILD_BATCH)
        st, ct = lvl_start[b0:b1], lvl_count[b0:b1]
        offs = np.cumsum(ct) - ct
        seg = np.repeat(np.arange(b1 - b0), ct)
        pos = np.arange(int(ct.sum())) + np.repeat(st - offs, ct)
        tri = order[pos]
        e_lo, e_hi = lo[:, tri], hi[:, tri]
        node_lo[b0:b1] = np.minimum.reduceat(e_lo, offs, axis=1).T
        node_hi[b0:b1] = np.maximum.reduceat(e_hi, offs, axis=1).T
        sp = split[b0:b1]
        if not sp.any():
            continue
        inner = sp[seg]
        seg_i = np.cumsum(sp)[seg[inner]] - 1  # index among the splitting nodes
        n_i = int(sp.sum())
        go_left, ok = _sah_split(e_lo[:, inner], e_hi[:, inner], cen[:, tri[inner]], seg_i, n_i, n_bins)
        local = np.arange(len(seg_i)) - (np.cumsum(ct[sp]) - ct[sp])[seg_i]
        go_left = np.where(ok[seg_i], go_left, local < (ct[sp] // 2)[seg_i])
        # stable partition within each node: lefts first, in their current order
        c_left = np.cumsum(go_left)
        before = (c_left - go_left)[np.cumsum(ct[sp]) - ct[sp]]  # lefts before each node
        rank_left = c_left - 1 - before[seg_i]
        nl = np.bincount(seg_i, weights=go_left, minlength=n_i).astype(np.int64)
        new_local = np.where(go_left, rank_left, nl[seg_i] + local - (rank_left + 1))
        order[st[sp][seg_i] + new_local] = tri[inner]
        n_left[b0:b1][sp] = nl
    return node_lo, node_hi, n_left


def _build_binary(lo, hi, leaf_size, n_bins, *, compiled=None):
    """Top-down binned-SAH binary tree over triangle boxes, one tree level at a time.

    ``lo, hi`` are (3, M) float32 triangle boxes.  All nodes of a level are
    split together (:func:`_split_level`, or its compiled twin
    :func:`tofcore.scene.bvh_build.split_level` — the same tree — where numba
    runs and :func:`_compiled_build_pays`; ``compiled`` True/False overrides
    that rule); a node with at most
    ``leaf_size`` triangles is a leaf; a node whose centroids cannot be
    separated by the bins is cut at its middle.  Triangles of a node stay
    contiguous in ``order`` (stable partition in place).

    Returns ``(order, node_lo, node_hi, left, right, start, count)``: node ids
    are breadth-first, ``left = right = -1`` on leaves, and a leaf's triangles
    are ``order[start:start + count]``.
    """
    m = lo.shape[1]
    cen = (lo + hi) * np.float32(0.5)
    if _compiled_build_pays(m) if compiled is None else compiled:
        from . import bvh_build  # imports numba: only for meshes that need it
        if bvh_build.available():
            try:
                records = np.ascontiguousarray(np.concatenate([lo, hi, cen]).T)  # (M, 9), in the order of `order`
                split = functools.partial(bvh_build.split_level, records,
                                          scratch=(np.empty_like(records), np.empty(m, np.int64)))
                return _levels(m, split, leaf_size, n_bins)
            except Exception as exc:  # noqa: BLE001 — numba's compile and cache errors have no common base
                # numba could not compile or load the level split (e.g. a damaged cache file: an
                # UnpicklingError or EOFError): the NumPy levels build the same tree
                warnings.warn(f"the compiled BVH build failed ({type(exc).__name__}: {exc}); building in NumPy",
                              RuntimeWarning, stacklevel=2)
    return _levels(m, functools.partial(_split_level, lo, hi, cen), leaf_size, n_bins)


def _build_compiled(v, tri, leaf_size):
    """`BVH.build`'s tree in compiled loops (:mod:`tofcore.scene.bvh_build`): the triangle records, the levels
    and the node and leaf records — the arrays of the NumPy build (:func:`_build_binary`, :func:`_tree_records`)
    bit for bit. Returns ``(nodes, leaves, depth, left, count)``, or None where numba does not run here or
    failed (with a warning: the NumPy build then makes the same tree)."""
    from . import bvh_build  # imports numba: only for meshes that need it

    if not bvh_build.available():
        return None
    try:
        records = bvh_build.triangle_records(v, tri)
        split = functools.partial(bvh_build.split_level, records,
                                  scratch=(np.empty_like(records), np.empty(len(tri), np.int64)))
        order, b_lo, b_hi, left, right, start, count = _levels(len(tri), split, leaf_size, N_BINS)
        del records, split
        nodes, leaves, depth = bvh_build.tree_records(
            v, tri, order, b_lo, b_hi, left, right, start, count, leaf_size, box_pad=BOX_PAD, width=WIDTH,
            node_rows=_NODE_ROWS, child_row=_CHILD_ROW, leaf_rows=_LEAF_ROWS, prim_row=_PRIM_ROW)
    except Exception as exc:  # noqa: BLE001 — numba's compile and cache errors have no common base
        warnings.warn(f"the compiled BVH build failed ({type(exc).__name__}: {exc}); building in NumPy",
                      RuntimeWarning, stacklevel=3)
        return None
    return nodes, leaves, int(depth), left, count


def _tree_records(corner_rows, order, b_lo, b_hi, left, right, start, count, leaf_size):
    """The 4-wide tree's records from the binary tree of :func:`_build_binary` (the NumPy reference of
    :func:`tofcore.scene.bvh_build.tree_records`): boxes padded by `BOX_PAD`, collapsed (:func:`_collapse`),
    node records and leaf records (:func:`_leaf_records`) as `BVH.build` describes them. Returns ``(nodes,
    leaves, depth)``: (W · `_NODE_ROWS`, `WIDTH`) and (L · `_LEAF_ROWS`, leaf_size) int32, wide levels."""
    magnitude, extent = np.maximum(np.abs(b_lo), np.abs(b_hi)), b_hi - b_lo
    pad = BOX_PAD * (np.maximum(np.maximum(magnitude[:, 0], magnitude[:, 1]), magnitude[:, 2])
                     + np.maximum(np.maximum(extent[:, 0], extent[:, 1]), extent[:, 2]))
    b_lo = b_lo - pad[:, None]
    b_hi = b_hi + pad[:, None]
    slots, depth = _collapse(left, right, _half_area(b_lo.T, b_hi.T))

    is_leaf = left < 0
    leaf_id = np.cumsum(is_leaf) - 1  # binary node -> leaf
    w = len(slots)
    wide_id = np.full(len(left), -1, np.int64)
    inner_slots = (slots >= 0) & ~is_leaf[np.maximum(slots, 0)]
    wide_id[slots[inner_slots]] = np.arange(1, w)  # breadth-first, root is wide node 0
    safe = np.maximum(slots, 0)
    used = (slots >= 0)[..., None]
    c_lo = np.where(used, b_lo[safe], np.float32(np.inf))  # (W, WIDTH, 3)
    c_hi = np.where(used, b_hi[safe], np.float32(-np.inf))
    nodes = np.empty((w, _NODE_ROWS, WIDTH), np.int32)
    nodes[:, 0:3].view(np.float32)[...] = c_lo.transpose(0, 2, 1)
    nodes[:, 3:6].view(np.float32)[...] = c_hi.transpose(0, 2, 1)
    to_node = np.maximum(wide_id[safe], 0) * _NODE_ROWS
    nodes[:, _CHILD_ROW] = np.where(is_leaf[safe] & used[..., 0], ~(leaf_id[safe] * _LEAF_ROWS), to_node)
    leaves = np.flatnonzero(is_leaf)
    leaf_rec = _leaf_records(corner_rows, order, start[leaves], count[leaves], leaf_size)
    return nodes.reshape(-1, WIDTH), leaf_rec.reshape(-1, leaf_size), depth


def _levels(m, split_level, leaf_size, n_bins):
    """The level loop of :func:`_build_binary`; ``split_level(order, starts, counts, leaf_size, n_bins,
    out=(node_lo, node_hi))`` splits the nodes of one level, their boxes into ``out``.

    The tree's arrays are allocated once for the most nodes a tree of ``m`` triangles has (2m − 1) and each
    level writes its rows: pages never written are never mapped, and there is no copy of every level's
    arrays into one at the end (at 3M triangles that copy took 0.2–0.4 s, mostly first touches of memory).
    """
    order = np.arange(m)
    lvl_start = np.zeros(1, np.int64)  # first position in `order` of each node of the level
    lvl_count = np.full(1, m, np.int64)  # triangle count of each node of the level
    most = 2 * m - 1
    out_lo, out_hi = np.empty((most, 3), np.float32), np.empty((most, 3), np.float32)
    out_left, out_right, out_start, out_count = (np.empty(most, np.int64) for _ in range(4))
    n_done = 0  # nodes of the levels above
    while lvl_count.size:
        k = lvl_count.size
        rows = slice(n_done, n_done + k)
        split = lvl_count > leaf_size
        n_left = split_level(order, lvl_start, lvl_count, leaf_size, n_bins, out=(out_lo[rows], out_hi[rows]))[2]
        ids = n_done + k + 2 * (np.cumsum(split) - 1)
        np.copyto(out_left[rows], np.where(split, ids, -1))
        np.copyto(out_right[rows], np.where(split, ids + 1, -1))
        out_start[rows], out_count[rows] = lvl_start, lvl_count
        n_done += k
        s, c, nl = lvl_start[split], lvl_count[split], n_left[split]
        lvl_start = np.stack([s, s + nl], axis=1).ravel()
        lvl_count = np.stack([nl, c - nl], axis=1).ravel()
    n = slice(0, n_done)
    return order, out_lo[n], out_hi[n], out_left[n], out_right[n], out_start[n], out_count[n]


def _collapse(left, right, area):
    """Collapse a binary tree into a `WIDTH`-wide one, one wide level at a time.

    Each wide node starts from a binary internal node's two children and
    repeatedly replaces its largest-area internal child by that child's two
    children until it has `WIDTH` children.  Returns ``(slots, depth)``:
    (W, WIDTH) binary ids of the children of each wide node (``-1`` empty),
    wide nodes breadth-first, and the number of wide levels.
    """
    internal = left >= 0
    if not internal[0]:
        slots = np.full((1, WIDTH), -1, np.int64)
        slots[0, 0] = 0
        return slots, 1
    levels = []
    frontier = np.zeros(1, np.int64)  # binary ids of the wide nodes of the level
    while frontier.size:
        f = frontier.size
        slots = np.full((f, WIDTH), -1, np.int64)
        slots[:, 0], slots[:, 1] = left[frontier], right[frontier]
        for j in range(2, WIDTH):
            is_inner = (slots >= 0) & internal[np.maximum(slots, 0)]
            a = np.where(is_inner, area[np.maximum(slots, 0)], -1.0)
            pick = np.argmax(a, axis=1)
            rows = np.flatnonzero(is_inner[np.arange(f), pick])
            c = slots[rows, pick[rows]]
            slots[rows, pick[rows]] = left[c]
            slots[rows, j] = right[c]
        levels.append(slots)
        frontier = slots[(slots >= 0) & internal[np.maximum(slots, 0)]]
    return np.concatenate(levels), len(levels)


def _leaf_records(corner_rows, order, start, count, leaf_size: int) -> np.ndarray:
    """(L, _LEAF_ROWS, leaf_size) int32 leaf records: v0, v1, v2 per axis (float32 bits, NaN padding), then
    the triangle index (−1 padding); leaf i holds triangles order[start[i]:start[i] + count[i]].
    ``corner_rows`` is (9, M) float32: v0 x, y, z, v1 x, y, z, v2 x, y, z of each triangle."""
    k = np.arange(leaf_size)
    valid = k[None, :] < count[:, None]
    prim = np.where(valid, order[np.minimum(start[:, None] + k, corner_rows.shape[1] - 1)], -1)
    leaf_rec = np.empty((len(start), _LEAF_ROWS, leaf_size), np.int32)
    rows = leaf_rec[:, :_PRIM_ROW].view(np.float32)
    safe = np.maximum(prim, 0)
    for r in range(_PRIM_ROW):  # row by row: one (L, leaf_size) gather each
        rows[:, r] = np.where(valid, corner_rows[r][safe], np.float32(np.nan))
    leaf_rec[:, _PRIM_ROW] = prim
    return leaf_rec


CACHED_TREES = 2
"""Trees :meth:`BVH.cached` keeps, the most recently used first (a render and a preview of another scene)."""

_trees: OrderedDict[bytes, "BVH"] = OrderedDict()
_trees_lock = threading.Lock()


def geometry_key(vertices: np.ndarray, triangles: np.ndarray, leaf_size: int) -> bytes:
    """A digest of the triangles as `BVH.build` reads them (float32 vertices, int64 indices, leaf size):
    equal for equal geometry, whatever object or array holds it (BLAKE2b, ≈ 20 ms per 1M triangles)."""
    digest = hashlib.blake2b(digest_size=20)
    v = np.ascontiguousarray(vertices, np.float32)
    t = np.ascontiguousarray(triangles, np.int64)
    digest.update(repr((v.shape, t.shape, int(leaf_size))).encode())
    digest.update(v.data)
    digest.update(t.data)
    return digest.digest()


class BVH:
    """4-wide binned-SAH bounding volume hierarchy over a triangle mesh.

    Build with `BVH.build` (or `BVH.cached`, which reuses the tree of the same triangles); query with `intersect` (closest hit) and
    `occluded` (any hit).  Instances are read-only, so one BVH may be queried
    from several threads.
    """

    def __init__(self, *, nodes, leaves, stats):
        self._nodes = nodes  # (W * _NODE_ROWS, WIDTH) int32 node records, see `build`
        self._leaves = leaves  # (L * _LEAF_ROWS, leaf_size) int32 leaf records, see `build`
        self._stats = stats

    @classmethod
    def build(cls, vertices: np.ndarray, triangles: np.ndarray, *, leaf_size: int = 2) -> "BVH":
        """Build the tree.

        Parameters
        ----------
        vertices : (N, 3) float32 world positions in metres.
        triangles : (M, 3) int32 vertex indices, validated and non-degenerate.
        leaf_size : most triangles per leaf (>= 1).  Every leaf test costs
            ``leaf_size`` triangle tests (padded rows), so 2 measured 8-18 %
            faster than 4 on the benchmark rooms, for 30-50 % more nodes.

        Notes
        -----
        Binned SAH with `N_BINS` bins per axis over centroid bounds, all nodes
        of a level at once (`_build_binary`), boxes padded by `BOX_PAD`, then
        collapsed to `WIDTH` children per node (`_collapse`; `_tree_records`).
        Meshes of at least `COMPILED_BUILD_MIN` triangles are built in
        compiled loops where numba runs and their compile is cached or pays
        (`_compiled_build_pays`, `_build_compiled`): the same records bit
        for bit.

        Storage: one record of `_NODE_ROWS` rows of `WIDTH` children per node:
        the box minimum x, y, z and maximum x, y, z (float32), and the
        children (int32): the first row of the child's record, or ``~`` the
        first row of a leaf record.  Empty slots have inverted infinite boxes
        that no ray enters.  A leaf record has `_LEAF_ROWS` rows of
        ``leaf_size`` triangles: v0, v1, v2 per axis (float32, NaN padding)
        and the triangle index (int32, -1 padding).  A (ray, node) pair reads
        two adjacent cache lines.
        """
        if leaf_size < 1:
            raise ConfigError(f"BVH.build: leaf_size must be >= 1, got {leaf_size!r}")
        t0 = time.perf_counter()
        v = np.asarray(vertices, np.float32)
        tri = np.asarray(triangles, np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or tri.ndim != 2 or tri.shape[1] != 3 or len(tri) == 0:
            raise SceneError(f"BVH.build: vertices and triangles must be (N, 3) and (M >= 1, 3), "
                             f"got {v.shape} and {tri.shape}")
        built = _build_compiled(v, tri, leaf_size) if _compiled_build_pays(len(tri)) else None
        if built is None:
            axes = np.ascontiguousarray(v.T)  # (3, N)
            corner_rows = np.concatenate([axes[:, tri[:, j]] for j in range(3)])  # (9, M): v0 xyz, v1 xyz, v2 xyz
            v0, v1, v2 = corner_rows[0:3], corner_rows[3:6], corner_rows[6:9]
            lo = np.minimum(np.minimum(v0, v1), v2)  # elementwise: far faster than a reduction over the corners
            hi = np.maximum(np.maximum(v0, v1), v2)
            order, b_lo, b_hi, left, right, start, count = _build_binary(lo, hi, leaf_size, N_BINS,
                                                                         compiled=False)
            nodes, leaf_rec, depth = _tree_records(corner_rows, order, b_lo, b_hi, left, right, start, count,
                                                   leaf_size)
        else:
            nodes, leaf_rec, depth, left, count = built
        leaves = np.flatnonzero(left < 0)
        sizes = count[leaves]
        stats = {
            "triangles": len(tri),
            "nodes": len(nodes) // _NODE_ROWS,
            "binary_nodes": len(left),
            "leaves": len(leaves),
            "depth": depth,
            "leaf_size_max": int(sizes.max()),
            "leaf_size_mean": float(sizes.mean()),
            "leaf_size_hist": np.bincount(sizes, minlength=leaf_size + 1)[1:].tolist(),
            "memory_bytes": nodes.nbytes + leaf_rec.nbytes,
            "build_time_s": time.perf_counter() - t0,
        }
        return cls(nodes=nodes, leaves=leaf_rec, stats=stats)

    @classmethod
    def cached(cls, vertices: np.ndarray, triangles: np.ndarray, *, leaf_size: int = 2) -> "BVH":
        """`build`, or the tree already built for the same triangles (:func:`geometry_key`).

        A camera, sensor or setting change leaves the geometry as it was, so renders and live-preview
        updates of one scene share one tree even when the scene is exported or loaded again (the add-on
        exports it for every preview update). The last `CACHED_TREES` trees are kept.
        """
        key = geometry_key(vertices, triangles, leaf_size)
        with _trees_lock:
            tree = _trees.get(key)
            if tree is not None:
                _trees.move_to_end(key, last=False)
                return tree
        tree = cls.build(vertices, triangles, leaf_size=leaf_size)
        with _trees_lock:
            _trees[key] = tree
            _trees.move_to_end(key, last=False)
            while len(_trees) > CACHED_TREES:
                _trees.popitem()
        return tree

    @property
    def stats(self) -> dict:
        """Node count (4-wide and binary), leaves, depth, leaf sizes, memory of the tree, build time in s."""
        return dict(self._stats)

    @device_twin(on="origins")
    def intersect(self, origins, directions, t_max=None, ignore_prim=None, *,
                  workers: int = 2, counters: dict | None = None) -> Hits:
        """Closest hit with ``0 < t < t_max`` of each ray.

        Parameters
        ----------
        origins, directions : (R, 3) float32, world frame; directions unit length.
        t_max : (R,) float32 in metres, or None for no limit.
        ignore_prim : (R,) int32 triangle never reported per ray (-1 none), or None.
        workers : threads over ray chunks; the result does not depend on it.
        counters : if given, ``box_tests``, ``tri_tests`` and ``rays`` are added to it.

        CuPy rays are traced on the GPU (:mod:`tofcore.gpu.traversal`, same answers; ``workers``
        and ``counters`` do not apply there) and give CuPy hits.
        """
        return self._run(origins, directions, t_max, ignore_prim, False, workers, counters)

    @device_twin(on="origins")
    def occluded(self, origins, directions, t_max, ignore_prim=None, *,
                 workers: int = 2, counters: dict | None = None) -> np.ndarray:
        """(R,) bool: whether any triangle is hit with ``0 < t < t_max``.

        Same parameters as `intersect`; a ray stops traversing at its first hit.
        """
        return self._run(origins, directions, t_max, ignore_prim, True, workers, counters)

    def _run(self, origins, directions, t_max, ignore_prim, any_hit, workers, counters):
        """Sort rays by octant, cut them into chunks of `RAY_CHUNK`, trace on threads, join."""
        o, d, tm, ig = _as_rays(origins, directions, t_max, ignore_prim)
        neg = d < 0
        octant = (neg[:, 0] + 2 * neg[:, 1] + 4 * neg[:, 2]).astype(np.uint8)
        order = np.argsort(octant, kind="stable")
        chunks = [order[s:s + RAY_CHUNK] for s in range(0, len(o), RAY_CHUNK)]  # ray indices
        use_ignore = bool((ig >= 0).any())
        pick = lambda x, idx: x.take(idx, 0, None, "clip")  # noqa: E731
        job = lambda c: self._trace(pick(octant, c), pick(o, c), pick(d, c), pick(tm, c),  # noqa: E731
                                    pick(ig, c) if use_ignore else None, any_hit)
        if workers > 1 and len(chunks) > 1:
            with ThreadPoolExecutor(max_workers=workers) as pool:
                parts = list(pool.map(job, chunks))
        else:
            parts = [job(c) for c in chunks]
        if counters is not None:
            counters["rays"] = counters.get("rays", 0) + len(o)
            counters["box_tests"] = counters.get("box_tests", 0) + sum(p[-1][0] for p in parts)
            counters["tri_tests"] = counters.get("tri_tests", 0) + sum(p[-1][1] for p in parts)
        n = len(o)
        out = ([np.zeros(n, bool)] if any_hit else
               [np.full(n, np.inf, np.float32), np.full(n, -1, np.int32), np.zeros(n, np.float32),
                np.zeros(n, np.float32)])
        for idx, part in zip(chunks, parts):
            for k, x in enumerate(out):
                x.put(idx, part[k], "clip")
        return out[0] if any_hit else Hits(*out)

    def _trace(self, octant, o, d, t_max, ignore, any_hit):
        """Traverse one chunk of rays, sorted by ``octant``, breadth first over (ray, node) pairs.

        Returns ``(t, prim, u, v, counts)`` or, for ``any_hit``,
        ``(occluded, counts)``; ``counts = (box tests, triangle tests)``.
        Row ``k`` of the records starting at rows ``first`` is
        ``take(records[k:], first)``; array methods are used instead of the
        ``np.`` functions, whose dispatch costs about a microsecond a call.
        """
        n, width_leaf = len(o), self._leaves.shape[1]
        ray_box, ray_leaf = _ray_records(o, d, t_max, width_leaf)
        best_box = ray_box[_RAY_BOX_ROWS - 1::_RAY_BOX_ROWS]  # (n, WIDTH) views of the best t rows
        best_leaf = ray_leaf[_RAY_LEAF_ROWS - 1::_RAY_LEAF_ROWS]
        box_rows = [ray_box[k:] for k in range(_RAY_BOX_ROWS)]
        leaf_rows = [ray_leaf[k:] for k in range(_RAY_LEAF_ROWS)]
        oct_start = np.searchsorted(octant, np.arange(9))  # rays of octant k: oct_start[k]:oct_start[k + 1]
        plane_rows = self._plane_rows(oct_start)
        child_rows = self._nodes[_CHILD_ROW:]
        tri_rows = [self._leaves.view(np.float32)[k:] for k in range(_PRIM_ROW)] + [self._leaves[_PRIM_ROW:]]
        ignore_rows = None if ignore is None else _repeat_rows(ignore[:, None].astype(np.int32), width_leaf)
        prim = np.full(n, -1, np.int32)  # best triangle so far
        bary_u = np.zeros(n, np.float32)  # barycentrics of the best hit
        bary_v = np.zeros(n, np.float32)
        occluded = np.zeros(n, bool)  # any hit found (any_hit mode)
        pair_ray = np.arange(n)  # ray of each (ray, node) pair of the level
        pair_node = np.zeros(n, np.intp)  # first record row of the node (the root)
        n_box = n_tri = 0  # box and triangle tests
        with np.errstate(divide="ignore", invalid="ignore"):  # NaN padding, rays parallel to triangles
            while pair_ray.size:
                n_box += WIDTH * pair_ray.size
                first = pair_ray * _RAY_BOX_ROWS
                cut = pair_ray.searchsorted(oct_start)  # pairs of octant k: cut[k]:cut[k + 1]
                segments = [(plane_rows[k], cut[k], cut[k + 1]) for k in plane_rows if cut[k + 1] > cut[k]]
                t_in, t_out = _slab_test(box_rows, segments, pair_node, first)
                flat = (t_in <= t_out).ravel().nonzero()[0]  # (pair, child) of every box entered
                child = child_rows.take(pair_node, 0, None, "clip").take(flat, None, None, "clip")
                ray = pair_ray.take(flat >> _WIDTH_BITS, None, None, "clip")
                is_leaf = child < 0
                inner = (~is_leaf).nonzero()[0]
                pair_ray = ray.take(inner, None, None, "clip")
                pair_node = child.take(inner, None, None, "clip").astype(np.intp)
                lf = is_leaf.nonzero()[0]
                if not lf.size:
                    continue
                leaf_ray = ray.take(lf, None, None, "clip")
                leaf = ~child.take(lf, None, None, "clip").astype(np.intp)
                n_tri += width_leaf * leaf.size
                first = leaf_ray * _RAY_LEAF_ROWS
                rc = [rows.take(first, 0, None, "clip") for rows in leaf_rows]
                tc = [rows.take(leaf, 0, None, "clip") for rows in tri_rows]
                hit, t, u, v = _watertight(rc[0:3], rc[3:6], rc[6:9], rc[9:12], tc[0:3], tc[3:6], tc[6:9], rc[-1])
                if ignore_rows is not None:
                    hit &= tc[_PRIM_ROW] != ignore_rows.take(leaf_ray, 0, None, "clip")
                f = hit.ravel().nonzero()[0]
                if not f.size:
                    continue
                r = leaf_ray.take(f // width_leaf, None, None, "clip")
                if any_hit:
                    occluded[r] = True
                    best_box[r] = -np.inf
                    best_leaf[r] = -np.inf
                    keep = (~occluded[pair_ray]).nonzero()[0]
                    pair_ray, pair_node = pair_ray.take(keep), pair_node.take(keep)
                    continue
                t, u, v, tri = (x.take(f, None, None, "clip") for x in (t, u, v, tc[_PRIM_ROW]))
                if r.size > 1 and (r[1:] == r[:-1]).any():  # several hits of one ray: keep the nearest
                    r, t, u, v, tri = _nearest_hits(best_box[:, 0], r, t, u, v, tri)
                best_box[r] = t[:, None]
                best_leaf[r] = t[:, None]
                prim[r], bary_u[r], bary_v[r] = tri, u, v
        counts = (n_box, n_tri)
        if any_hit:
            return occluded, counts
        t_hit = np.where(prim >= 0, best_box[:, 0], np.float32(np.inf)).astype(np.float32)
        return t_hit, prim, bary_u, bary_v, counts

    def _plane_rows(self, oct_start: np.ndarray) -> dict:
        """Octant k → the node-record rows of its entry planes x, y, z and exit planes x, y, z."""
        planes = self._nodes.view(np.float32)
        plane_rows = {}
        for k in np.flatnonzero(np.diff(oct_start)):
            flip = [(k >> a) & 1 for a in range(3)]  # negative direction: enter at the box maximum
            plane_rows[k] = [planes[a + 3 * flip[a]:] for a in range(3)] + [planes[a + 3 - 3 * flip[a]:]
                                                                             for a in range(3)]
        return plane_rows
