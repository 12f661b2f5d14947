"""The compiled tracer on the GPU: the same source (kernels.py) compiled by numba.cuda, as a wavefront.

:func:`load_kernels` executes ``kernels.py`` a second time under the module name
``tofcore.compiled.kernels_cuda``, for which every scalar function becomes a ``numba.cuda`` device
function and the ``wf_*`` functions kernels (:mod:`tofcore.compiled._target`). :func:`trace_pass` runs
the path in stages over groups of paths — start (camera and light rays), light vertices, then per depth
shade, resolve — with the BVH's own CUDA traversal (:mod:`tofcore.gpu.traversal`, one thread per ray,
bit for bit NumPy's) tracing every ray set in between, and gathers each pixel's addends in sample order:
the pass's sums are the CPU's addend by addend, so a GPU frame is the CPU frame up to the GPU's libm and
its fused multiply–adds in the shading code (tests/tofcore/test_gpu.py states the tolerance). No atomics:
the same frame on every run.

Why a wavefront (docs/benchmarks.md, issue 21): the whole path as one kernel (a megakernel) needed 255
registers a thread and ran at 12.5 % occupancy with 13 of 32 threads of a warp active — 208–229 ms for
the bench_peers frame, against 126 ms for these stages.

The machine code is cached by numba (``cache=True``) beside the sources (``tofcore/compiled/__pycache__``)
or under ``NUMBA_CACHE_DIR``: the first process on a machine compiles for ~15–30 s, later ones load it
(``tofcore warmup --device gpu``).
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
"""Threads per block of the stage kernels (128 measured the same, docs/benchmarks.md)."""

GROUP_BYTES = 512 << 20
"""Device memory one group's per-path state may take: the group size follows from it (about 0.4–0.9 M paths;
the Kinect v2 frame peaked at 2.3 GiB on the device with 768 MiB)."""

MAX_GROUP_PATHS = 1 << 20

STAGE_SECONDS: dict[str, float] = {}
"""Seconds per stage summed over the passes traced while :data:`PROFILE` is on (benchmarks only: each stage
then ends with a device synchronisation)."""

PROFILE = False

_MODULE = None


def _stage_done(name: str, since: float) -> float:
    """With :data:`PROFILE` on, wait for the device and add the time since ``since`` to stage ``name``."""
    if not PROFILE:
        return since
    cuda.synchronize()
    now = time.perf_counter()
    STAGE_SECONDS[name] = STAGE_SECONDS.get(name, 0.0) + now - since
    return now


def load_kernels():
    """The CUDA build of kernels.py (loaded once per process)."""
    global _MODULE
    if _MODULE is None:
        name = __name__.rsplit(".", 1)[0] + ".kernels" + CUDA_SUFFIX
        spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name("kernels.py"))
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        _MODULE = module
    return _MODULE


@dataclass(frozen=True, eq=False)
class DeviceScene:
    """A render's packed arrays (:class:`tofcore.compiled.setup.Packed`) on the GPU, uploaded once, and the
    scene's BVH (its records are uploaded by :mod:`tofcore.gpu.traversal` at the first ray)."""

    scene: tuple
    settings: tuple
    n_correlations: int
    max_depth: int
    bvh: object


def upload(packed, bvh) -> DeviceScene:
    """Copy the packed scene, camera, LED and channel tables to the GPU."""
    module = load_kernels()
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
    return DeviceScene(scene, settings, n_corr, int(packed.max_depth), bvh)


