"""The binned-SAH split of :func:`tofcore.scene.bvh._build_binary`, one tree level at a time, compiled (numba).

`tofcore.scene.bvh` builds its binary tree level by level in NumPy (the readable reference,
``_sah_split``); this module computes the same levels in compiled loops, nodes of a level in parallel on
numba's threads, and gives the same tree bit for bit (tests/tofcore/test_bvh.py compares every array).
For each node with more than ``leaf_size`` triangles, on each axis in turn (x, y, z):

* its triangles' centroids ``c`` are cut into ``n_bins`` equal bins over the centroid bounds
  ``[c_min, c_max]``: ``bin = ⌊(c − c_min) · s⌋`` clipped to ``[0, n_bins − 1]``, with the float32 scale
  ``s = n_bins (1 − 10⁻⁶) / (c_max − c_min)`` (0 for a flat extent);
* a cut after bin ``i`` costs ``A(bins 0..i) · N(0..i) + A(bins i+1..) · N(i+1..)`` in float64, with
  ``A`` the half surface area ``ex·ey + ey·ez + ez·ex`` of the union of the bins' triangle boxes in
  float32 (0 for none), and ``+∞`` where a side is empty;
* the cheapest cut of the first axis that has the lowest cost wins (strictly lower replaces).

Triangles with ``bin ≤ cut`` go left; a node with no finite cut is split at its middle (the first
``⌊n/2⌋`` left). The partition is stable: lefts, then rights, each in their previous order. All float32
arithmetic is the reference's own (no fused multiply-adds: numba compiles without fast-math), so the
cuts are the same.

The cost is linear in the triangles of a level (three binning sweeps, one partition), so the build is
``O(M log M)`` in compiled loops instead of NumPy's scatter-adds (``ufunc.at``), sorts and gathers per
level: ``bench/bench_bvh.py --build-only`` measures both.

The passes before and after the levels are compiled too (:func:`triangle_records`: the corner gathers,
boxes and centroids; :func:`tree_records`: the padding, the collapse to 4-wide nodes, the node and leaf
records), the same arrays as ``BVH.build``'s NumPy passes, without their temporaries.
"""

from __future__ import annotations

import os

import numpy as np

try:
    import numba
except Exception:  # ImportError, or a numba that does not work with this NumPy
    numba = None

SMALL_NODE = 32
"""Nodes of at most this many triangles evaluate only the cuts between their occupied bins (:func:`_small_cut`):
the same cut, without sweeping every bin."""

PARALLEL_LEVEL = 65536
"""Meshes of fewer triangles split their levels on one thread: waking numba's threads for every level costs
more there than it saves (and on a busy machine a thread may wait a scheduler slice for its core)."""

_NODES_PER_TASK = 64  # nodes of a level one thread takes at a time (its bin arrays are allocated once)

_OPTIONS = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)
if numba is not None:
    _compiled, _compiled_parallel, prange = numba.njit(**_OPTIONS), numba.njit(parallel=True, **_OPTIONS), numba.prange
else:
    _compiled = _compiled_parallel = (lambda function: function)
    prange = range


def available() -> bool:
    """Whether numba runs here and is allowed to (``TOFCORE_TRACER=numpy`` keeps everything in NumPy)."""
    return numba is not None and os.environ.get("TOFCORE_TRACER", "").strip().lower() != "numpy"


