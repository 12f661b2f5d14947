"""The compiled tracer on the GPU: the same source (kernels.py) compiled by numba.cuda, one path per thread.

:func:`load_kernels` executes ``kernels.py`` a second time under the module name
``tofcore.compiled.kernels_cuda``, for which every scalar function becomes a ``numba.cuda`` device
function and :func:`tofcore.compiled.kernels.gpu_trace_samples` a kernel (:mod:`tofcore.compiled._target`).
:func:`trace_pass` launches that kernel over groups of m sample indices, one path per thread: sample
``s0 + l`` of a pixel goes to lane l of the pass's sums, so each lane of a pixel grows in sample order, no
two threads ever add to one lane (no atomics: the same frame on every run), and small frames still give
the GPU enough threads. Next-event estimates and light-vertex connections are kept apart as on the CPU;
the lanes are added in lane order and then to the transport in the reference's order: a GPU frame is the
CPU frame up to the GPU's libm, its fused multiply–adds and the lanes' rounding (tests/tofcore/test_gpu.py
states the tolerance).

The machine code is cached by numba (``cache=True``) beside the sources (``tofcore/compiled/__pycache__``)
or under ``NUMBA_CACHE_DIR``: the first process on a machine compiles for ~30 s, later ones load it.
"""

from __future__ import annotations

import importlib.util
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

if not hasattr(np, "row_stack"):  # NumPy 2.5 removed it; numba-cuda 0.30 still registers an overload for it
    np.row_stack = np.vstack
import numba  # noqa: E402
from numba import cuda  # noqa: E402

from ._target import CUDA_SUFFIX  # noqa: E402
from .layout import N_COUNTERS  # noqa: E402

THREADS_PER_BLOCK = 256
"""Threads per block: at the kernel's 255 registers a thread, one block of 256 fills an H100 SM's register
file; measured 208 ms a bench_peers frame against 237 ms at 128 and 257 ms at 64 (docs/benchmarks.md)."""

_MODULE = None
_VARIANTS: dict = {}


def load_kernels(max_registers: int | None = None):
    """(the CUDA build of kernels.py, its path kernel); ``max_registers`` limits the registers per thread
    (None: the compiler's choice, the cached build; a limit compiles a variant, uncached, for benchmarks)."""
    global _MODULE
    if _MODULE is None:
        name = __name__.rsplit(".", 1)[0] + ".kernels" + CUDA_SUFFIX
        spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name("kernels.py"))
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        _MODULE = module
    if max_registers is None:
        return _MODULE, _MODULE.gpu_trace_samples
    if max_registers not in _VARIANTS:
        _VARIANTS[max_registers] = cuda.jit(max_registers=max_registers)(_MODULE.gpu_trace_samples.py_func)
    return _MODULE, _VARIANTS[max_registers]


@dataclass(frozen=True, eq=False)
class DeviceScene:
    """A render's packed arrays (:class:`tofcore.compiled.setup.Packed`) on the GPU, uploaded once."""

    scene: tuple
    settings: tuple
    n_correlations: int
    max_depth: int


def upload(packed) -> DeviceScene:
    """Copy the packed scene, camera, LED and channel tables to the GPU."""
    module, _ = load_kernels()
    n_corr = len(packed.corr_kinds)
    if n_corr + 2 > module.GPU_MAX_CHANNELS:
        raise ValueError(f"the GPU tracer takes at most {module.GPU_MAX_CHANNELS - 2} correlation channels, "
                         f"got {n_corr}")
    dev = cuda.to_device
    corr_table = packed.corr_table if n_corr else np.zeros((1, 6))  # numba types an empty table by a row
    scene = (tuple(dev(np.ascontiguousarray(a)) for a in packed.geo), dev(packed.cam), dev(packed.cam_table),
             dev(packed.frame), tuple(dev(np.ascontiguousarray(a)) for a in packed.leds), dev(packed.corr_kinds),
             dev(corr_table))
    settings = (packed.key, packed.max_depth, packed.independent, packed.light_paths)
    return DeviceScene(scene, settings, n_corr, int(packed.max_depth))


PATHS_PER_LAUNCH = 1 << 20
"""Paths a launch aims at: enough threads to fill the GPU many times over (at 255 registers a thread an H100
holds ~34 k), so small frames run several sample indices per launch, each in its own lane of the sums."""

LANE_BYTES = 512 << 20
"""Device memory the lanes of a pass's sums may take together."""