def launch_plan(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(order, active): pixels by decreasing sample count (stable), and for each sample index s < the
    largest count how many pixels have more than s samples — pixel order[i] has sample s for i < active[s]."""
    counts = np.asarray(counts, dtype=np.int64)
    order = np.argsort(-counts, kind="stable")
    most = int(counts.max()) if counts.size else 0
    more_than = counts.size - np.cumsum(np.bincount(counts, minlength=most + 1))  # [s]: #pixels with count > s
    return order, more_than[:most]


def groups(active: np.ndarray, limit: int) -> list[tuple[int, int]]:
    """Consecutive sample-index ranges [s0, s1) of at most ``limit`` paths each (at least one index)."""
    out, s0 = [], 0
    while s0 < len(active):
        s1, paths = s0 + 1, int(active[s0])
        while s1 < len(active) and paths + int(active[s1]) <= limit:
            paths += int(active[s1])
            s1 += 1
        out.append((s0, s1))
        s0 = s1
    return out


def path_bytes(n_depth: int, n_corr: int, n_led: int) -> int:
    """Device bytes of one path's state in a group: what :func:`_group_arrays` allocates for one path."""
    arrays = _group_arrays(np, 1, n_depth, n_corr, n_led + 1, load_kernels().LIGHT_COLUMNS)
    return sum(a.nbytes for v in arrays.values() for a in (v if isinstance(v, tuple) else (v,)))


def trace_pass(device_scene: DeviceScene, out, first: np.ndarray, counts: np.ndarray,
               threads_per_block: int = THREADS_PER_BLOCK) -> np.ndarray:
    """Trace samples [first[p], first[p] + counts[p]) of every pixel into ``out``'s sums on the GPU.

    ``out`` holds CuPy arrays ``signal_sum`` (K, P), ``correlation_sum`` (K, J, P) and ``replicate_sum``
    (R, J + 2, P) (a :class:`tofcore.tracer.transport.Transport` on the GPU); NumPy arrays under numba's
    CUDA simulator (tests). Per group of sample indices (:func:`groups`): start every path, trace the
    camera and light rays, the light vertices; per depth shade the live paths, trace the shadow rays that
    need a test, resolve, trace the next rays; gather. Returns the pass's ray counts (N_COUNTERS,) on the host.
    """
    from .. import backend

    module = load_kernels()
    xp = backend.namespace(out.signal_sum)
    bvh, scene, settings = device_scene.bvh, device_scene.scene, device_scene.settings
    n_pix = int(np.asarray(counts).size)
    k_max, n_corr = device_scene.max_depth, device_scene.n_correlations
    n_led = int(scene[4][0].shape[0])
    slots = n_led + 1
    order, active = launch_plan(counts)
    sums = (xp.zeros((k_max, n_pix)), xp.zeros((k_max, n_corr, n_pix)), xp.zeros((k_max, n_pix)),
            xp.zeros((k_max, n_corr, n_pix)), xp.zeros(out.replicate_sum.shape))
    dev_sums = _kernel_arrays(sums)
    rays_counted = xp.zeros(N_COUNTERS, np.int64)
    pixels = tuple(cuda.to_device(np.ascontiguousarray(a, dtype=np.int64)) for a in (order, first, counts))
    limit = max(1, min(MAX_GROUP_PATHS, GROUP_BYTES // path_bytes(k_max, n_corr, n_led)))

    def launch(kernel, n, *args):
        kernel[(n + threads_per_block - 1) // threads_per_block, threads_per_block](*args)

    for s0, s1 in groups(active, limit):
        offsets = np.concatenate([[0], np.cumsum(active[s0:s1])]).astype(np.int64)
        group = (*pixels, s0, cuda.to_device(offsets))
        arrays = _group_arrays(xp, int(offsets[-1]), k_max, n_corr, slots, module.LIGHT_COLUMNS)
        _trace_group(module, device_scene, group, arrays, launch)
        t = time.perf_counter()
        launch(module.wf_gather, int(offsets[1]), group, _kernel_array(arrays["path"][1]),
               _kernel_arrays(arrays["contrib"]), _kernel_array(arrays["total"]), dev_sums)
        rays_counted += arrays["counters"].sum(axis=1)
        _stage_done("gather", t)
    nee_w, nee_wg, con_w, con_wg, replicate = sums
    out.signal_sum += con_w          # the reference's order: connections, then next-event estimates
    out.signal_sum += nee_w
    out.correlation_sum += con_wg
    out.correlation_sum += nee_wg
    out.replicate_sum += replicate
    return backend.to_host(rays_counted)


def _group_arrays(xp, n: int, k_max: int, n_corr: int, slots: int, light_columns: int) -> dict:
    """The per-path arrays of a group of ``n`` paths (the table in kernels.py's wavefront section)."""
    f32, i32 = np.float32, np.int32
    return {"path": (xp.empty(n, np.int64), xp.empty(n, np.int64), xp.zeros(n, np.int8), xp.zeros(n, np.int8)),
            "pstate": (xp.empty((n, 13)), xp.empty(n, i32)),
            "rays": (xp.empty((n, 3), f32), xp.empty((n, 3), f32), xp.empty(n, i32), xp.empty(n, f32)),
            "light_rays": (xp.zeros((n, 3), f32), xp.zeros((n, 3), f32), xp.full(n, -1, i32)),
            "light": xp.zeros((n, light_columns)),
            "pend": (xp.zeros((n, slots)), xp.zeros((n, slots))),
            "shadow": (xp.zeros((n * slots, 3), f32), xp.zeros((n * slots, 3), f32), xp.zeros(n * slots, f32),
                       xp.full(n * slots, -1, i32)),
            "total": xp.zeros((n_corr + 2, n)),
            "contrib": (xp.zeros((k_max, n)), xp.zeros((k_max, n_corr, n)), xp.zeros((k_max, n)),
                        xp.zeros((k_max, n_corr, n))),
            "counters": xp.zeros((N_COUNTERS, n), np.int64)}


def _trace_group(module, device_scene: DeviceScene, group: tuple, arrays: dict, launch) -> None:
    """The stages of one group up to its gather: start, light vertices, then per depth trace, shade, trace
    the shadow rays, resolve. Every slot is traced at every depth: an ended path's ray and a shadow slot
    without a test have t_max −1, which the traversal rejects at the root — no compaction and no host
    synchronisation to count them."""
    bvh, scene, settings = device_scene.bvh, device_scene.scene, device_scene.settings
    k = _kernel_arrays
    n = int(arrays["path"][0].shape[0])
    rays, light_rays, shadow = arrays["rays"], arrays["light_rays"], arrays["shadow"]
    path, counters = k(arrays["path"]), _kernel_array(arrays["counters"])
    buffers = (k(arrays["pstate"]), _kernel_array(arrays["light"]), k(arrays["pend"]), k(shadow), k(rays), counters)
    t = _stage_done("allocate", time.perf_counter())
    launch(module.wf_start, n, scene, settings, group, path, buffers[0], buffers[4], k(light_rays), counters)
    t = _stage_done("start", t)
    if settings[3]:
        h = bvh.intersect(light_rays[0], light_rays[1])
        t = _stage_done("trace", t)
        launch(module.wf_light, n, scene, settings, path, k((h.prim, h.u, h.v)), buffers[1])
        t = _stage_done("light", t)
    total, contrib = _kernel_array(arrays["total"]), k(arrays["contrib"])
    for depth in range(1, device_scene.max_depth + 1):
        h = bvh.intersect(rays[0], rays[1], rays[3], ignore_prim=rays[2])
        t = _stage_done("trace", t)
        launch(module.wf_shade, n, scene, settings, depth, path, k((h.prim, h.u, h.v)), buffers)
        t = _stage_done("shade", t)
        occluded = bvh.occluded(shadow[0], shadow[1], shadow[2], ignore_prim=shadow[3])
        t = _stage_done("trace shadows", t)
        launch(module.wf_resolve, n, scene, depth, path, buffers[2], _kernel_array(occluded), total, contrib)
        t = _stage_done("resolve", t)


def _kernel_arrays(arrays: tuple) -> tuple:
    """Arrays as the kernels take them (:func:`_kernel_array`), converted once per group, not per launch."""
    return tuple(_kernel_array(a) for a in arrays)


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


def trace_frame(packed, bvh, n_pix: int, spp: int, threads_per_block: int = THREADS_PER_BLOCK) -> dict:
    """One pass of ``spp`` samples of every pixel on the GPU, for benchmarks and checks.

    Returns host arrays ``signal_sum`` (K, P), ``correlation_sum`` (K, J, P), ``replicate_sum``
    (R, J + 2, P), ``counters`` (N_COUNTERS,), the seconds of the pass (``kernel_s``, synchronised) and
    of the whole call (``seconds``: uploads, pass, read-back).
    """
    from .. import backend
    from ..tracer import qmc

    xp = np if numba.config.ENABLE_CUDASIM else backend.select_device("gpu").xp
    start = time.perf_counter()
    device_scene = upload(packed, bvh)
    n_corr = device_scene.n_correlations
    out = Sums(xp.zeros((packed.max_depth, n_pix)), xp.zeros((packed.max_depth, n_corr, n_pix)),
               xp.zeros((qmc.REPLICATES, n_corr + 2, n_pix)))
    first, counts = np.zeros(n_pix, np.int64), np.full(n_pix, spp, np.int64)
    cuda.synchronize()
    launch = time.perf_counter()
    counters = trace_pass(device_scene, out, first, counts, threads_per_block)
    cuda.synchronize()
    kernel_s = time.perf_counter() - launch
    return {"signal_sum": backend.to_host(out.signal_sum), "correlation_sum": backend.to_host(out.correlation_sum),
            "replicate_sum": backend.to_host(out.replicate_sum), "counters": counters, "kernel_s": kernel_s,
            "seconds": time.perf_counter() - start}
