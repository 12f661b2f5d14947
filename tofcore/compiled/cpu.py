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