def launch_plan(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(order, active): pixels by decreasing sample count (stable), and for each sample index s < the
    largest count how many pixels have more than s samples — pixel order[i] has sample s for i < active[s]."""
    counts = np.asarray(counts, dtype=np.int64)
    order = np.argsort(-counts, kind="stable")
    most = int(counts.max()) if counts.size else 0
    more_than = counts.size - np.cumsum(np.bincount(counts, minlength=most + 1))  # [s]: #pixels with count > s
    return order, more_than[:most]


def lane_count(active: np.ndarray, n_pix: int, bytes_per_lane: int) -> int:
    """Sample indices per launch m: about :data:`PATHS_PER_LAUNCH` paths, at most :data:`LANE_BYTES` of sums."""
    if not len(active):
        return 1
    by_paths = -(-PATHS_PER_LAUNCH // max(int(active[0]), 1))
    return int(max(1, min(len(active), by_paths, LANE_BYTES // max(bytes_per_lane, 1))))


def trace_pass(device_scene: DeviceScene, out, first: np.ndarray, counts: np.ndarray,
               threads_per_block: int = THREADS_PER_BLOCK, max_registers: int | None = None) -> np.ndarray:
    """Trace samples [first[p], first[p] + counts[p]) of every pixel into ``out``'s sums on the GPU.

    ``out`` holds CuPy arrays ``signal_sum`` (K, P), ``correlation_sum`` (K, J, P) and ``replicate_sum``
    (R, J + 2, P) (a :class:`tofcore.tracer.transport.Transport` on the GPU). A launch traces m sample
    indices (:func:`lane_count`), each into its own lane of the sums; the lanes are added in lane order,
    then connections before next-event estimates as on the CPU. Returns the pass's ray counts
    (N_COUNTERS,) on the host (one synchronisation per pass).
    """
    from .. import backend

    _, kernel = load_kernels(max_registers)
    xp = backend.namespace(out.signal_sum)  # CuPy; NumPy under numba's CUDA simulator (tests)
    n_pix = int(np.asarray(counts).size)
    k_max, n_corr = device_scene.max_depth, device_scene.n_correlations
    order, active = launch_plan(counts)
    per_lane = 8 * n_pix * (2 * k_max * (1 + n_corr) + int(np.prod(out.replicate_sum.shape[:-1])) + N_COUNTERS)
    m = lane_count(active, n_pix, per_lane)
    nee_w, con_w = xp.zeros((m, k_max, n_pix)), xp.zeros((m, k_max, n_pix))
    nee_wg, con_wg = xp.zeros((m, k_max, n_corr, n_pix)), xp.zeros((m, k_max, n_corr, n_pix))
    replicate = xp.zeros((m,) + tuple(out.replicate_sum.shape))
    counters = xp.zeros((m, N_COUNTERS, n_pix), np.int64)
    sums = tuple(_kernel_array(a) for a in (nee_w, nee_wg, con_w, con_wg, replicate, counters))
    pixels = tuple(cuda.to_device(np.ascontiguousarray(a, dtype=np.int64)) for a in (order, first, counts))
    for s0 in range(0, len(active), m):
        offsets = np.concatenate([[0], np.cumsum(active[s0:s0 + m])]).astype(np.int64)
        blocks = (int(offsets[-1]) + threads_per_block - 1) // threads_per_block
        kernel[blocks, threads_per_block](device_scene.scene, device_scene.settings,
                                          (*pixels, s0, cuda.to_device(offsets)), sums)
    for lane in range(1, m):  # lane order, the same on every run
        for a in (nee_w, nee_wg, con_w, con_wg, replicate, counters):
            a[0] += a[lane]
    out.signal_sum += con_w[0]          # the reference's order: connections, then next-event estimates
    out.signal_sum += nee_w[0]
    out.correlation_sum += con_wg[0]
    out.correlation_sum += nee_wg[0]
    out.replicate_sum += replicate[0]
    return backend.to_host(counters[0].sum(axis=1))


def _kernel_array(a):
    """A CuPy array as numba sees it (one conversion per pass, not per launch); a NumPy array as it is
    (numba's CUDA simulator)."""
    return cuda.as_cuda_array(a) if hasattr(a, "__cuda_array_interface__") else a


@dataclass
class Sums:
    """Stand-alone sums for :func:`trace_frame` (the layout of tofcore.tracer.transport.Transport)."""

    signal_sum: object
    correlation_sum: object
    replicate_sum: object


def trace_frame(packed, n_pix: int, spp: int, threads_per_block: int = THREADS_PER_BLOCK,
                max_registers: int | None = None) -> dict:
    """One pass of ``spp`` samples of every pixel on the GPU, for benchmarks and checks.

    Returns host arrays ``signal_sum`` (K, P), ``correlation_sum`` (K, J, P), ``replicate_sum``
    (R, J + 2, P), ``counters`` (N_COUNTERS,), the seconds of the launches (``kernel_s``, synchronised) and
    of the whole call (``seconds``: uploads, kernels, read-back).
    """
    from .. import backend
    from ..tracer import qmc

    xp = np if numba.config.ENABLE_CUDASIM else backend.select_device("gpu").xp
    start = time.perf_counter()
    device_scene = upload(packed)
    n_corr = device_scene.n_correlations
    out = Sums(xp.zeros((packed.max_depth, n_pix)), xp.zeros((packed.max_depth, n_corr, n_pix)),
               xp.zeros((qmc.REPLICATES, n_corr + 2, n_pix)))
    first, counts = np.zeros(n_pix, np.int64), np.full(n_pix, spp, np.int64)
    cuda.synchronize()
    launch = time.perf_counter()
    counters = trace_pass(device_scene, out, first, counts, threads_per_block, max_registers)
    cuda.synchronize()
    kernel_s = time.perf_counter() - launch
    return {"signal_sum": backend.to_host(out.signal_sum), "correlation_sum": backend.to_host(out.correlation_sum),
            "replicate_sum": backend.to_host(out.replicate_sum), "counters": counters, "kernel_s": kernel_s,
            "seconds": time.perf_counter() - start}
