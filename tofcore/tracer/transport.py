"""Light transport: a wavefront path tracer that buckets light by bounce count and path length.

For every pixel and sample a camera ray leaves the lens; at every surface
vertex x_k the tracer connects to **every LED** with a shadow ray (next-event
estimation), then samples the BSDF for the next direction, until ``max_depth``
vertices or a miss (SPEC §1, thesis §5.1). Each LED connection is a
contribution with

* weight w (radiance at the lens, W m⁻² sr⁻¹, per unit LED intensity scale),
* optical path length L = |LED → x_k| + |x_k → x_{k-1}| + … + |x_1 → lens| (float64, metres),
* bounce count k (1 = direct reflection, ≥ 2 = multipath).

Per pixel and per k the tracer accumulates Σw and Σw·g_j(L/c) for the
correlation functions g_j of the caller's sensor model (DESIGN.md "path-length
bucketing"). Rays that leave the scene pick up ambient radiance, which is
unmodulated and summed apart from the LED signal.

Estimator, for a path with throughput β_k = Π f cosθ / p after k−1 sampled
bounces (thesis eq. 2.31 with eq. 2.8):

.. math:: w = \\beta_k \\, f(x_k, \\omega_o, \\omega_{LED}) \\, |\\cos\\theta_{x_k}| \\, I(\\theta_{LED}) / d^2

Sampling: every decision of a path (pixel and lens position, each bounce's lobe
and direction) takes its uniforms from Owen-scrambled Sobol' points, per pixel
and per pair of dimensions, in independent replicates (:mod:`tofcore.tracer.qmc`):
randomized quasi-Monte Carlo, unbiased, with an honest error estimate from the
spread of the replicates (:meth:`Transport.variance_of_mean`).

Determinism: the samples are functions of (seed, pixel, sample, dimension)
(:mod:`tofcore.tracer.rng`, :mod:`tofcore.tracer.qmc`); every chunk holds whole pixels and sums
them in sample order, so the result is the same bit for bit whatever the chunk size.
Memory is bounded by the chunk size (rays in flight), not by spp.
"""

from __future__ import annotations

import functools
import importlib
import pickle
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from .. import backend, limits
from ..backend import namespace, scatter_sum
from ..constants import SPEED_OF_LIGHT_M_S
from ..errors import Cancelled, ConfigError
from ..limits import usable_cpus
from ..scene.ambient import Ambient
from ..scene.bsdf import eval_bsdf, sample_bsdf
from ..scene.camera import Camera
from ..scene.led import LED, leds_at_pinhole
from ..scene.pose import rigid_problem
from ..scene.scene import Scene
from . import qmc, rng, workers
from .light_paths import bsdf_strategy_weight, connect, led_probabilities, trace_light_vertices
from .surface import MaterialTable, Surface, dot, leaving, point_offset, rotate, shadow_ray, spawn_offset, surface_at
from .workers import process_support

Correlation = Callable[[np.ndarray], np.ndarray]
"""g_j(τ): delay τ in seconds (float64 array) → correlation value per contribution (same shape)."""

COMPILED_TRACER = "tofcore.compiled"
"""The compiled per-path tracer. It stands above this module (it reuses the scene's, the tracer's and
the sensor's functions), so :func:`trace_progressive` imports it by name, as
:func:`tofcore.backend.twin` imports device kernels; it decides itself whether it can run a trace."""


@dataclass(frozen=True)
class CorrelationList:
    """Correlation functions g_j given one by one, evaluated as a bank: ``bank(tau)`` → (J, N).

    The tracer evaluates every channel of a contribution at once through a *bank*: a callable τ → (J, N)
    with ``len(bank) == J``. A sensor gives one (:meth:`tofcore.sensor.modulation.Modulation.correlation_bank`,
    one block per frequency); any other sequence of g_j(τ) is wrapped in this class.
    """

    functions: tuple[Correlation, ...]

    def __len__(self) -> int:
        return len(self.functions)

    def __call__(self, tau):
        return namespace(tau).stack([g_j(tau) for g_j in self.functions])

# Sample dimensions: each decision of a path owns one (a pair of uniforms, or one).
_DIM_PIXEL, _DIM_LENS = 0, 1  # 2-D: position in the pixel, on the lens


def _lobe_dim(vertex: int) -> int:
    """1-D: the lobe chosen at surface vertex ``vertex`` (1 = first hit)."""
    return 2 * vertex


def _direction_dim(vertex: int) -> int:
    """2-D: the direction sampled at surface vertex ``vertex``."""
    return 2 * vertex + 1


@dataclass(frozen=True)
class FirstHit:
    """Noise-free ground truth from one ray through each pixel centre (pinhole at the lens centre).

    Misses: NaN distances/positions/normals, ids −1.
    """

    distance_m: np.ndarray   # (H, W) float64, radial distance lens → surface
    position_m: np.ndarray   # (H, W, 3) float32, world frame
    normal: np.ndarray       # (H, W, 3) float32, world frame, facing the camera
    material_id: np.ndarray  # (H, W) int32
    object_id: np.ndarray    # (H, W) int32
    direction: np.ndarray    # (H, W, 3) float32, world-frame unit ray directions


