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
        kernel = _module(cp).get_function(kernel_name)
        kernel(((n + _THREADS - 1) // _THREADS,), (_THREADS,), args + (status,))
        if int(status[0]):
            raise TofError("BVH: GPU traversal stack overflow (tree deeper than 32 levels); "
                           "use device='cpu' for this scene")


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
