"""BVH traversal on the GPU: one CUDA thread per ray over the records :class:`tofcore.scene.bvh.BVH` builds.

The twin of ``BVH.intersect`` (closest hit) and ``BVH.occluded`` (any hit, early exit): same records,
same watertight triangle test in the same float32 operation order (compiled without FMA contraction),
same ``ignore_prim`` rule; see ``traversal.cu``. :func:`tofcore.backend.device_twin` dispatches here when the
rays are CuPy arrays.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from .. import backend
from ..errors import TofError
from ..scene import bvh as _bvh
from ..scene.bvh import Hits

_THREADS = 128
_SOURCE = Path(__file__).with_name("traversal.cu")


#: the constants the kernel shares with :mod:`tofcore.scene.bvh`, #defined from the Python source.
LAYOUT = {"WIDTH": _bvh.WIDTH, "NODE_ROWS": _bvh._NODE_ROWS, "LEAF_ROWS": _bvh._LEAF_ROWS,
          "CHILD_ROW": _bvh._CHILD_ROW, "PRIM_ROW": _bvh._PRIM_ROW, "TINY_DIR": _bvh._TINY_DIR}


def source() -> str:
    """The CUDA source: the shared constants as ``#define`` lines, then ``traversal.cu``."""
    return "".join(f"#define {name} {value!r}\n" for name, value in LAYOUT.items()) + _SOURCE.read_text()


@functools.lru_cache(maxsize=None)
def _module(cp_module):
    return cp_module.RawModule(code=source(), options=("--std=c++17", "--fmad=false"))


def _rays(cp, bvh, origins, directions, t_max, ignore_prim):
    o = cp.ascontiguousarray(origins, dtype=cp.float32).reshape(-1, 3)
    d = cp.ascontiguousarray(directions, dtype=cp.float32).reshape(-1, 3)
    n = len(o)
    if len(d) != n:
        raise ValueError(f"BVH: directions must have the shape of origins {o.shape}, got {d.shape}")
    tm = cp.full(n, np.inf, cp.float32) if t_max is None else cp.ascontiguousarray(
        cp.broadcast_to(cp.asarray(t_max, cp.float32), (n,)))
    ig = cp.full(n, -1, cp.int32) if ignore_prim is None else cp.ascontiguousarray(
        cp.broadcast_to(cp.asarray(ignore_prim).astype(cp.int32, copy=False), (n,)))
    nodes = backend.device_copy(cp, bvh._nodes)
    leaves = backend.device_copy(cp, bvh._leaves)
    return o, d, tm, ig, nodes, leaves, n


def _launch(cp, kernel_name, n, args):
    status = cp.zeros(1, cp.int32)
    if n:
        _launch_into(cp, kernel_name, n, args, status)
        check_status(status)


def _launch_into(cp, kernel_name, n, args, status):
    kernel = _module(cp).get_function(kernel_name)
    kernel(((n + _THREADS - 1) // _THREADS,), (_THREADS,), args + (status,))


def check_status(status) -> None:
    """Raise if a traversal flagged a stack overflow in ``status`` (one synchronisation)."""
    if int(status[0]):
        raise TofError("BVH: GPU traversal stack overflow (tree deeper than 32 levels); "
                       "use device='cpu' for this scene")


def closest_hits_into(bvh, rays: tuple, n: int, hits: tuple, status) -> None:
    """Closest hits of rays 0 … n − 1 of ``rays`` = (origins (≥ n, 3) f32, directions, t_max (≥ n,) f32,
    ignore_prim (≥ n,) i32) into ``hits`` = (prim, u, v, t) CuPy arrays: :func:`intersect` without
    allocating or synchronising — the wavefront's buffers are reused from group to group, and a stack
    overflow is flagged in ``status`` for :func:`check_status` at the end of the pass."""
    if n:
        cp = backend.namespace(rays[0])
        nodes, leaves = backend.device_copy(cp, bvh._nodes), backend.device_copy(cp, bvh._leaves)
        prim, u, v, t = hits
        _launch_into(cp, "closest_hit", n, (nodes, leaves, np.int32(leaves.shape[1]), *rays, np.int64(n),
                                           t, prim, u, v), status)


def occluded_into(bvh, rays: tuple, n: int, out, status) -> None:
    """Any hit of rays 0 … n − 1 of ``rays`` (as :func:`closest_hits_into`) into the bool array ``out``:
    :func:`occluded` without allocating or synchronising."""
    if n:
        cp = backend.namespace(rays[0])
        nodes, leaves = backend.device_copy(cp, bvh._nodes), backend.device_copy(cp, bvh._leaves)
        _launch_into(cp, "any_hit", n, (nodes, leaves, np.int32(leaves.shape[1]), *rays, np.int64(n), out), status)


def intersect(bvh, origins, directions, t_max=None, ignore_prim=None, *, workers: int = 2, counters=None):
    """Closest hits (``tofcore.scene.bvh.Hits`` of CuPy arrays), as ``BVH.intersect`` (``workers`` and
    ``counters`` are the reference's CPU options, unused here)."""
    cp = backend.namespace(origins, directions)
    o, d, tm, ig, nodes, leaves, n = _rays(cp, bvh, origins, directions, t_max, ignore_prim)
    t = cp.empty(n, cp.float32)
    prim = cp.empty(n, cp.int32)
    u = cp.empty(n, cp.float32)
    v = cp.empty(n, cp.float32)
    _launch(cp, "closest_hit", n, (nodes, leaves, np.int32(leaves.shape[1]), o, d, tm, ig, np.int64(n),
                                   t, prim, u, v))
    return Hits(t=t, prim=prim, u=u, v=v)


def occluded(bvh, origins, directions, t_max, ignore_prim=None, *, workers: int = 2, counters=None):
    """(R,) bool CuPy array: any hit with ``0 < t < t_max``, as ``BVH.occluded`` (CPU options unused)."""
    cp = backend.namespace(origins, directions)
    o, d, tm, ig, nodes, leaves, n = _rays(cp, bvh, origins, directions, t_max, ignore_prim)
    out = cp.empty(n, cp.bool_)
    _launch(cp, "any_hit", n, (nodes, leaves, np.int32(leaves.shape[1]), o, d, tm, ig, np.int64(n), out))
    return out
