"""The compiled tracer on the CPU: every pixel of a chunk on numba's threads, each path one call of
:func:`tofcore.compiled.kernels.trace_path`.

A pixel's samples are traced by one thread in sample order and its sums are added to the frame's
accumulators in the order the NumPy reference adds them (per bounce bucket: the light-vertex
connections of the previous vertex, then the next-event estimates; per replicate: the path totals in
sample order), so the two tracers differ only where the compiled libm rounds a transcendental function
differently from NumPy's (tests/tofcore/test_compiled.py).
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from . import kernels
from .layout import N_COUNTERS, STACK_SIZE


@numba.njit(parallel=True, cache=True, nogil=True, error_model="numpy")
def trace_pixels(geo, cam, cam_table, frame, leds, corr_kinds, corr_table, key, max_depth, independent,
                 light_paths, p0, p1, first, counts, signal_sum, correlation_sum, replicate_sum, counters):
    """Trace samples [first[p], first[p] + counts[p]) of pixels p0 ≤ p < p1 into the frame's sums.

    ``signal_sum`` (K, P), ``correlation_sum`` (K, J, P), ``replicate_sum`` (R, J + 2, P) as in
    :class:`tofcore.transport.Transport`; ``counters`` (p1 − p0, N_COUNTERS) receives each pixel's ray counts.
    """
    n_depth = signal_sum.shape[0]
    n_corr = corr_kinds.shape[0]
    n_rep = replicate_sum.shape[0]
    n_ch = n_corr + 2
    for local in prange(p1 - p0):
        p = p0 + local
        nee_w = np.zeros(n_depth)
        con_w = np.zeros(n_depth)
        nee_wg = np.zeros((n_depth, n_corr))
        con_wg = np.zeros((n_depth, n_corr))
        total = np.zeros(n_ch)
        wg = np.zeros(n_corr)
        replicate = np.zeros((n_rep, n_ch))
        count = np.zeros(N_COUNTERS, np.int64)
        stack = np.empty(STACK_SIZE, np.int64)
        stack_t = np.empty(STACK_SIZE, np.float32)
        for sample in range(first[p], first[p] + counts[p]):
            kernels.trace_path(geo, cam, cam_table, frame, leds, corr_kinds, corr_table, key, p, sample,
                               max_depth, independent, light_paths, nee_w, nee_wg, con_w, con_wg, total, wg,
                               count, stack, stack_t)
            r = sample % n_rep
            for c in range(n_ch):
                replicate[r, c] += total[c]
        for k in range(n_depth):
            signal_sum[k, p] += con_w[k]
            signal_sum[k, p] += nee_w[k]
            for j in range(n_corr):
                correlation_sum[k, j, p] += con_wg[k, j]
                correlation_sum[k, j, p] += nee_wg[k, j]
        for r in range(n_rep):
            for c in range(n_ch):
                replicate_sum[r, c, p] += replicate[r, c]
        for c in range(N_COUNTERS):
            counters[local, c] = count[c]


def trace_chunk(packed, out, p0: int, p1: int, first: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Trace pixels [p0, p1) of a pass into the transport ``out``; returns the (N_COUNTERS,) ray counts."""
    counters = np.zeros((p1 - p0, N_COUNTERS), np.int64)
    trace_pixels(packed.geo, packed.cam, packed.cam_table, packed.frame, packed.leds, packed.corr_kinds,
                 packed.corr_table, packed.key, packed.max_depth, packed.independent, packed.light_paths,
                 p0, p1, np.ascontiguousarray(first, dtype=np.int64), np.ascontiguousarray(counts, dtype=np.int64),
                 out.signal_sum, out.correlation_sum, out.replicate_sum, counters)
    return counters.sum(axis=0)
