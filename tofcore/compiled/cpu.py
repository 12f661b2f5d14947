"""The compiled tracer on the CPU: :func:`tofcore.compiled.kernels.trace_pixels` over a chunk's pixels on
numba's threads, each path one call of :func:`tofcore.compiled.kernels.trace_path`.

A pixel's samples are traced by one thread in sample order and its sums are added to the frame's
accumulators in the order the NumPy reference adds them (per bounce bucket: the light-vertex
connections of the previous vertex, then the next-event estimates; per replicate: the path totals in
sample order), so the two tracers differ only where the compiled libm rounds a transcendental function
differently from NumPy's (tests/tofcore/test_compiled.py).

One chunk at a time per process (:data:`PARALLEL_LOCK`): numba's ``workqueue`` threading layer, the one
it falls back to where neither TBB nor OpenMP loads, aborts the whole process ("Concurrent access has been
detected") when two Python threads run ``parallel=True`` code at once — two renders on two threads did
(tests/tofcore/test_compiled_threads.py), and Blender's add-on starts a live preview while the one it
cancelled may still trace its last chunk. The chunks of concurrent renders take turns; each chunk still
runs on all of numba's threads.
"""

from __future__ import annotations

import threading

import numpy as np

from ..tracer import stages
from ..tracer.transport import FirstHit
from . import kernels
from .layout import N_COUNTERS

PARALLEL_LOCK = threading.Lock()
"""Held while a chunk runs on numba's threads (see the module docstring)."""


def trace_chunk(packed, out, p0: int, p1: int, first: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Trace pixels [p0, p1) of a pass into the transport ``out``; returns the (N_COUNTERS,) ray counts."""
    counters = np.zeros((p1 - p0, N_COUNTERS), np.int64)
    pixels = (p0, p1, np.ascontiguousarray(first, dtype=np.int64), np.ascontiguousarray(counts, dtype=np.int64))
    film = out.transient_sum if out.transient_sum is not None else np.zeros((0, 0))
    with PARALLEL_LOCK:
        kernels.trace_pixels(packed.scene(), packed.settings(), pixels,
                             (out.signal_sum, out.correlation_sum, out.replicate_sum, out.ambient_sum, film, counters))
    return counters.sum(axis=0)


def first_hit(packed, setup, stats) -> FirstHit:
    """The noise-free ground truth (:func:`tofcore.tracer.stages.first_hit`, the same rays, hits and arithmetic)
    traced by :func:`tofcore.compiled.kernels.first_hits` on numba's threads: the reference traverses in NumPy
    on two threads, 0.3 s of a 4.5-s frame on 16 cores."""
    d = np.ascontiguousarray(stages.pixel_centre_directions(setup))
    n = len(d)
    prim, point, normal = np.full(n, -1, np.int32), np.zeros((n, 3)), np.zeros((n, 3))
    with PARALLEL_LOCK:
        kernels.first_hits(packed.geo, tuple(float(x) for x in setup.lens_center), d, (prim, point, normal))
    stats.camera_rays += n
    hit = prim >= 0
    return stages.first_hit_record(setup, d, hit, np.where(hit, prim, 0), point, normal)


def compile_kernels(packed, out, first: np.ndarray, counts: np.ndarray) -> None:
    """Compile (or load) every CPU kernel a trace calls, tracing nothing: the paths' driver on an empty pixel
    range and the ground truth's on no rays."""
    trace_chunk(packed, out, 0, 0, first, counts)
    with PARALLEL_LOCK:
        kernels.first_hits(packed.geo, (0.0, 0.0, 0.0), np.zeros((0, 3)),
                           (np.zeros(0, np.int32), np.zeros((0, 3)), np.zeros((0, 3))))