def split_level(records, order, starts, counts, leaf_size: int, n_bins: int, *, parallel: bool | None = None,
                scratch=None, out=None):
    """Split every node of one level (compiled): ``records`` and ``order`` are partitioned in place; returns
    ``(node_lo, node_hi, n_left)``: (K, 3) float32 node boxes and (K,) int64 triangles sent left (0 for a
    leaf).

    ``records`` is (M, 9) float32, per position of ``order``: the triangle's box minimum, maximum and
    centroid (xyz each), so every pass reads its triangles in sequence; node ``k`` holds positions
    ``starts[k]:starts[k] + counts[k]``. ``parallel``: on numba's threads (default: for meshes of at least
    `PARALLEL_LEVEL` triangles) or on this one. ``scratch``: arrays like ``records`` and ``order`` that the
    partition may overwrite (default: new ones; a caller splitting every level passes the same two, so
    their pages are mapped once, not once a level). ``out``: two C-contiguous (K, 3) float32 arrays for the
    node boxes (default: new ones).
    """
    k = len(starts)
    node_lo, node_hi = (np.empty((k, 3), np.float32), np.empty((k, 3), np.float32)) if out is None else out
    n_left = np.zeros(k, np.int64)
    scale_numerator = np.float32(n_bins * (1 - 1e-6))
    if parallel is None:
        parallel = len(order) >= PARALLEL_LEVEL
    split = _split_level_parallel if parallel else _split_level_serial
    records_scratch, order_scratch = (np.empty_like(records), np.empty_like(order)) if scratch is None else scratch
    split(records, order, records_scratch, order_scratch, starts, counts, leaf_size, n_bins, scale_numerator,
          node_lo, node_hi, n_left)
    return node_lo, node_hi, n_left


def warm_up(leaf_size: int = 4, n_bins: int = 32) -> None:
    """Compile (or load from numba's cache) every compiled loop of a mesh's build (`DRIVERS`), the parallel and
    the serial build of each, on a mesh of 8 triangles: the argument types of a mesh's build, so that a mesh of
    at least ``bvh.COMPILED_BUILD_MIN`` triangles loads them (``tofcore warmup``: about 9 s of compile on 2
    cores, once)."""
    m = 8
    centroids = np.arange(m, dtype=np.float32)[:, None] * np.ones(3, np.float32)
    vertices = np.ascontiguousarray(np.concatenate([centroids - 0.5, centroids + 0.5, centroids + [0.5, -0.5, 0]]))
    triangles = np.arange(3 * m, dtype=np.int64).reshape(3, m).T.copy()
    for parallel in (True, False):
        records = triangle_records(vertices, triangles, parallel=parallel)
        split_level(records, np.arange(m), np.zeros(1, np.int64), np.full(1, m, np.int64), leaf_size, n_bins,
                    parallel=parallel)
        # a root over two leaves of four triangles
        lo, hi = records[:3, :3].copy(), records[:3, 3:6].copy()
        left, right = np.array([1, -1, -1], np.int64), np.array([2, -1, -1], np.int64)
        tree_records(vertices, triangles, np.arange(m), lo, hi, left, right, np.array([0, 0, 4], np.int64),
                     np.array([m, 4, 4], np.int64), 4, box_pad=2.0**-16, parallel=parallel, **LAYOUT)


