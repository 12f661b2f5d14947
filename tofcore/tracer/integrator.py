r"""The path loop of one chunk: the stages of :mod:`tofcore.tracer.stages` over one path state.

Per pixel the estimator is the mean over its samples i of the light each path brings to the lens,
bucketed by the number k of surface vertices it went through,

.. math:: \hat S_k = \frac1n \sum_i \Big( \sum_{\text{LED } l} w^{NEE}_{i,k,l}
          + w^{LV}_{i,k} \Big), \qquad w^{LV}_{i,k} \text{ in bucket } k + 1,

with every w also kept as w·g_j(L/c) per correlation channel; the loop below is that sum, vertex by vertex
(next-event estimation to the LEDs, the light-vertex connection, then the BSDF's next direction).
"""

from __future__ import annotations

import time

import numpy as np

from .accumulate import Tally
from .light_paths import trace_light_vertices
from .setup import TraceSetup
from .stages import camera_rays, intersect, light_vertex, next_event, scatter, shade
from .transport import TraceStats, Transport


def trace_chunk(setup: TraceSetup, out: Transport, p0: int, p1: int, *, first, counts) -> TraceStats:
    """Trace samples [first[p], first[p] + counts[p]) of every pixel p in [p0, p1) into ``out``.

    Writes only the pixels [p0, p1) of ``out``, so chunks can run in parallel threads or worker processes.
    Returns the chunk's ray counters.
    """
    start = time.perf_counter()
    stats = TraceStats()
    state = camera_rays(setup, *chunk_samples(setup.xp, p0, first[p0:p1], counts[p0:p1]))
    tally = Tally.for_chunk(out, p0, p1, state)
    light = trace_light_vertices(setup, stats, state.pixel, state.sample) if setup.light_paths else None
    for k in range(1, setup.max_depth + 1):
        state, hits, ambient = intersect(setup, state, k, stats)
        if ambient is not None:
            tally.add_ambient(*ambient)
        if len(state) == 0:
            break
        state, vertex = shade(setup, state, hits, k)
        tally.add(state, next_event(setup, state, vertex, stats))
        if k == setup.max_depth:
            break
        if light is not None:
            tally.add(state, light_vertex(setup, state, vertex, light, stats))
        state = scatter(setup, state, vertex)
        if len(state) == 0:
            break
    tally.finish(ambient=setup.ambient is not None)
    stats.chunk_seconds = time.perf_counter() - start
    return stats


def chunk_samples(xp, p0: int, first, counts) -> tuple[np.ndarray, np.ndarray]:
    """(pixel, sample) of every path of a chunk: pixel p = p0, p0 + 1, … takes the samples first[p] … first[p]
    + counts[p] − 1 (``first`` and ``counts`` indexed from p0).

    Paths are ordered (pixel, sample), so each pixel sums its samples in sample order whatever the chunking.
    """
    n_paths = int(counts.sum())
    local_pixel = xp.repeat(xp.arange(len(counts)), counts)
    rank = xp.arange(n_paths) - (xp.cumsum(counts) - counts)[local_pixel]
    return p0 + local_pixel, first[local_pixel] + rank
