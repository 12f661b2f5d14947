"""Tracing a frame: :func:`trace` and :func:`trace_progressive`, passes of samples over the whole frame.

A trace checks its settings into a :class:`~tofcore.tracer.setup.TraceSetup`, traces the noise-free first
hits (:func:`~tofcore.tracer.stages.first_hit`), then runs passes of samples (:func:`pass_schedule`), each
cut into chunks that :mod:`tofcore.tracer.parallel` runs, and yields the accumulated
:class:`~tofcore.tracer.transport.Transport` after every pass.
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .. import backend, limits
from ..errors import ConfigError
from ..limits import usable_cpus
from ..scene.ambient import Ambient
from ..scene.camera import Camera
from ..scene.led import LED
from ..scene.scene import Scene
from . import parallel, qmc, workers
from .setup import Correlation, TraceSettings, TraceSetup, make_setup
from .stages import first_hit
from .transport import FirstHit, TraceStats, Transport


def trace(scene: Scene, camera: Camera, leds: Sequence[LED], **kwargs) -> Transport:
    """Trace a whole frame; see :func:`trace_progressive` for the parameters.

    Only the finished frame is wanted, so the passes are of 16 samples (``progressive=False``, fewer
    waits for the slowest chunk) unless ``progressive`` is given.
    """
    transport = None
    kwargs.setdefault("progressive", False)
    passes = trace_progressive(scene, camera, leds, **kwargs)
    try:
        for transport in passes:
            pass
    finally:  # an interrupt releases the workers' shared memory at once, not when the generator is collected
        passes.close()
    return transport


def trace_progressive(scene: Scene, camera: Camera, leds: Sequence[LED], *,
                      world_from_sensor: np.ndarray | None = None,
                      correlations: Sequence[Correlation] | Callable = (),
                      ambient: Ambient | None = None,
                      spp: int = 16, max_depth: int = 5, seed: int = 0,
                      chunk_size: int | None = None, workers: int | None = None,
                      transient_bin_m: float | None = None, transient_max_m: float | None = None,
                      cancel: Callable[[], bool] | None = None,
                      device: str | backend.Device = "cpu", progressive: bool = True,
                      sampler: str = "sobol", light_paths: bool = True,
                      allocate: Callable[[Transport, int], np.ndarray | None] | None = None,
                      pass_size: Callable[[Transport, int], int] | None = None) -> Iterator[Transport]:
    """Trace in progressive passes, yielding the accumulated :class:`Transport` after each.

    Parameters
    ----------
    scene, camera, leds : what to render; LED positions are in the sensor frame.
    world_from_sensor : 4×4 pose (sensor frame = OpenCV: x right, y down, z forward); identity by default.
    correlations : g_j(τ), τ in seconds, one per sensor bucket/phase image; or a bank τ → (J, N) of them
        all with ``len`` J (:meth:`tofcore.sensor.modulation.Modulation.correlation_bank`, faster).
    ambient : background radiance; ``None`` or black skips all ambient work.
    spp : samples per pixel in total; max_depth : surface vertices per path (1 = direct only).
    seed : non-negative int; the same seed gives the same frame for any ``chunk_size``.
    chunk_size : paths in flight per chunk; bounds memory. Default: 65,536 on the CPU (temporaries
        stay in cache); on the GPU as many as :func:`~.parallel.gpu_chunk_paths` allows in free device memory.
    workers : processes tracing chunks at once on the CPU (default: the usable CPUs, affinity and cgroup
        quota respected, :func:`tofcore.limits.usable_cpus`; the GPU uses one). They share the scene,
        BVH and accumulators (:mod:`tofcore.tracer.workers`); passes too small to be worth it (fewer than
        two chunks) run in this process. Where no worker process can be started (a Blender without its
        Python interpreter) the chunks run on threads instead, and ``stats.parallel`` says which.
        Chunks own disjoint pixels, so the result does not depend on it.
    transient_bin_m, transient_max_m : optional histogram of w over path length (bin width, range), metres.
    cancel : polled before every chunk; when it returns True, :class:`~tofcore.errors.Cancelled` is raised.
    progressive : passes of 1, 1, 2, 4, … samples (True) or of 16 (False); see :func:`pass_schedule`.
    sampler : ``"sobol"`` (randomized QMC, :mod:`tofcore.tracer.qmc`) or ``"independent"`` (plain uniforms, for
        comparisons). Both are unbiased and keep the R replicates of the error estimate.
    light_paths : connect every camera vertex to one light vertex per sample (an LED's first hit), both
        strategies weighted by multiple importance sampling (:mod:`tofcore.tracer.light_paths`). Unbiased
        either way; it removes the fireflies of surfaces close to an LED. Needs ``max_depth`` ≥ 2.
    allocate : adaptive sampling: called before every pass with the accumulated transport and the pass's
        mean samples per pixel n; returns (P,) int samples per pixel for this pass (summing to about n·P,
        e.g. :func:`tofcore.tracer.estimator.allocate_samples`) or None for n everywhere. Each pixel's samples
        keep their indices 0, 1, 2, … whatever the allocation, so a pixel's estimate is the same
        function of its own samples as without it. ``spp`` then counts the mean over the pixels.
    pass_size : called before every pass with the accumulated transport and the scheduled pass's samples
        per pixel n (:func:`next_pass_size`); returns the pass's samples per pixel, 0..n (0 ends the trace).
        A time budget sizes its last pass with it (:mod:`tofcore.tracer.budget`); the samples stay the same
        whatever the sizes, only the passes they fall into change.
    device : ``"cpu"`` (NumPy), ``"gpu"`` (CuPy) or ``"auto", or a resolved :class:`tofcore.backend.Device`.
        On the GPU the accumulators of the yielded :class:`Transport` are CuPy arrays (``first_hit`` is
        always NumPy); the same seed gives the same sums within float rounding (``tests/tofcore/test_gpu.py``).

    The yielded object is the live accumulator: copy what you keep between passes.
    """
    settings = TraceSettings(
        world_from_sensor=world_from_sensor, correlations=correlations, ambient=ambient, spp=spp,
        max_depth=max_depth, seed=seed, chunk_size=chunk_size, workers=workers, transient_bin_m=transient_bin_m,
        transient_max_m=transient_max_m, cancel=cancel, device=device, progressive=progressive, sampler=sampler,
        light_paths=light_paths, allocate=allocate, pass_size=pass_size)
    return _passes(scene, camera, leds, settings)


def _passes(scene: Scene, camera: Camera, leds: Sequence[LED], settings: TraceSettings) -> Iterator[Transport]:
    """:func:`trace_progressive` on its checked settings."""
    dev = backend.select_device(settings.device)
    setup = make_setup(scene, camera, leds, settings, dev)
    chunk_size, n_workers = _parallel_settings(settings, setup)
    start = time.perf_counter()
    tracer = importlib.import_module(parallel.COMPILED_TRACER).choose(setup)  # compiled where numba allows
    stats = TraceStats(tracer=tracer.tracer, tracer_reason=tracer.reason)
    if tracer.packed is not None and not dev.is_gpu and settings.cancel is not None:
        # numba's compile cannot be cancelled, a child process compiling for us can
        stats.compile = importlib.import_module(parallel.COMPILED_TRACER + ".child_compile").compile_aside(
            settings.cancel)
    # Start the worker processes first: they boot and import tofcore while this one traces the first hits.
    # The compiled tracer runs on numba's threads instead (they release the GIL).
    spawn = n_workers > 1 and not dev.is_gpu and tracer.packed is None
    why_not = parallel.start_workers(n_workers) if spawn else "one"
    transport = _empty_transport(setup, first_hit(setup, stats), stats)
    shared = None
    try:  # from the shared memory on, the finally releases it, whatever stops the trace (Ctrl-C included)
        with workers.sigint_held():  # a Ctrl-C meanwhile is raised once `shared` holds what to release
            shared, why_not = (None, why_not) if why_not else parallel.share(setup, transport)
        stats.parallel = "processes" if shared is not None else "one" if why_not == "one" else f"threads: {why_not}"
        if tracer.packed is not None:
            stats.parallel = importlib.import_module(parallel.COMPILED_TRACER).parallel_label(tracer, n_workers)
        stats.setup_seconds = time.perf_counter() - start
        n_pix = camera.width * camera.height
        done = np.zeros(n_pix, np.int64)  # host copy of transport.sample_count
        with ThreadPoolExecutor(max_workers=n_workers) as threads:
            runner = parallel.PassRunner(setup, transport, shared, threads, n_workers, chunk_size, settings.cancel,
                                         compiled=tracer if tracer.packed is not None else None)
            nominal = 0  # samples per pixel the passes so far were asked for
            while nominal < settings.spp:
                n_samples = next_pass_size(nominal, int(settings.spp), settings.progressive)
                if settings.pass_size is not None:
                    n_samples = _checked_pass_size(settings.pass_size(transport, n_samples), n_samples)
                    if n_samples == 0:
                        return
                nominal += n_samples
                counts = None if settings.allocate is None else settings.allocate(transport, n_samples)
                counts = np.full(n_pix, n_samples, np.int64) if counts is None else _checked_counts(counts, n_pix)
                runner.run(done, counts)
                done += counts
                transport.sample_count += dev.xp.asarray(counts)
                stats.passes += 1
                stats.seconds = time.perf_counter() - start
                yield transport
    finally:
        if shared is not None:
            parallel.unshare(shared, transport)
        if tracer.packed is not None:
            importlib.import_module(parallel.COMPILED_TRACER).release(tracer)


def _parallel_settings(settings: TraceSettings, setup: TraceSetup) -> tuple[int, int]:
    """(paths per chunk, workers), checked; the GPU traces one stream of large chunks."""
    spp, chunk_size, workers = settings.spp, settings.chunk_size, settings.workers
    if not isinstance(spp, (int, np.integer)) or spp < 1:
        raise ConfigError(f"trace: spp must be an integer >= 1, got {spp!r}")
    if chunk_size is None:
        chunk_size = (parallel.gpu_chunk_paths(setup.xp, setup.n_channels) if setup.device.is_gpu
                      else parallel.CPU_CHUNK_PATHS)
    if not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1:
        raise ConfigError(f"trace: chunk_size must be an integer >= 1, got {chunk_size!r}")
    workers = usable_cpus() if workers is None else workers
    if not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ConfigError(f"trace: workers must be an integer >= 1, got {workers!r}")
    limits.MAX_WORKERS.check(int(workers), "trace", "workers")
    if setup.device.is_gpu:
        workers = 1  # one stream of large wavefronts; threads would only serialise on it
    return chunk_size, workers


def _empty_transport(setup: TraceSetup, first: FirstHit, stats: TraceStats) -> Transport:
    """Zero sums for the frame, on the tracing device."""
    xp, cam, k, j = setup.xp, setup.camera, setup.max_depth, setup.n_channels
    n_pix = cam.width * cam.height
    return Transport(
        width=cam.width, height=cam.height, max_depth=k, n_correlations=j,
        sample_count=xp.zeros(n_pix, np.int64),
        signal_sum=xp.zeros((k, n_pix)), correlation_sum=xp.zeros((k, j, n_pix)),
        ambient_sum=xp.zeros(n_pix), replicate_sum=xp.zeros((qmc.REPLICATES, j + 2, n_pix)),
        first_hit=first,
        transient_sum=xp.zeros((n_pix, setup.transient_bins)) if setup.transient_bins else None,
        transient_bin_m=setup.transient_bin_m, stats=stats)


def _checked_counts(counts, n_pix: int) -> np.ndarray:
    counts = np.asarray(backend.to_host(counts))
    if counts.shape != (n_pix,) or not np.issubdtype(counts.dtype, np.integer) or (counts < 0).any():
        raise ConfigError(f"trace: allocate must return ({n_pix},) non-negative integers, "
                          f"got shape {counts.shape} of {counts.dtype}")
    return counts.astype(np.int64)


def _checked_pass_size(n, scheduled: int) -> int:
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or not 0 <= n <= scheduled:
        raise ConfigError(f"trace: pass_size must return an integer in [0, {scheduled}], got {n!r}")
    return int(n)


def next_pass_size(done: int, spp: int, progressive: bool = True) -> int:
    """Samples per pixel of the pass after ``done`` of ``spp``: ``min(max(done, 1), 16)`` (progressive: the
    passes double, 1, 1, 2, 4, 8, 16, 16, …), else 16; never more than the ``spp − done`` left."""
    size = min(max(done, 1), _MAX_PASS) if progressive else _MAX_PASS
    return min(size, spp - done)


def pass_schedule(spp: int, progressive: bool = True) -> list[int]:
    """Samples per pass summing to ``spp``: 1, 1, 2, 4, 8, 16, 16, … (progressive), else 16, 16, ….

    Progressive passes give early frames and error estimates (previews, time budgets, target errors);
    without them a render needs no small passes, and on a GPU every pass costs the same kernel
    launches whatever its size. Depends on spp and ``progressive`` only (never on chunk size or
    device), so results are reproducible, and the first passes of a longer render equal a shorter
    render of the same kind.
    """
    passes, done = [], 0
    while done < spp:
        passes.append(next_pass_size(done, spp, progressive))
        done += passes[-1]
    return passes


_MAX_PASS = 16  # samples per pixel in the largest pass