@dataclass
class TraceStats:
    """Counters of one trace."""

    camera_rays: int = 0
    bounce_rays: int = 0
    shadow_rays: int = 0
    seconds: float = 0.0
    passes: int = 0
    light_rays: int = 0           # rays from the LEDs to their first hit (light vertices)
    skipped_shadow_rays: int = 0  # first-hit shadow rays known to be unoccluded (LED at a pinhole)
    camera_seconds: float = 0.0   # thread-seconds inside the BVH for each kind of ray
    bounce_seconds: float = 0.0
    shadow_seconds: float = 0.0
    chunk_seconds: float = 0.0    # thread-seconds inside chunks (all tracing work, summed over workers)
    setup_seconds: float = 0.0    # wall time before the first pass: first-hit buffers, sharing, worker start
    parallel: str = ""            # how chunks ran: "processes", "threads: <why>" or "one"
    tracer: str = "numpy"         # "compiled" (tofcore.compiled) or "numpy" (this module)
    tracer_reason: str = ""       # why the NumPy tracer ran where numba is installed, or is not

    @property
    def rays(self) -> int:
        return self.camera_rays + self.bounce_rays + self.shadow_rays + self.light_rays

    def add(self, other: TraceStats) -> None:
        """Add the ray counters and BVH times of a chunk (not ``seconds`` or ``passes``)."""
        for key in ("camera_rays", "bounce_rays", "shadow_rays", "light_rays", "skipped_shadow_rays",
                    "camera_seconds", "bounce_seconds", "shadow_seconds", "chunk_seconds"):
            setattr(self, key, getattr(self, key) + getattr(other, key))

    def as_dict(self) -> dict:
        return {"camera_rays": self.camera_rays, "bounce_rays": self.bounce_rays, "shadow_rays": self.shadow_rays,
                "light_rays": self.light_rays,
                "rays": self.rays, "seconds": self.seconds, "passes": self.passes,
                "skipped_shadow_rays": self.skipped_shadow_rays,
                "camera_seconds": self.camera_seconds, "bounce_seconds": self.bounce_seconds,
                "shadow_seconds": self.shadow_seconds, "chunk_seconds": self.chunk_seconds,
                "setup_seconds": self.setup_seconds, "parallel": self.parallel,
                "tracer": self.tracer, "tracer_reason": self.tracer_reason,
                "rays_per_second": self.rays / self.seconds if self.seconds > 0 else None}