def _split_level(records, order, records_scratch, order_scratch, starts, counts, leaf_size, n_bins,
                 scale_numerator, node_lo, node_hi, n_left):
    """The nodes of a level in tasks of up to `_NODES_PER_TASK` on numba's threads (see :func:`split_level`)."""
    n_nodes = len(starts)
    per_task = min(_NODES_PER_TASK, max(1, n_nodes // 64))
    n_tasks = (n_nodes + per_task - 1) // per_task
    for task in prange(n_tasks):
        count = np.empty((3, n_bins), np.int64)
        bins = np.empty((3, 6, n_bins), np.float32)  # per axis: the bins' box minimum and maximum (xyz each)
        area_right = np.empty(n_bins, np.float32)
        c_min = np.empty(3, np.float32)
        scale = np.empty(3, np.float32)
        keys = np.empty(SMALL_NODE, np.int64)
        for node in range(task * per_task, min(n_nodes, (task + 1) * per_task)):
            n_left[node] = _node_split(records, order, records_scratch, order_scratch, starts[node], counts[node],
                                       leaf_size, n_bins, scale_numerator, node_lo, node_hi, node, count, bins,
                                       area_right, c_min, scale, keys)


def _named(function, name):
    """A copy of ``function`` under another name. numba's cache keys a function by its module, name and
    line, not by its compile options: the parallel and the serial build of one function would share one
    cache entry, and the second to load would get the first's code (the serial split ran on the parallel
    path, or the reverse)."""
    import types

    copy = types.FunctionType(function.__code__, function.__globals__, name, function.__defaults__,
                              function.__closure__)
    copy.__qualname__, copy.__doc__ = name, function.__doc__
    return copy


_split_level_parallel = _compiled_parallel(_named(_split_level, "_split_level_parallel"))
_split_level_serial = _compiled(_named(_split_level, "_split_level_serial"))  # prange is range here


@_compiled
def _half_area(lo0, lo1, lo2, hi0, hi1, hi2):
    """Half the surface area of a box in float32, 0 for an empty (inverted) box."""
    zero = np.float32(0.0)
    e0, e1, e2 = max(hi0 - lo0, zero), max(hi1 - lo1, zero), max(hi2 - lo2, zero)
    return e0 * e1 + e1 * e2 + e2 * e0


@_compiled
def _bin_of(records, j, a, c_min, scale, n_bins):
    """The bin of the triangle at position ``j`` along axis ``a``: ⌊(c − c_min)·s⌋ clipped, in float32."""
    return min(max(np.int64((records[j, 6 + a] - c_min[a]) * scale[a]), 0), n_bins - 1)


@_compiled
def _node_split(records, order, records_scratch, order_scratch, start, n, leaf_size, n_bins, scale_numerator,
                node_lo, node_hi, node, count, bins, area_right, c_min, scale, keys):
    """One node: its box into row ``node`` of ``node_lo, node_hi``; for an inner node, the binned-SAH cut and
    the stable partition of positions ``start:start + n``. Returns the number of triangles sent left (0 for a
    leaf). The other arrays are the task's scratch."""
    inf = np.float32(np.inf)
    for a in range(3):
        b_lo, b_hi, cmin, cmax = inf, -inf, inf, -inf
        for j in range(start, start + n):
            b_lo, b_hi = min(b_lo, records[j, a]), max(b_hi, records[j, 3 + a])
            cmin, cmax = min(cmin, records[j, 6 + a]), max(cmax, records[j, 6 + a])
        node_lo[node, a], node_hi[node, a], c_min[a] = b_lo, b_hi, cmin
        extent = cmax - cmin
        scale[a] = scale_numerator / extent if extent > np.float32(0.0) else np.float32(0.0)
    if n <= leaf_size:
        return 0
    if n <= SMALL_NODE:
        best_cost, best_axis, best_cut = _small_cut(records, start, n, n_bins, c_min, scale, keys, area_right)
    else:
        best_cost, best_axis, best_cut = _binned_cut(records, start, n, n_bins, c_min, scale, count, bins,
                                                     area_right)
    return _partition(records, order, records_scratch, order_scratch, start, n, n_bins, c_min, scale, best_cost,
                      best_axis, best_cut)


@_compiled
def _binned_cut(records, start, n, n_bins, c_min, scale, count, bins, area_right):
    """The cheapest cut (cost, axis, bin) of the node at positions ``start:start + n``, over all bins: the
    bins' counts and boxes, then a sweep from each side. Cost +∞ where no cut leaves both sides occupied."""
    inf = np.float32(np.inf)
    count[:, :] = 0
    bins[:, :3, :] = inf
    bins[:, 3:, :] = -inf
    for j in range(start, start + n):
        for a in range(3):
            b = _bin_of(records, j, a, c_min, scale, n_bins)
            count[a, b] += 1
            for k in range(3):
                bins[a, k, b] = min(bins[a, k, b], records[j, k])
                bins[a, 3 + k, b] = max(bins[a, 3 + k, b], records[j, 3 + k])
    best_cost, best_axis, best_cut = np.inf, 0, 0
    for a in range(3):
        box = bins[a]
        r0, r1, r2, s0, s1, s2 = inf, inf, inf, -inf, -inf, -inf  # bins i.. (right sweep)
        for i in range(n_bins - 1, -1, -1):
            r0, r1, r2 = min(r0, box[0, i]), min(r1, box[1, i]), min(r2, box[2, i])
            s0, s1, s2 = max(s0, box[3, i]), max(s1, box[4, i]), max(s2, box[5, i])
            area_right[i] = _half_area(r0, r1, r2, s0, s1, s2)
        l0, l1, l2, m0, m1, m2 = inf, inf, inf, -inf, -inf, -inf  # bins ..i (the cuts, from the left)
        n_l = 0
        for i in range(n_bins - 1):
            l0, l1, l2 = min(l0, box[0, i]), min(l1, box[1, i]), min(l2, box[2, i])
            m0, m1, m2 = max(m0, box[3, i]), max(m1, box[4, i]), max(m2, box[5, i])
            n_l += count[a, i]
            n_r = n - n_l
            if n_l == 0 or n_r == 0:
                continue
            cost = (np.float64(_half_area(l0, l1, l2, m0, m1, m2)) * np.float64(n_l)
                    + np.float64(area_right[i + 1]) * np.float64(n_r))
            if cost < best_cost:
                best_cost, best_axis, best_cut = cost, a, i
    return best_cost, best_axis, best_cut


@_compiled
def _small_cut(records, start, n, n_bins, c_min, scale, keys, area_right):
    """:func:`_binned_cut` for a node of at most `SMALL_NODE` triangles: the same (cost, axis, bin).

    Per axis the triangles are sorted by bin (a stable insertion sort of the positions, in ``keys``); a cut
    after bin i leaves the same two sides for every i between two occupied bins, so only the cut after
    each occupied bin is evaluated — the first of its equals, as the sweep over all bins finds it — with
    the same boxes (min/max are exact) and the same float64 cost.
    """
    inf = np.float32(np.inf)
    best_cost, best_axis, best_cut = np.inf, 0, 0
    for a in range(3):
        for i in range(n):  # insertion sort of the positions by bin, stable
            j, b = i, _bin_of(records, start + i, a, c_min, scale, n_bins)
            while j > 0 and _bin_of(records, start + keys[j - 1], a, c_min, scale, n_bins) > b:
                keys[j] = keys[j - 1]
                j -= 1
            keys[j] = i
        r0, r1, r2, s0, s1, s2 = inf, inf, inf, -inf, -inf, -inf  # sorted triangles i.. (right sweep)
        for i in range(n - 1, -1, -1):
            e = start + keys[i]
            r0, r1, r2 = min(r0, records[e, 0]), min(r1, records[e, 1]), min(r2, records[e, 2])
            s0, s1, s2 = max(s0, records[e, 3]), max(s1, records[e, 4]), max(s2, records[e, 5])
            area_right[i] = _half_area(r0, r1, r2, s0, s1, s2)
        l0, l1, l2, m0, m1, m2 = inf, inf, inf, -inf, -inf, -inf
        for i in range(n - 1):
            e = start + keys[i]
            l0, l1, l2 = min(l0, records[e, 0]), min(l1, records[e, 1]), min(l2, records[e, 2])
            m0, m1, m2 = max(m0, records[e, 3]), max(m1, records[e, 4]), max(m2, records[e, 5])
            b = _bin_of(records, e, a, c_min, scale, n_bins)
            if b == _bin_of(records, start + keys[i + 1], a, c_min, scale, n_bins):
                continue  # not the last triangle of its bin
            cost = (np.float64(_half_area(l0, l1, l2, m0, m1, m2)) * np.float64(i + 1)
                    + np.float64(area_right[i + 1]) * np.float64(n - i - 1))
            if cost < best_cost:
                best_cost, best_axis, best_cut = cost, a, b
    return best_cost, best_axis, best_cut


@_compiled
def _partition(records, order, records_scratch, order_scratch, start, n, n_bins, c_min, scale, best_cost,
               best_axis, best_cut):
    """Stable partition of positions ``start:start + n`` by the cut (bin ≤ cut goes left; without a finite
    cut the first ⌊n/2⌋ go left): lefts in place from the start, rights through the scratch, then copied
    back. Returns the number sent left."""
    n_l, n_r = 0, 0
    for j in range(start, start + n):
        if best_cost < np.inf:
            left = _bin_of(records, j, best_axis, c_min, scale, n_bins) <= best_cut
        else:
            left = j - start < n // 2
        if left:
            _move(order, records, j, order, records, start + n_l)
            n_l += 1
        else:
            _move(order, records, j, order_scratch, records_scratch, start + n_r)
            n_r += 1
    for j in range(n_r):
        _move(order_scratch, records_scratch, start + j, order, records, start + n_l + j)
    return n_l


@_compiled
def _move(order, records, j, to_order, to_records, k):
    """Position ``j``'s triangle and record to position ``k`` of the other arrays (element by element: a
    row slice would make an array view per triangle)."""
    to_order[k] = order[j]
    for c in range(records.shape[1]):
        to_records[k, c] = records[j, c]


# ----------------------------------------------------------------------------- before and after the levels
# `BVH.build`'s NumPy passes around the levels (tofcore.scene.bvh: the corner gathers and boxes; `_tree_records`:
# the padding, `_collapse` to 4-wide nodes, the node and leaf records) as compiled loops: the same arrays bit for
# bit, without the (M,)- and (W, 4)-sized temporaries of the NumPy passes (fresh memory costs a page fault a page).
# Ties of min/max keep NumPy's choice (``np.minimum(a, b)`` is ``b`` where ``a == b``, so ``min(b, a)`` here: the
# sign of a zero), and the float32 arithmetic is the reference's own, in its order.


LAYOUT = dict(width=4, node_rows=7, child_row=6, leaf_rows=10, prim_row=9)
"""The records :func:`tree_records` writes (``tofcore.scene.bvh``'s `WIDTH`, `_NODE_ROWS`, `_CHILD_ROW`,
`_LEAF_ROWS`, `_PRIM_ROW`; its caller passes them and they are checked)."""


def triangle_records(vertices, triangles, *, parallel: bool | None = None):
    """(M, 9) float32 records of :func:`split_level`: each triangle's box minimum, maximum and centroid (xyz
    each), in triangle order — what ``bvh._build_binary`` stacks from the corner gathers, in one pass over the
    triangles. ``vertices`` (N, 3) float32, ``triangles`` (M, 3) int64; ``parallel`` as :func:`split_level`'s."""
    vertices, triangles = np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(triangles, np.int64)
    records = np.empty((len(triangles), 9), np.float32)
    if parallel is None:
        parallel = len(triangles) >= PARALLEL_LEVEL
    (_triangle_records_parallel if parallel else _triangle_records_serial)(vertices, triangles, records)
    return records


def _triangle_records(vertices, triangles, records):
    """The loop of :func:`triangle_records`."""
    half = np.float32(0.5)
    for i in prange(len(triangles)):
        p0, p1, p2 = triangles[i, 0], triangles[i, 1], triangles[i, 2]
        for a in range(3):
            x0, x1, x2 = vertices[p0, a], vertices[p1, a], vertices[p2, a]
            lo = min(x2, min(x1, x0))  # np.minimum(np.minimum(x0, x1), x2), ties included
            hi = max(x2, max(x1, x0))
            records[i, a], records[i, 3 + a], records[i, 6 + a] = lo, hi, (lo + hi) * half


def tree_records(vertices, triangles, order, node_lo, node_hi, left, right, start, count, leaf_size: int, *,
                 box_pad: float, width: int, node_rows: int, child_row: int, leaf_rows: int, prim_row: int,
                 parallel: bool | None = None):
    """The 4-wide tree's node and leaf records from the binary tree of the levels, as
    ``bvh._tree_records`` (the NumPy reference) makes them: ``(nodes, leaves, depth)``, (W · node_rows, width)
    and (L · leaf_rows, leaf_size) int32 and the number of wide levels.

    ``node_lo, node_hi`` (K, 3) float32 binary node boxes are padded in place; ``left, right, start, count``
    (K,) int64 as ``bvh._build_binary`` returns them. The layout (`width` children, rows of a record) is
    ``tofcore.scene.bvh``'s, passed in (this module imports nothing of it).
    """
    layout = dict(width=width, node_rows=node_rows, child_row=child_row, leaf_rows=leaf_rows, prim_row=prim_row)
    if layout != LAYOUT:
        raise ValueError(f"tree_records: the layout must be {LAYOUT} (the compiled loops'), got {layout}")
    vertices, triangles = np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(triangles, np.int64)
    if parallel is None:
        parallel = len(order) >= PARALLEL_LEVEL
    is_leaf = left < 0
    leaf_of = np.cumsum(is_leaf) - 1  # binary node -> leaf
    leaves = np.flatnonzero(is_leaf)
    _pad_boxes(node_lo, node_hi, np.float32(box_pad))
    slots = np.empty((max(1, len(left) - len(leaves)), 4), np.int64)  # pages of rows never written stay unmapped
    w, depth = _collapse_wide(left, right, node_lo, node_hi, slots)
    nodes = np.empty((w, node_rows, width), np.int32)
    leaf_rec = np.empty((len(leaves), leaf_rows, leaf_size), np.int32)
    fill_nodes, fill_leaves = ((_node_records_parallel, _leaf_records_parallel) if parallel else
                               (_node_records_serial, _leaf_records_serial))
    fill_nodes(slots, left, leaf_of, node_lo, node_hi, nodes, nodes.view(np.float32))
    fill_leaves(vertices, triangles, order, start, count, leaves, leaf_rec, leaf_rec.view(np.float32))
    return nodes.reshape(-1, width), leaf_rec.reshape(-1, leaf_size), depth


@_compiled
def _pad_boxes(node_lo, node_hi, box_pad):
    """Pad each box by ``box_pad`` · (largest |coordinate| + largest extent), in float32, in place."""
    for k in range(len(node_lo)):
        m0 = max(abs(node_hi[k, 0]), abs(node_lo[k, 0]))
        m1 = max(abs(node_hi[k, 1]), abs(node_lo[k, 1]))
        m2 = max(abs(node_hi[k, 2]), abs(node_lo[k, 2]))
        e0, e1, e2 = node_hi[k, 0] - node_lo[k, 0], node_hi[k, 1] - node_lo[k, 1], node_hi[k, 2] - node_lo[k, 2]
        pad = box_pad * (max(m2, max(m1, m0)) + max(e2, max(e1, e0)))
        for a in range(3):
            node_lo[k, a] = node_lo[k, a] - pad
            node_hi[k, a] = node_hi[k, a] + pad


@_compiled
def _collapse_wide(left, right, node_lo, node_hi, slots):
    """``bvh._collapse`` as a queue: wide node ``i`` (breadth first, the root 0) takes the two children of
    binary node ``queue[i]``, then twice replaces its inner child of the largest box area (the first of equals)
    by that child's two children; its inner children join the queue in slot order. ``slots`` (≥ W, 4) gets the
    binary children (−1 empty); returns (W, number of wide levels)."""
    if left[0] < 0:  # the root is a leaf
        slots[0, 0], slots[0, 1], slots[0, 2], slots[0, 3] = 0, -1, -1, -1
        return 1, 1
    queue = np.empty(len(slots), np.int64)  # binary node of each wide node
    level = np.empty(len(slots), np.int64)  # wide level of each wide node
    queue[0], level[0] = 0, 0
    w = 1
    for i in range(len(slots)):
        if i == w:
            break
        f = queue[i]
        slots[i, 0], slots[i, 1], slots[i, 2], slots[i, 3] = left[f], right[f], -1, -1
        for j in range(2, 4):
            pick, best = 0, -1.0
            for s in range(4):
                c = slots[i, s]
                area = -1.0
                if c >= 0 and left[c] >= 0:
                    area = np.float64(_half_area(node_lo[c, 0], node_lo[c, 1], node_lo[c, 2],
                                                 node_hi[c, 0], node_hi[c, 1], node_hi[c, 2]))
                if s == 0 or area > best:
                    pick, best = s, area
            c = slots[i, pick]
            if c >= 0 and left[c] >= 0:
                slots[i, pick], slots[i, j] = left[c], right[c]
        for s in range(4):
            c = slots[i, s]
            if c >= 0 and left[c] >= 0:
                queue[w], level[w] = c, level[i] + 1
                w += 1
    return w, level[w - 1] + 1


def _node_records(slots, left, leaf_of, node_lo, node_hi, nodes, nodes_f):
    """The node records (see `BVH.build`): child boxes (+∞/−∞ for an empty slot) and child rows (the wide node's
    first row, ``~`` the leaf's first row, 0 for an empty slot); wide ids are the queue order of
    :func:`_collapse_wide` (counted here again: each wide node's inner children, in slot order)."""
    w = len(nodes)
    first_child = np.empty(w, np.int64)  # wide id of each wide node's first inner child
    n = 1
    for i in range(w):
        first_child[i] = n
        for s in range(4):
            c = slots[i, s]
            if c >= 0 and left[c] >= 0:
                n += 1
    inf = np.float32(np.inf)
    for i in prange(w):
        next_id = first_child[i]
        for s in range(4):
            c = slots[i, s]
            if c < 0:
                for a in range(3):
                    nodes_f[i, a, s], nodes_f[i, 3 + a, s] = inf, -inf
                nodes[i, 6, s] = 0
                continue
            for a in range(3):
                nodes_f[i, a, s], nodes_f[i, 3 + a, s] = node_lo[c, a], node_hi[c, a]
            if left[c] < 0:
                nodes[i, 6, s] = ~(leaf_of[c] * 10)
            else:
                nodes[i, 6, s] = next_id * 7
                next_id += 1


def _leaf_records(vertices, triangles, order, start, count, leaves, leaf_rec, leaf_rec_f):
    """The leaf records (see `BVH.build`): v0, v1, v2 per axis of each slot's triangle (NaN padding), then the
    triangle index (−1 padding); leaf ``i`` is binary node ``leaves[i]``."""
    nan = np.float32(np.nan)
    leaf_size = leaf_rec.shape[2]
    for i in prange(len(leaves)):
        node = leaves[i]
        for k in range(leaf_size):
            if k < count[node]:
                p = order[start[node] + k]
                for j in range(3):
                    for a in range(3):
                        leaf_rec_f[i, 3 * j + a, k] = vertices[triangles[p, j], a]
                leaf_rec[i, 9, k] = p
            else:
                for r in range(9):
                    leaf_rec_f[i, r, k] = nan
                leaf_rec[i, 9, k] = -1


_triangle_records_parallel = _compiled_parallel(_named(_triangle_records, "_triangle_records_parallel"))
_triangle_records_serial = _compiled(_named(_triangle_records, "_triangle_records_serial"))
_node_records_parallel = _compiled_parallel(_named(_node_records, "_node_records_parallel"))
_node_records_serial = _compiled(_named(_node_records, "_node_records_serial"))
_leaf_records_parallel = _compiled_parallel(_named(_leaf_records, "_leaf_records_parallel"))
_leaf_records_serial = _compiled(_named(_leaf_records, "_leaf_records_serial"))

DRIVERS = (_split_level_parallel, _split_level_serial, _triangle_records_parallel, _triangle_records_serial,
           _pad_boxes, _collapse_wide, _node_records_parallel, _node_records_serial, _leaf_records_parallel,
           _leaf_records_serial)
"""The compiled functions a mesh's build calls from Python (:func:`warm_up` compiles them all)."""


def cached(parallel: bool) -> bool:
    """Whether this process has compiled, or numba's cache holds, the loops of one build (``parallel``: the build
    of meshes of at least `PARALLEL_LEVEL` triangles, else the serial one), fresh for these sources and this
    numba — a build then loads them in milliseconds instead of compiling them (4–6 s on 2 cores). A damaged
    data file behind a fresh index is compiled anew by numba; an index that cannot be read counts as not
    cached."""
    other = "_serial" if parallel else "_parallel"
    for driver in DRIVERS:
        if driver.py_func.__name__.endswith(other):
            continue
        if driver.overloads:  # compiled in this process already
            continue
        cache_file = getattr(getattr(driver, "_cache", None), "_cache_file", None)
        try:
            if cache_file is None or not cache_file._load_index():
                return False
        except Exception:  # noqa: BLE001 — a damaged index: numba compiles anew
            return False
    return True
