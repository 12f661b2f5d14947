"""The compiled tracer's path function compiled for CUDA from the same source (a spike, issue 21 route c).

:func:`load_kernels` executes ``kernels.py`` a second time under the module name
``tofcore.compiled.kernels_cuda``, for which every scalar function becomes a ``numba.cuda`` device
function (:mod:`tofcore.compiled._target`); :func:`trace_frame` runs one thread per pixel — the pixel's
samples in sample order, the per-bucket sums kept apart as on the CPU (next-event estimates and
light-vertex connections) and added in the reference's order — so a frame is the CPU frame up to the
GPU's libm and its fused multiply–adds. Not wired into :func:`tofcore.trace` yet: ``bench/bench_compiled.py``
times it and compares it with the CPU tracers.
"""

from __future__ import annotations

import importlib.util
import sys
import time
from pathlib import Path

import numpy as np

if not hasattr(np, "row_stack"):  # NumPy 2.5 removed it; numba-cuda 0.30 still registers an overload for it
    np.row_stack = np.vstack
from numba import cuda, float32, float64, int64  # noqa: E402

from ._target import CUDA_SUFFIX
from .layout import N_COUNTERS, STACK_SIZE

MAX_CHANNELS = 32
"""Correlation channels + 2 a thread can hold (local arrays need a size known when compiling)."""

_KERNELS = None


def load_kernels():
    """The module of device functions: kernels.py compiled by numba.cuda (loaded once per process)."""
    global _KERNELS
    if _KERNELS is None:
        name = __name__.rsplit(".", 1)[0] + ".kernels" + CUDA_SUFFIX
        spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name("kernels.py"))
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        _KERNELS = (module, _build(module))
    return _KERNELS


def _build(k):
    @cuda.jit
    def trace_pixels(scene, settings, pixels, sums):
        """Trace pixel p's samples: ``scene`` and ``settings`` as in kernels.trace_path, ``pixels`` =
        (first, counts), ``sums`` = per-pixel (nee_w, nee_wg, con_w, con_wg, replicate, counters)."""
        p = cuda.grid(1)
        first, counts = pixels
        if p >= first.shape[0]:
            return
        nee_w, nee_wg, con_w, con_wg, replicate, counters = sums
        n_ch = scene[5].shape[0] + 2
        total = cuda.local.array(MAX_CHANNELS, float64)
        count = cuda.local.array(N_COUNTERS, int64)
        work = (count, cuda.local.array(STACK_SIZE, int64), cuda.local.array(STACK_SIZE, float32),
                cuda.local.array(MAX_CHANNELS, float64))
        path_sums = (nee_w[p], nee_wg[p], con_w[p], con_wg[p], total)
        for c in range(N_COUNTERS):
            count[c] = 0
        for sample in range(first[p], first[p] + counts[p]):
            k.trace_path(scene, settings, p, sample, path_sums, work)
            r = sample % replicate.shape[1]
            for c in range(n_ch):
                replicate[p, r, c] += total[c]
        for c in range(N_COUNTERS):
            counters[p, c] = count[c]

    return trace_pixels


def trace_frame(packed, n_pix: int, spp: int, threads_per_block: int = 128) -> dict:
    """One pass of ``spp`` samples of every pixel on the GPU; sums in the layout of tofcore.transport.Transport.

    Returns host arrays ``signal_sum`` (K, P), ``correlation_sum`` (K, J, P), ``replicate_sum``
    (R, J + 2, P), ``counters`` (N_COUNTERS,) and the seconds of the kernel (``kernel_s``, synchronised)
    and of the whole call (``seconds``: uploads, kernel, read-back).
    """
    from ..tracer import qmc

    module, kernel = load_kernels()
    start = time.perf_counter()
    n_corr = len(packed.corr_kinds)
    if n_corr + 2 > MAX_CHANNELS:
        raise ValueError(f"cuda.trace_frame: at most {MAX_CHANNELS - 2} correlation channels, got {n_corr}")
    k_max = packed.max_depth
    dev = cuda.to_device
    # an empty channel table still needs a row for numba's typing
    corr_table = packed.corr_table if n_corr else np.zeros((1, 6))
    scene = (tuple(dev(np.ascontiguousarray(a)) for a in packed.geo), dev(packed.cam), dev(packed.cam_table),
             dev(packed.frame), tuple(dev(np.ascontiguousarray(a)) for a in packed.leds), dev(packed.corr_kinds),
             dev(corr_table))
    settings = (packed.key, packed.max_depth, packed.independent, packed.light_paths)
    pixels = (dev(np.zeros(n_pix, np.int64)), dev(np.full(n_pix, spp, np.int64)))
    sums = [dev(np.zeros(shape)) for shape in ((n_pix, k_max), (n_pix, k_max, max(n_corr, 1)), (n_pix, k_max),
                                               (n_pix, k_max, max(n_corr, 1)), (n_pix, qmc.REPLICATES, n_corr + 2))]
    counters = cuda.device_array((n_pix, N_COUNTERS), np.int64)
    cuda.synchronize()
    launch = time.perf_counter()
    kernel[(n_pix + threads_per_block - 1) // threads_per_block, threads_per_block](scene, settings, pixels,
                                                                                    (*sums, counters))
    cuda.synchronize()
    kernel_s = time.perf_counter() - launch
    nee_w, nee_wg, con_w, con_wg, replicate = (s.copy_to_host() for s in sums)
    signal = np.zeros((k_max, n_pix))
    signal += con_w.T
    signal += nee_w.T
    corr = np.zeros((k_max, n_corr, n_pix))
    corr += con_wg[:, :, :n_corr].transpose(1, 2, 0)
    corr += nee_wg[:, :, :n_corr].transpose(1, 2, 0)
    return {"signal_sum": signal, "correlation_sum": corr,
            "replicate_sum": np.zeros((qmc.REPLICATES, n_corr + 2, n_pix)) + replicate.transpose(1, 2, 0),
            "counters": counters.copy_to_host().sum(axis=0), "kernel_s": kernel_s,
            "seconds": time.perf_counter() - start}