@dataclass(eq=False)
class Transport:
    """Accumulated light transport of one frame; sums, with means and errors as methods.

    Sums are over samples; divide by ``sample_count`` (done by the accessors).
    Channels of the replicate sums: 0 = signal Σw, 1..J = correlations, J+1 = ambient; replicate r holds
    the samples i ≡ r (mod R) of each pixel (:mod:`tofcore.tracer.qmc`).
    """

    width: int
    height: int
    max_depth: int
    n_correlations: int
    sample_count: np.ndarray      # (P,) int64 samples per pixel, P = H·W
    signal_sum: np.ndarray        # (K, P) float64: Σ w per bounce bucket k = 1..K
    correlation_sum: np.ndarray   # (K, J, P) float64: Σ w·g_j(L/c)
    ambient_sum: np.ndarray       # (P,) float64: Σ ambient radiance (unmodulated)
    replicate_sum: np.ndarray     # (R, J+2, P) float64: Σ of the per-sample channel totals of replicate r
    first_hit: FirstHit
    transient_sum: np.ndarray | None = None  # (P, B) float64: Σ w per path-length bin
    transient_bin_m: float | None = None
    stats: TraceStats = field(default_factory=TraceStats)

    # ------------------------------------------------------------- accessors
    def _per_sample(self, sums: np.ndarray) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = sums / self.sample_count
        return mean.reshape(sums.shape[:-1] + (self.height, self.width))

    def signal(self, max_k: int | None = None) -> np.ndarray:
        """(H, W) mean LED radiance at the lens summed over bounces k ≤ ``max_k`` (all by default)."""
        return self._per_sample(self.signal_sum[: self._k(max_k)].sum(axis=0))

    def correlation(self, max_k: int | None = None) -> np.ndarray:
        """(J, H, W) mean Σ w·g_j summed over bounces k ≤ ``max_k`` (all by default): the partial sums of §6.3.1."""
        return self._per_sample(self.correlation_sum[: self._k(max_k)].sum(axis=0))

    def signal_per_bounce(self) -> np.ndarray:
        """(K, H, W) mean signal of each bounce bucket k = 1..K."""
        return self._per_sample(self.signal_sum)

    def correlation_per_bounce(self) -> np.ndarray:
        """(K, J, H, W) mean correlation sums of each bounce bucket."""
        return self._per_sample(self.correlation_sum)

    def ambient(self) -> np.ndarray:
        """(H, W) mean ambient (unmodulated) radiance at the lens."""
        return self._per_sample(self.ambient_sum)

    def transient(self) -> np.ndarray | None:
        """(H, W, B) mean radiance per path-length bin of width ``transient_bin_m`` (bin b centred at (b+½)·width)."""
        if self.transient_sum is None:
            return None
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = self.transient_sum / self.sample_count[:, None]
        return mean.reshape(self.height, self.width, -1)

    def replicate_means(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-replicate means (R, J+2, H, W) of the channels (signal, correlations…, ambient) and the
        (R, H, W) sample counts behind them; NaN where a replicate has no sample yet."""
        n = self.replicate_counts()
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = self.replicate_sum / n[:, None, :]
        return (mean.reshape(mean.shape[:2] + (self.height, self.width)),
                n.reshape(-1, self.height, self.width))

    def replicate_counts(self) -> np.ndarray:
        """(R, P) samples of each replicate per pixel: samples i < n with i ≡ r (mod R)."""
        xp = namespace(self.sample_count)
        r = xp.arange(qmc.REPLICATES)[:, None]
        return (self.sample_count[None, :] - r + qmc.REPLICATES - 1) // qmc.REPLICATES

    def variance_of_mean(self) -> np.ndarray:
        r"""(J+2, H, W) variance of the per-pixel mean of each channel (signal, correlations…, ambient).

        From the spread of the R independent replicates (:mod:`tofcore.tracer.qmc`): with replicate means
        m_r, :math:`\widehat{\mathrm{Var}}[\bar m] = \sum_r (m_r - \bar m_R)^2 / (R (R - 1))`, the
        replicates weighted equally (their counts differ by at most one sample); NaN until every
        replicate has a sample.
        """
        means, n = self.replicate_means()
        r = means.shape[0]
        with np.errstate(invalid="ignore"):
            centred = means - means.mean(axis=0)
            var = (centred**2).sum(axis=0) / (r * (r - 1))
        return np.where((n.min(axis=0) >= 1)[None], var, np.nan)

    def _k(self, max_k: int | None) -> int:
        if max_k is None:
            return self.max_depth
        if not 1 <= max_k <= self.max_depth:
            raise ConfigError(f"Transport: max_k must be in [1, {self.max_depth}], got {max_k!r}")
        return max_k


def pass_schedule(spp: int, progressive: bool = True) -> list[int]:
    """Samples per pass summing to ``spp``: 1, 1, 2, 4, 8, 16, 16, … (progressive), else 16, 16, ….

    Progressive passes give early frames and error estimates (previews, time budgets, target errors);
    without them a render needs no small passes, and on a GPU every pass costs the same kernel
    launches whatever its size. Depends on spp and ``progressive`` only (never on chunk size or
    device), so results are reproducible, and the first passes of a longer render equal a shorter
    render of the same kind.
    """
    if not progressive:
        return [min(_MAX_PASS, spp - done) for done in range(0, spp, _MAX_PASS)]
    passes, done, size = [], 0, 1
    while done < spp:
        n = min(size, spp - done)
        passes.append(n)
        done += n
        if len(passes) > 1:
            size = min(2 * size, _MAX_PASS)
    return passes


_MAX_PASS = 16  # samples per pixel in the largest pass


@dataclass(frozen=True)
class _Context:
    """Everything a chunk needs, fixed for the whole trace."""

    scene: Scene
    table: MaterialTable        # the scene's arrays on the tracing device
    camera: Camera
    device: backend.Device      # where the wavefront runs; xp = device.xp
    world_from_sensor: np.ndarray  # 4×4 host pose, world frame
    rotation: object            # (3, 3) world_from_sensor rotation, device array
    lens_center: object         # (3,) scene frame (world − scene.origin_m, where the tracer works), device array
    led_positions: object       # (L, 3) scene frame, device array
    led_axis: object            # (3,) optical axis (+z of the sensor), device array
    leds: tuple[LED, ...]
    skip_first_shadow: np.ndarray  # (L,) bool: LED at the centre of a pinhole lens
    correlations: Callable      # bank: delays τ (N,) in seconds → (J, N) channels g_j(τ)
    n_channels: int             # J correlation channels summed per pixel
    ambient: Ambient | None
    max_depth: int
    key: np.uint64
    sampler: str                # "sobol" or "independent" (tofcore.tracer.qmc.SAMPLERS)
    light_paths: bool           # connect camera vertices to light vertices (tofcore.tracer.light_paths)
    led_probability: np.ndarray  # (L,) host: probability of each LED emitting the light vertex
    transient_bins: int
    transient_bin_m: float | None


def trace(scene: Scene, camera: Camera, leds: Sequence[LED], **kwargs) -> Transport:
    """Trace a whole frame; see :func:`trace_progressive` for the parameters.

    Only the finished frame is wanted, so the passes are of 16 samples (``progressive=False``, fewer
    waits for the slowest chunk) unless ``progressive`` is given.
    """
    transport = None
    kwargs.setdefault("progressive", False)
    for transport in trace_progressive(scene, camera, leds, **kwargs):
        pass
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
                      allocate: Callable[[Transport, int], np.ndarray | None] | None = None) -> Iterator[Transport]:
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
        stay in cache); on the GPU as many as :func:`gpu_chunk_paths` allows in free device memory.
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
        e.g. :func:`tofcore.tracer.adaptive.allocate_samples`) or None for n everywhere. Each pixel's samples
        keep their indices 0, 1, 2, … whatever the allocation, so a pixel's estimate is the same
        function of its own samples as without it. ``spp`` then counts the mean over the pixels.
    device : ``"cpu"`` (NumPy), ``"gpu"`` (CuPy) or ``"auto", or a resolved :class:`tofcore.backend.Device`.
        On the GPU the accumulators of the yielded :class:`Transport` are CuPy arrays (``first_hit`` is
        always NumPy); the same seed gives the same sums within float rounding (``tests/tofcore/test_gpu.py``).

    The yielded object is the live accumulator: copy what you keep between passes.
    """
    dev = backend.select_device(device)
    xp = dev.xp
    ctx = _context(scene, camera, leds, world_from_sensor, correlations, ambient, max_depth, seed,
                   transient_bin_m, transient_max_m, dev, sampler, light_paths)
    if not isinstance(spp, (int, np.integer)) or spp < 1:
        raise ConfigError(f"trace: spp must be an integer >= 1, got {spp!r}")
    if chunk_size is None:
        chunk_size = gpu_chunk_paths(xp, ctx.n_channels) if dev.is_gpu else CPU_CHUNK_PATHS
    if not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1:
        raise ConfigError(f"trace: chunk_size must be an integer >= 1, got {chunk_size!r}")
    workers = usable_cpus() if workers is None else workers
    if not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ConfigError(f"trace: workers must be an integer >= 1, got {workers!r}")
    limits.MAX_WORKERS.check(int(workers), "trace", "workers")
    if dev.is_gpu:
        workers = 1  # one stream of large wavefronts; threads would only serialise on it
    start = time.perf_counter()
    n_pix = camera.width * camera.height
    n_corr = ctx.n_channels
    compiled = importlib.import_module(COMPILED_TRACER)
    tracer = compiled.choose(ctx)  # the compiled per-path tracer where numba and the render's features allow
    stats = TraceStats(tracer=tracer.tracer, tracer_reason=tracer.reason)
    # Start the worker processes first: they boot and import tofcore while this one traces the first hits.
    # The compiled tracer runs on numba's threads instead (they release the GIL).
    why_not = _start_workers(workers) if workers > 1 and not dev.is_gpu and tracer.packed is None else "one"
    transport = Transport(
        width=camera.width, height=camera.height, max_depth=max_depth, n_correlations=n_corr,
        sample_count=xp.zeros(n_pix, np.int64),
        signal_sum=xp.zeros((max_depth, n_pix)), correlation_sum=xp.zeros((max_depth, n_corr, n_pix)),
        ambient_sum=xp.zeros(n_pix), replicate_sum=xp.zeros((qmc.REPLICATES, n_corr + 2, n_pix)),
        first_hit=_first_hit(ctx, stats),
        transient_sum=xp.zeros((n_pix, ctx.transient_bins)) if ctx.transient_bins else None,
        transient_bin_m=ctx.transient_bin_m, stats=stats)
    done = np.zeros(n_pix, np.int64)  # host copy of transport.sample_count
    shared, why_not = (None, why_not) if why_not else _share(ctx, transport)
    stats.parallel = "processes" if shared is not None else "one" if why_not == "one" else f"threads: {why_not}"
    if tracer.packed is not None:
        stats.parallel = f"numba threads: {compiled.thread_count(workers)}"
    stats.setup_seconds = time.perf_counter() - start
    try:
        with ThreadPoolExecutor(max_workers=workers) as threads:
            for n_samples in pass_schedule(int(spp), progressive):
                counts = None if allocate is None else allocate(transport, n_samples)
                counts = np.full(n_pix, n_samples, np.int64) if counts is None else _checked_counts(counts, n_pix)
                chunks = _chunks(counts, _pass_chunk_paths(int(counts.sum()), chunk_size, workers))
                if tracer.packed is not None:
                    chunks = _chunks(counts, max(chunk_size, compiled.COMPILED_CHUNK_PATHS))
                    results = compiled.trace_pass(tracer, transport, done, counts, chunks, workers, cancel)
                elif shared is not None and len(chunks) > 1:
                    results = _run_in_processes(shared, workers, done, counts, chunks, cancel)
                else:
                    run = functools.partial(_trace_chunk, ctx, transport, first=xp.asarray(done),
                                            counts=xp.asarray(counts))

                    def job(chunk: tuple[int, int]) -> TraceStats | None:
                        return None if cancel is not None and cancel() else run(*chunk)

                    results = threads.map(job, chunks) if shared is None else map(job, chunks)
                finished = 0
                for chunk_stats in results:
                    if chunk_stats is None:
                        raise Cancelled("trace: cancelled")
                    stats.add(chunk_stats)
                    finished += 1
                if finished < len(chunks):
                    raise Cancelled("trace: cancelled")
                done += counts
                transport.sample_count += xp.asarray(counts)
                stats.passes += 1
                stats.seconds = time.perf_counter() - start
                yield transport
    finally:
        if shared is not None:
            _unshare(shared, transport)


_ACCUMULATORS = ("sample_count", "signal_sum", "correlation_sum", "ambient_sum", "replicate_sum", "transient_sum")


@dataclass
class _SharedTrace:
    """A render's context and accumulators in shared memory, and the per-pass sample plan the workers read."""

    shared: workers.Shared
    key: str
    first: np.ndarray   # (P,) samples each pixel had before this pass (shared view)
    counts: np.ndarray  # (P,) samples each pixel gets in this pass (shared view)


def _start_workers(n_workers: int) -> str:
    """Start (or reuse) the pool of ``n_workers`` processes; returns "" or why processes cannot run here
    (no interpreter to start them with, a daemonic parent, ``TOFCORE_PARALLEL=threads``)."""
    possible, why = process_support()
    if not possible:
        return why
    try:
        workers.pool(n_workers, warm_up=__name__)
    except Exception as exc:  # e.g. "daemonic processes are not allowed to have children", no fork/spawn here
        return f"worker processes could not start ({type(exc).__name__}: {exc})"
    return ""


def _share(ctx: _Context, transport: Transport) -> tuple[_SharedTrace | None, str]:
    """Put the context and the accumulators into shared memory; the transport then holds the shared views.

    Returns (None, why) where worker processes cannot run this trace: a correlation function that does
    not pickle (a lambda: use ``functools.partial`` of a module-level function, as
    :meth:`~tofcore.sensor.modulation.Modulation.correlations` does) or no room in /dev/shm.
    """
    n_pix = transport.width * transport.height
    first, counts = np.zeros(n_pix, np.int64), np.zeros(n_pix, np.int64)
    written = [getattr(transport, name) for name in _ACCUMULATORS if getattr(transport, name) is not None]
    try:
        shared = workers.Shared((ctx, transport, first, counts), always=written + [first, counts])
    except (pickle.PicklingError, TypeError, AttributeError) as exc:
        return None, f"the trace context does not pickle for worker processes ({exc})"
    except OSError as exc:  # no room in /dev/shm
        return None, f"no shared memory for worker processes ({exc})"
    for name in _ACCUMULATORS:
        if getattr(transport, name) is not None:
            setattr(transport, name, shared.view(getattr(transport, name)))
    return _SharedTrace(shared, uuid.uuid4().hex, shared.view(first), shared.view(counts)), ""


def _unshare(run: _SharedTrace, transport: Transport) -> None:
    """Give the transport private copies of its sums and release the shared memory."""
    for name in _ACCUMULATORS:
        if getattr(transport, name) is not None:
            setattr(transport, name, np.array(getattr(transport, name)))
    run.shared.close()


def _run_in_processes(run: _SharedTrace, n: int, done: np.ndarray, counts: np.ndarray, chunks, cancel):
    """Trace one pass's chunks on the worker processes; yields each chunk's TraceStats."""
    run.first[:] = done
    run.counts[:] = counts
    return workers.run(n, run.shared, run.key, _trace_shared_chunk, chunks, cancel)


def _trace_shared_chunk(shared_objects, p0: int, p1: int) -> TraceStats:
    """In a worker process: trace pixels [p0, p1) of the pass described in the shared memory."""
    ctx, out, first, counts = shared_objects
    return _trace_chunk(ctx, out, p0, p1, first=first, counts=counts)


def _checked_counts(counts, n_pix: int) -> np.ndarray:
    counts = np.asarray(backend.to_host(counts))
    if counts.shape != (n_pix,) or not np.issubdtype(counts.dtype, np.integer) or (counts < 0).any():
        raise ConfigError(f"trace: allocate must return ({n_pix},) non-negative integers, "
                          f"got shape {counts.shape} of {counts.dtype}")
    return counts.astype(np.int64)


MIN_CHUNK_PATHS = 1 << 13
"""Paths per chunk at least, when a pass is split finer to keep every worker busy (NumPy's per-call
overhead grows below a few thousand elements)."""


def _pass_chunk_paths(pass_paths: int, chunk_size: int, workers: int) -> int:
    """Paths per chunk for a pass: ``chunk_size``, or less so that the pass has ≥ 4 chunks per worker.

    A 1-spp pass of a 512 × 424 frame is 217 k paths: 4 chunks of 65 k would leave 12 of 16 workers idle.
    The frame does not depend on the split (chunks hold whole pixels).
    """
    if workers == 1:
        return chunk_size
    return max(min(chunk_size, MIN_CHUNK_PATHS), min(chunk_size, -(-pass_paths // (4 * workers))))


def _chunks(counts: np.ndarray, chunk_size: int) -> list[tuple[int, int]]:
    """Pixel ranges [p0, p1) of about ``chunk_size`` paths each (whole pixels; at least one pixel)."""
    ends = np.cumsum(counts)
    chunks, p0 = [], 0
    while p0 < len(counts):
        before = ends[p0 - 1] if p0 else 0
        p1 = max(p0 + 1, int(np.searchsorted(ends, before + chunk_size, side="right")))
        chunks.append((p0, min(p1, len(counts))))
        p0 = p1
    return chunks


def _context(scene, camera, leds, world_from_sensor, correlations, ambient, max_depth, seed,
             transient_bin_m, transient_max_m, device: backend.Device, sampler: str = "sobol",
             light_paths: bool = True) -> _Context:
    if not isinstance(scene, Scene):
        raise ConfigError(f"trace: scene must be a tofcore.Scene, got {type(scene).__name__}")
    if not isinstance(camera, Camera):
        raise ConfigError(f"trace: camera must be a tofcore.Camera, got {type(camera).__name__}")
    leds = tuple(leds)
    if not leds or not all(isinstance(x, LED) for x in leds):
        raise ConfigError(f"trace: leds must be a non-empty sequence of tofcore.LED, got {leds!r}")
    if sampler not in qmc.SAMPLERS:
        raise ConfigError(f"trace: sampler must be one of {list(qmc.SAMPLERS)}, got {sampler!r}")
    if not isinstance(max_depth, (int, np.integer)) or max_depth < 1:
        raise ConfigError(f"trace: max_depth must be an integer >= 1, got {max_depth!r}")
    pose = np.eye(4) if world_from_sensor is None else np.asarray(world_from_sensor, dtype=np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise ConfigError(f"trace: world_from_sensor must be a finite 4x4 matrix, got shape {pose.shape}")
    rot = pose[:3, :3]
    problem = rigid_problem(pose)
    if problem is not None:
        raise ConfigError(f"trace: world_from_sensor must be a rigid transform (rotation + translation): {problem}")
    if not callable(correlations):
        correlations = CorrelationList(tuple(correlations))
        for j, g in enumerate(correlations.functions):
            if not callable(g):
                raise ConfigError(f"trace: correlations[{j}] must be callable g(tau_s), got {type(g).__name__}")
    elif not hasattr(correlations, "__len__"):
        raise ConfigError(f"trace: a correlation bank must have len() (its channel count), "
                          f"got {type(correlations).__name__}")
    bins = 0
    if transient_bin_m is not None:
        if not transient_bin_m > 0 or not transient_max_m or not transient_max_m > transient_bin_m:
            raise ConfigError(f"trace: transient_bin_m must be > 0 and transient_max_m > transient_bin_m, "
                              f"got {transient_bin_m!r} and {transient_max_m!r}")
        bins = int(np.ceil(transient_max_m / transient_bin_m))
    positions = np.array([x.position_m for x in leds])
    lens_scene = pose[:3, 3] - np.asarray(scene.origin_m)  # the tracer works in the scene frame
    led_scene = positions @ rot.T + lens_scene
    xp = device.xp
    return _Context(
        scene=scene, table=MaterialTable(scene, xp), camera=camera, device=device, world_from_sensor=pose,
        rotation=xp.asarray(rot), lens_center=xp.asarray(lens_scene),
        led_positions=xp.asarray(led_scene), led_axis=xp.asarray(rot[:, 2]), leds=leds,
        skip_first_shadow=leds_at_pinhole(camera, leds),
        correlations=correlations, n_channels=len(correlations),
        ambient=None if ambient is None or ambient.is_black else ambient,
        max_depth=int(max_depth), key=rng.seed_key(seed), sampler=sampler,
        light_paths=bool(light_paths) and max_depth >= 2 and led_probabilities(leds).sum() > 0,
        led_probability=led_probabilities(leds),
        transient_bins=bins, transient_bin_m=transient_bin_m)


CPU_CHUNK_PATHS = 1 << 16
"""Paths per chunk on the CPU: the per-bounce temporaries of 65,536 paths stay in L2/L3."""

GPU_BYTES_PER_PATH = 2048
"""Peak device memory per path in flight (all path state and per-bounce temporaries, 12 correlation
channels), measured with CuPy's memory pool on the GPU benchmark frame (docs/benchmarks.md)."""

GPU_MEMORY_FRACTION = 0.5
"""Share of the free device memory one chunk may take (the rest: CuPy's pool slack, other processes)."""

GPU_MAX_CHUNK_PATHS = 1 << 23
"""At most 8.4 M paths per chunk: a whole 512 × 424 × 16 spp pass fits; more adds nothing but memory."""


def gpu_chunk_paths(xp, n_correlations: int) -> int:
    """Paths per chunk on the GPU: as many as fit in ``GPU_MEMORY_FRACTION`` of the free device memory.

    Memory per path grows with the correlation channels (8 bytes each, per-path totals and per-bounce
    sums); ``GPU_BYTES_PER_PATH`` holds 12. The chunk never drops below ``CPU_CHUNK_PATHS``, so a
    nearly full GPU fails with a clear out-of-memory error rather than crawling.
    """
    free = backend.free_device_bytes(xp) or 0
    per_path = GPU_BYTES_PER_PATH + 24 * max(0, n_correlations - 12)
    return int(min(GPU_MAX_CHUNK_PATHS, max(CPU_CHUNK_PATHS, free * GPU_MEMORY_FRACTION // per_path)))


def _first_hit(ctx: _Context, stats: TraceStats) -> FirstHit:
    """Trace the pixel-centre rays on the tracing device; the buffers come back as NumPy arrays."""
    xp = ctx.device.xp
    cam = ctx.camera
    d = rotate(xp.asarray(cam.pixel_center_directions().reshape(-1, 3).astype(np.float64)), ctx.rotation)
    n = len(d)
    origin = xp.broadcast_to(ctx.lens_center, (n, 3))
    hits = ctx.scene.bvh.intersect(leaving(origin, d), d.astype(np.float32))
    stats.camera_rays += n
    hit = hits.prim >= 0
    distance = xp.full(n, np.nan)
    position = xp.full((n, 3), np.nan, np.float32)
    normal = xp.full((n, 3), np.nan, np.float32)
    material = xp.full(n, -1, np.int32)
    obj = xp.full(n, -1, np.int32)
    if hit.any():
        surf = surface_at(ctx.scene, ctx.table, hits.prim[hit], hits.u[hit], hits.v[hit], origin[hit], d[hit])
        distance[hit] = xp.linalg.norm(surf.position - ctx.lens_center, axis=1)
        position[hit] = surf.position + xp.asarray(ctx.scene.origin_m)  # world frame
        normal[hit] = surf.geometric_normal
        material[hit] = ctx.table.material_ids[hits.prim[hit]]
        obj[hit] = ctx.table.object_ids[hits.prim[hit]]
    shape = (cam.height, cam.width)
    host = backend.to_host
    return FirstHit(distance_m=host(distance).reshape(shape), position_m=host(position).reshape(shape + (3,)),
                    normal=host(normal).reshape(shape + (3,)), material_id=host(material).reshape(shape),
                    object_id=host(obj).reshape(shape), direction=host(d).astype(np.float32).reshape(shape + (3,)))


def _trace_chunk(ctx: _Context, out: Transport, p0: int, p1: int, *, first, counts) -> TraceStats:
    """Trace samples [first[p], first[p] + counts[p]) of every pixel p in [p0, p1) into ``out``.

    Writes only the pixels [p0, p1) of ``out``, so chunks can run in parallel threads or worker processes.
    Returns the chunk's ray counters.
    """
    chunk_start = time.perf_counter()
    n_pix = p1 - p0
    n_corr = ctx.n_channels
    xp = ctx.device.xp
    stats = TraceStats()
    # Path state, one entry per live path (compacted after every bounce):
    n_paths = int(counts[p0:p1].sum())
    slot = xp.arange(n_paths)                                   # index of the path within the chunk
    local_pixel = xp.repeat(xp.arange(n_pix), counts[p0:p1])    # pixel within the chunk; paths ordered (pixel, sample)
    pixel = p0 + local_pixel                                    # flat pixel index in the frame
    rank = slot - (xp.cumsum(counts[p0:p1]) - counts[p0:p1])[local_pixel]
    sample = first[p0:p1][local_pixel] + rank                   # sample index of the pixel
    slot_pixel, slot_replicate = local_pixel, sample % qmc.REPLICATES  # per slot, for the replicate sums
    throughput = xp.ones(len(slot))                             # β: Π f cosθ / pdf so far
    path_length = xp.zeros(len(slot))                           # metres travelled from the lens, float64
    prev_prim = xp.full(len(slot), -1, np.int32)                # triangle the ray leaves (never hit again)
    prev_pdf = xp.zeros(len(slot))                              # solid-angle pdf of the bounce that led here
    prev_delta = xp.zeros(len(slot), dtype=bool)                # ... and whether it was a mirror (delta) lobe
    # Per-path totals over all bounces, for the replicate sums: signal, correlations..., ambient.
    path_total = xp.zeros((n_corr + 2, len(slot)))
    light = trace_light_vertices(ctx, stats, pixel, sample) if ctx.light_paths else None  # indexed by slot

    cam = ctx.camera
    rot = ctx.rotation
    pixel_u, pixel_v = qmc.sample_2d(ctx.key, pixel, sample, _DIM_PIXEL, ctx.sampler)
    lens_u, lens_v = qmc.sample_2d(ctx.key, pixel, sample, _DIM_LENS, ctx.sampler)
    o_s, d_s = cam.generate_rays(pixel, pixel_u, pixel_v, lens_u, lens_v)
    origin = rotate(o_s, rot) + ctx.lens_center                 # ray origins, scene frame (off the surface after bounce 1)
    direction = rotate(d_s, rot)                                # unit ray directions
    prev_point = origin                                         # true position of the previous vertex (lens point first)

    for depth in range(1, ctx.max_depth + 1):
        clock = time.perf_counter()
        query = leaving(origin, direction) if depth == 1 else origin.astype(np.float32)
        hits = ctx.scene.bvh.intersect(query, direction.astype(np.float32), ignore_prim=prev_prim, workers=1)
        if depth == 1:
            stats.camera_rays += len(slot)
            stats.camera_seconds += time.perf_counter() - clock
        else:
            stats.bounce_rays += len(slot)
            stats.bounce_seconds += time.perf_counter() - clock
        hit = hits.prim >= 0
        if ctx.ambient is not None and not hit.all():
            miss = ~hit
            path_total[-1, slot[miss]] += throughput[miss] * ctx.ambient.radiance(direction[miss])
        # Compact: keep the paths that hit a surface.
        keep = np.flatnonzero(hit)
        slot, local_pixel, pixel, sample = slot[keep], local_pixel[keep], pixel[keep], sample[keep]
        throughput, path_length = throughput[keep], path_length[keep]
        prev_pdf, prev_delta = prev_pdf[keep], prev_delta[keep]
        origin, direction, prev_point, prim = origin[keep], direction[keep], prev_point[keep], hits.prim[keep]
        if len(slot) == 0:
            break
        surf = surface_at(ctx.scene, ctx.table, prim, hits.u[keep], hits.v[keep], origin, direction)
        segment = np.linalg.norm(surf.position - prev_point, axis=1)
        path_length = path_length + segment
        wo = surf.to_local(-direction)
        corners = ctx.table.vertices[ctx.table.triangles[prim]]      # (N, 3, 3) the hit triangles, for the offset
        offset = spawn_offset(surf.position, surf.geometric_normal, corners)
        spawn = surf.position + surf.geometric_normal * offset[:, None]
        # Area density at this vertex of having sampled it from the previous one (MIS with light vertices).
        bsdf_area_pdf = (prev_pdf * dot(-direction, surf.geometric_normal) / segment**2
                         if ctx.light_paths and depth >= 2 else None)

        # Next-event estimation to every LED, summed per path in LED order.
        w_sum = xp.zeros(len(slot))
        wg_sum = xp.zeros((n_corr, len(slot)))
        for i, led in enumerate(ctx.leds):
            w, led_distance = _connect_led(ctx, stats, surf, spawn, wo, prim, throughput, i, led, depth,
                                           bsdf_area_pdf, prev_delta)
            total_length = path_length + led_distance
            if ctx.transient_bins:
                _add_transient(ctx, out, p0, p1, local_pixel, w, total_length)
            w_sum += w
            if n_corr:
                wg = ctx.correlations(total_length / SPEED_OF_LIGHT_M_S)
                wg *= w
                wg_sum += wg
        _accumulate(ctx, out, p0, p1, depth - 1, local_pixel, slot, w_sum, wg_sum, path_total)

        if depth == ctx.max_depth:
            break
        if light is not None:  # this vertex → the sample's light vertex → its LED: depth + 1 surface vertices
            w, extra = connect(ctx, stats, light, slot, surf, spawn, wo, prim, throughput)
            total_length = path_length + extra
            if ctx.transient_bins:
                _add_transient(ctx, out, p0, p1, local_pixel, w, total_length)
            wg = None
            if n_corr:
                wg = ctx.correlations(total_length / SPEED_OF_LIGHT_M_S)
                wg *= w
            _accumulate(ctx, out, p0, p1, depth, local_pixel, slot, w, wg, path_total)
        # Sample the BSDF for the next direction.
        u1, u2 = qmc.sample_2d(ctx.key, pixel, sample, _direction_dim(depth), ctx.sampler)
        u_lobe = qmc.sample_1d(ctx.key, pixel, sample, _lobe_dim(depth), ctx.sampler)
        bs = sample_bsdf(surf.params, wo, u_lobe, u1, u2)
        new_dir = surf.to_world(bs.wi)
        # A direction below the geometric surface would leak through it (shading normals): end the path.
        alive = (bs.weight > 0) & (dot(new_dir, surf.geometric_normal) > 0)
        keep = np.flatnonzero(alive)
        slot, local_pixel, pixel, sample = slot[keep], local_pixel[keep], pixel[keep], sample[keep]
        throughput = throughput[keep] * bs.weight[keep]
        prev_pdf, prev_delta = bs.pdf[keep], bs.is_delta[keep]
        path_length, prev_prim = path_length[keep], prim[keep]
        prev_point, origin = surf.position[keep], spawn[keep]
        direction = new_dir[keep] / np.linalg.norm(new_dir[keep], axis=1, keepdims=True)
        if len(slot) == 0:
            break

    n_ch, n_rep = n_corr + 2, qmc.REPLICATES
    bins = ((slot_replicate * n_ch)[None, :] * n_pix + xp.arange(n_ch)[:, None] * n_pix + slot_pixel).ravel()
    out.replicate_sum[:, :, p0:p1] += scatter_sum(bins, path_total.ravel(),
                                                  n_rep * n_ch * n_pix).reshape(n_rep, n_ch, n_pix)
    if ctx.ambient is not None:
        out.ambient_sum[p0:p1] += scatter_sum(slot_pixel, path_total[-1], n_pix)
    stats.chunk_seconds = time.perf_counter() - chunk_start
    return stats


def _accumulate(ctx: _Context, out: Transport, p0: int, p1: int, k: int, local_pixel, slot, w, wg,
                path_total) -> None:
    """Add contributions (weights w, correlation products wg (J, N)) of bounce bucket k + 1 to the pixels
    and to the paths' totals."""
    n_pix, n_corr = p1 - p0, ctx.n_channels
    out.signal_sum[k, p0:p1] += scatter_sum(local_pixel, w, n_pix)
    path_total[0, slot] += w
    if n_corr:  # all channels in one scatter: channel c of pixel p goes to bin c·n_pix + p
        bins = (namespace(w).arange(n_corr)[:, None] * n_pix + local_pixel).ravel()
        out.correlation_sum[k, :, p0:p1] += scatter_sum(bins, wg.ravel(), n_corr * n_pix).reshape(n_corr, n_pix)
        path_total[1:n_corr + 1, slot] += wg


def _connect_led(ctx: _Context, stats: TraceStats, surf: Surface, spawn: np.ndarray, wo: np.ndarray,
                 prim: np.ndarray, throughput: np.ndarray, i: int, led: LED, depth: int,
                 bsdf_area_pdf=None, prev_delta=None) -> tuple[np.ndarray, np.ndarray]:
    """Next-event estimate to LED ``i``: (weight w per path, distance hit point → LED).

    With ``bsdf_area_pdf`` (light vertices on), w carries strategy A's MIS weight
    (:func:`tofcore.tracer.light_paths.bsdf_strategy_weight`)."""
    to_led = ctx.led_positions[i] - surf.position
    dist = np.linalg.norm(to_led, axis=1)
    wi_world = to_led / dist[:, None]
    cos_geo = dot(wi_world, surf.geometric_normal)
    cos_shading = dot(wi_world, surf.shading_normal)
    cos_axis = -dot(wi_world, ctx.led_axis[None, :])
    intensity = led.intensity(cos_axis)
    f = eval_bsdf(surf.params, wo, surf.to_local(wi_world))
    w = throughput * f * np.maximum(cos_shading, 0.0) * intensity / dist**2
    w = np.where(cos_geo > 0, w, 0.0)
    if bsdf_area_pdf is not None:
        w = w * bsdf_strategy_weight(bsdf_area_pdf, prev_delta, led, float(ctx.led_probability[i]),
                                     cos_axis, cos_geo, dist)
    test = np.flatnonzero(w > 0)
    if depth == 1 and ctx.skip_first_shadow[i]:
        stats.skipped_shadow_rays += len(test)
    elif len(test):
        clock = time.perf_counter()
        margin = point_offset(ctx.led_positions[i][None])  # stop short of the LED (flush with a wall)
        blocked = ctx.scene.bvh.occluded(*shadow_ray(spawn[test], ctx.led_positions[i], margin),
                                         ignore_prim=prim[test], workers=1)
        stats.shadow_rays += len(test)
        stats.shadow_seconds += time.perf_counter() - clock
        w[test[blocked]] = 0.0
    return w, dist


def _add_transient(ctx: _Context, out: Transport, p0: int, p1: int, local_pixel: np.ndarray, w: np.ndarray,
                   length: np.ndarray) -> None:
    """Add weights to the path-length histogram, split linearly between the two nearest bin centres.

    The split keeps Σw and Σw·L of every contribution inside the range (moment-preserving, DESIGN.md).
    """
    nb = ctx.transient_bins
    x = length / ctx.transient_bin_m - 0.5
    b0 = np.floor(x)
    frac = x - b0
    b0 = b0.astype(np.int64)
    n = (p1 - p0) * nb
    hist = namespace(w).zeros(n)
    for b, wt in ((b0, w * (1.0 - frac)), (b0 + 1, w * frac)):
        ok = (b >= 0) & (b < nb) & (wt != 0)
        hist += scatter_sum(local_pixel[ok] * nb + b[ok], wt[ok], n)
    out.transient_sum[p0:p1] += hist.reshape(p1 - p0, nb)
