"""Tracing a frame: :func:`trace` and :func:`trace_progressive`, passes of samples over the whole frame.

A trace checks its settings into a :class:`~tofcore.tracer.setup.TraceSetup`, has its :class:`Tracer` chosen
(the NumPy reference, :func:`~tofcore.tracer.parallel.reference`, unless the caller hands in another choice, as
:func:`tofcore.trace` and :func:`tofcore.render` hand in :func:`tofcore.compiled.tracer.choose`), traces the
noise-free first hits (:func:`~tofcore.tracer.stages.first_hit`), then runs passes of samples and yields the
accumulated :class:`~tofcore.tracer.transport.Transport` after every pass.

This module alone decides the passes (:class:`PassSchedule`): how many samples each pass gets
(:func:`pass_schedule`, cut to a time budget by :class:`~tofcore.tracer.budget.TimeBudget`), which pixels get
them (:func:`~tofcore.tracer.estimator.allocate_samples`) and when the trace ends (``spp``, the budget, a
target error), from the caller's :class:`PassPolicy` and what the caller reports after each pass
(:class:`PassReport`: the error of each pixel of its output, which the tracer cannot compute, since it never
sees the sensor model).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from .. import backend, limits
from ..errors import ConfigError
from ..limits import usable_cpus
from ..scene.ambient import Ambient
from ..scene.camera import Camera
from ..scene.led import LED
from ..scene.scene import Scene
from . import parallel, qmc
from .budget import TimeBudget
from .estimator import allocate_samples, rms_error
from .parallel import Execution, reference
from .setup import Correlation, TraceSettings, TraceSetup, make_setup
from .transport import FirstHit, TraceStats, Transport


class Tracer(Protocol):
    """What runs the passes of one trace; the pass loop (:func:`trace_progressive`) calls its methods in order.

    :class:`~tofcore.tracer.parallel.ReferenceTracer` (NumPy, the frame's definition) and
    :class:`tofcore.compiled.tracer.CompiledTracer` implement it, and :class:`~tofcore.tracer.parallel.HostTracer`
    runs either on the CPU for a GPU render the wavefront cannot trace. A *tracer choice* (:data:`TracerChoice`) makes one for a
    trace's checked set-up and :class:`~tofcore.tracer.parallel.Execution`.
    """

    name: str    # "numpy" or "compiled": TraceStats.tracer
    reason: str  # why the NumPy reference runs where the choice would rather not ("" otherwise)

    def start(self, stats: TraceStats) -> None:
        """Before the first hits: start what runs meanwhile (worker processes, a kernel compile)."""

    def first_hit(self, setup: TraceSetup, stats: TraceStats) -> FirstHit:
        """The noise-free ground truth: one ray through each pixel centre (:func:`~tofcore.tracer.stages.first_hit`
        defines it)."""

    def attach(self, transport: Transport) -> str:
        """The frame's sums exist, the passes add to them; returns how the chunks run (TraceStats.parallel)."""

    def run(self, done: np.ndarray, counts: np.ndarray) -> None:
        """One pass: samples [done[p], done[p] + counts[p]) of every pixel p; raises Cancelled when asked to."""

    def close(self) -> None:
        """The trace has ended, however: release what :meth:`start` and :meth:`attach` took."""


TracerChoice = Callable[[TraceSetup, Execution], Tracer]
"""Picks the tracer for a trace: (set-up, execution) → :class:`Tracer`, called once per trace."""


@dataclass(frozen=True)
class PassPolicy:
    """How a trace spends its samples: how many, in which passes, on which pixels, and when it may stop early.

    Parameters
    ----------
    spp : most samples per pixel (the mean over the pixels where ``adaptive``).
    progressive : passes of 1, 1, 2, 4, … samples (True) or of 16 (False), :func:`pass_schedule`. A time
        budget or a target error always gets progressive passes: they act on measurements of early passes.
    time_budget_s : seconds from the trace's start to the caller's final result: each pass is sized from the
        measured cost of the passes before it so that the budget is used (:mod:`tofcore.tracer.budget`),
        up to ``spp``. Not reproducible across machines.
    target_error_m : stop once the RMS of the reported error (:class:`PassReport`) over the pixels that see a
        surface is at most this, leaving out those the report counts apart (a render's unwrap flips: the
        number its convergence log and summary print).
    adaptive : after a uniform pilot of 16 samples per pixel, give each pass's samples to the pixels whose
        reported error is largest (:func:`~tofcore.tracer.estimator.allocate_samples`).
    """

    spp: int = 16
    progressive: bool = True
    time_budget_s: float | None = None
    target_error_m: float | None = None
    adaptive: bool = False

    def __post_init__(self):
        if not isinstance(self.spp, (int, np.integer)) or self.spp < 1:
            raise ConfigError(f"trace: spp must be an integer >= 1, got {self.spp!r}")
        for name in ("progressive", "adaptive"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ConfigError(f"trace: {name} must be True or False, got {getattr(self, name)!r}")
        for name in ("time_budget_s", "target_error_m"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0):
                raise ConfigError(f"trace: {name} must be a number > 0, got {value!r}")


@dataclass(frozen=True)
class PassReport:
    """What the caller measured after a pass (:meth:`Passes.report`): the error a target and the adaptive
    allocation act on, and what the caller's own work per pass costs the time budget."""

    error_m: np.ndarray            # (H, W) standard error of each pixel's output (m), NaN where not known yet
    estimate_s: float = 0.0        # seconds that estimate took (the final frame needs a few of them)
    frame_s: float | None = None   # seconds the caller's latest frame took to build; None before the first
    apart: np.ndarray | None = None  # (H, W) bool: pixels whose error the caller reports apart (unwrap flips):
    #                                  the target's RMS leaves them out, as the reported error does; the adaptive
    #                                  allocation still reads their error


def trace(scene: Scene, camera: Camera, leds: Sequence[LED], **kwargs) -> Transport:
    """Trace a whole frame; see :func:`trace_progressive` for the parameters.

    Only the finished frame is wanted, so the passes are of 16 samples (``progressive=False``, fewer
    waits for the slowest chunk) unless ``progressive`` or a ``policy`` is given.
    """
    transport = None
    if kwargs.get("policy") is None:
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
                      spp: int | None = None, max_depth: int = 5, seed: int = 0,
                      chunk_size: int | None = None, workers: int | None = None,
                      transient_bin_m: float | None = None, transient_max_m: float | None = None,
                      cancel: Callable[[], bool] | None = None,
                      device: str | backend.Device = "cpu", progressive: bool | None = None,
                      sampler: str = "sobol", light_paths: bool = True, policy: PassPolicy | None = None,
                      allocate: Callable[[Transport, int], np.ndarray | None] | None = None,
                      pass_size: Callable[[Transport, int], int] | None = None,
                      activity: Callable[[dict], None] | None = None,
                      tracer: TracerChoice = reference) -> Passes:
    """Trace in progressive passes, yielding the accumulated :class:`Transport` after each.

    Parameters
    ----------
    scene, camera, leds : what to render; LED positions are in the sensor frame.
    world_from_sensor : 4×4 pose (sensor frame = OpenCV: x right, y down, z forward); identity by default.
    correlations : g_j(τ), τ in seconds, one per sensor bucket/phase image; or a bank τ → (J, N) of them
        all with ``len`` J (:meth:`tofcore.sensor.modulation.Modulation.correlation_bank`, faster).
    ambient : background radiance; ``None`` or black skips all ambient work.
    spp : samples per pixel in total (default 16); max_depth : surface vertices per path (1 = direct only).
    seed : non-negative int; the same seed gives the same frame for any ``chunk_size``.
    chunk_size : paths in flight per chunk of the CPU's tracers; bounds memory. Default: 65,536 (temporaries
        stay in cache). The GPU's wavefront traces a pass at once, in groups sized by its free memory.
    workers : processes tracing chunks at once on the CPU (default: the usable CPUs, affinity and cgroup
        quota respected, :func:`tofcore.limits.usable_cpus`; the GPU's wavefront ignores it). They share the scene,
        BVH and accumulators (:mod:`tofcore.tracer.workers`); passes too small to be worth it (fewer than
        two chunks) run in this process. Where no worker process can be started (a Blender without its
        Python interpreter) the chunks run on threads instead, and ``stats.parallel`` says which.
        Chunks own disjoint pixels, so the result does not depend on it.
    transient_bin_m, transient_max_m : optional histogram of w over path length (bin width, range), metres.
    cancel : polled before every chunk; when it returns True, :class:`~tofcore.errors.Cancelled` is raised.
    progressive : passes of 1, 1, 2, 4, … samples (True, default) or of 16 (False); see :func:`pass_schedule`.
    sampler : ``"sobol"`` (randomized QMC, :mod:`tofcore.tracer.qmc`) or ``"independent"`` (plain uniforms, for
        comparisons). Both are unbiased and keep the R replicates of the error estimate.
    light_paths : connect every camera vertex to one light vertex per sample (an LED's first hit), both
        strategies weighted by multiple importance sampling (:mod:`tofcore.tracer.light_paths`). Unbiased
        either way; it removes the fireflies of surfaces close to an LED. Needs ``max_depth`` ≥ 2.
    policy : the whole :class:`PassPolicy` (time budget, target error, adaptive allocation) instead of
        ``spp`` and ``progressive``; its budget, target and allocation act on what :meth:`Passes.report`
        is told after each pass (``tofcore.render`` tells it the depth error of its frame).
    allocate : the caller's own allocation, instead of the policy's: called before every pass with the
        accumulated transport and the pass's mean samples per pixel n; returns (P,) int samples per pixel for
        this pass (summing to about n·P, e.g. :func:`tofcore.tracer.estimator.allocate_samples`) or None for n
        everywhere. Each pixel's samples keep their indices 0, 1, 2, … whatever the allocation, so a pixel's
        estimate is the same function of its own samples as without it. ``spp`` then counts the mean.
    pass_size : the caller's own cut of each pass: called before every pass with the accumulated transport and
        the pass's scheduled samples per pixel n; returns the pass's samples per pixel, 0..n (0 ends the
        trace). The samples stay the same whatever the sizes, only the passes they fall into change.
    device : ``"cpu"`` (NumPy), ``"gpu"`` (CuPy) or ``"auto", or a resolved :class:`tofcore.backend.Device`.
        On the GPU the accumulators of the yielded :class:`Transport` are CuPy arrays (``first_hit`` is
        always NumPy); the same seed gives the same sums within float rounding (``tests/tofcore/test_gpu.py``).
        The GPU traces paths with the compiled wavefront only; the reference (and the compiled tracer where
        numba-cuda is missing) traces a GPU render's paths on the CPU (:class:`~.parallel.HostTracer`).
    activity : told, in the tracing thread, what a pass does before it ends (:class:`PassActivity`):
        ``{"stage": "compile", "seconds": s}`` about twice a second while the compiled tracer's kernels
        compile (once per install), and ``{"stage": "trace", "pass": n, "spp": s, "spp_max": m}`` after every
        block of pixels (chunk) of a CPU pass, ``s`` the mean samples per pixel traced so far.
    tracer : picks the :class:`Tracer` that runs the passes (:data:`TracerChoice`): the NumPy reference here;
        :func:`tofcore.trace_progressive` passes :func:`tofcore.compiled.tracer.choose`, the compiled tracer
        wherever it can run the trace.

    Returns
    -------
    Passes
        Iterate it; the yielded object is the live accumulator, so copy what you keep between passes.
    """
    settings = TraceSettings(
        world_from_sensor=world_from_sensor, correlations=correlations, ambient=ambient, max_depth=max_depth,
        seed=seed, chunk_size=chunk_size, workers=workers, transient_bin_m=transient_bin_m,
        transient_max_m=transient_max_m, cancel=cancel, device=device, sampler=sampler, light_paths=light_paths,
        activity=activity)
    schedule = PassSchedule(_policy(policy, spp, progressive), allocate=allocate, pass_size=pass_size)
    return Passes(_passes(scene, camera, leds, settings, schedule, tracer), schedule)


def _policy(policy: PassPolicy | None, spp: int | None, progressive: bool | None) -> PassPolicy:
    """The policy given, or the one that ``spp`` and ``progressive`` stand for."""
    if policy is None:
        return PassPolicy(spp=16 if spp is None else spp, progressive=True if progressive is None else progressive)
    if not isinstance(policy, PassPolicy):
        raise ConfigError(f"trace: policy must be a tofcore.tracer.trace.PassPolicy, got {type(policy).__name__}")
    if spp is not None or progressive is not None:
        raise ConfigError(f"trace: spp and progressive go into the policy when one is given, got spp={spp!r} "
                          f"and progressive={progressive!r} beside it")
    return policy


class Passes(Iterator[Transport]):
    """The passes of one trace, each run when the next is asked for (:func:`trace_progressive`).

    Iterate for the accumulated :class:`Transport` after each pass. After a pass the caller may
    :meth:`report` what it measured: the schedule then decides the next pass at once and says whether one
    follows. :meth:`close` ends the trace early and releases its workers' shared memory and device arrays.
    """

    def __init__(self, run: Iterator[Transport], schedule: PassSchedule):
        self._run = run
        self._schedule = schedule
        self._latest: Transport | None = None

    def __next__(self) -> Transport:
        self._latest = next(self._run)
        return self._latest

    def report(self, report: PassReport) -> bool:
        """Hand the schedule the caller's measurements of the pass just traced; True when no pass follows
        (``spp`` reached, the time budget spent or the target error met)."""
        if self._latest is None:
            raise ConfigError("trace: a pass report comes after a pass")
        return self._schedule.report(report, self._latest.first_hit.distance_m)

    def close(self) -> None:
        self._run.close()


def _passes(scene: Scene, camera: Camera, leds: Sequence[LED], settings: TraceSettings, schedule: PassSchedule,
            choose: TracerChoice) -> Iterator[Transport]:
    """:func:`trace_progressive` on its checked settings: the passes that ``schedule`` asks for, on the tracer
    that ``choose`` picks."""
    schedule.start()
    dev = backend.select_device(settings.device)
    setup = make_setup(scene, camera, leds, settings, dev)
    activity = PassActivity(settings.activity, spp_max=schedule.policy.spp, pixels=camera.width * camera.height)
    execution = replace(_execution(settings, setup), on_chunk=activity.chunk if settings.activity else None)
    start = time.perf_counter()
    tracer = choose(setup, execution)
    stats = TraceStats(tracer=tracer.name, tracer_reason=tracer.reason)
    try:  # from here on, close() releases what the tracer took, whatever stops the trace (Ctrl-C included)
        tracer.start(stats)  # worker processes boot while this one traces the first hits
        transport = _empty_transport(setup, tracer.first_hit(setup, stats), stats)
        stats.parallel = tracer.attach(transport)
        stats.setup_seconds = time.perf_counter() - start
        while (counts := schedule.next_pass(transport)) is not None:
            activity.begin(stats.passes + 1, int(transport.sample_count.sum()))
            tracer.run(schedule.done, counts)
            schedule.add(counts)
            transport.sample_count += dev.xp.asarray(counts)
            stats.passes += 1
            stats.seconds = time.perf_counter() - start
            yield transport
    finally:
        tracer.close()


class PassActivity:
    """What a pass of a trace does before it ends, told to ``activity`` (:func:`trace_progressive`).

    A pass of 16 samples of a Kinect frame is 3.5 M paths, a minute of NumPy tracing on two cores: after
    every chunk (a block of whole pixels) the caller hears the mean samples per pixel traced so far,
    s = (N_before + N_chunks) / P, N the paths of the passes before and of the pass's finished chunks, P
    the pixels. The compile stage (``{"stage": "compile", ...}``) is told by the compiled tracer itself
    (:mod:`tofcore.compiled.tracer`).
    """

    def __init__(self, activity: Callable[[dict], None] | None, *, spp_max: int, pixels: int):
        self.activity = activity
        self.spp_max = spp_max
        self.pixels = max(1, pixels)
        self.number = 0          # the pass running now
        self.paths = 0           # paths traced before it and in its finished chunks

    def begin(self, number: int, paths_before: int) -> None:
        """A pass starts: its number, and the paths traced by the passes before it."""
        self.number, self.paths = number, paths_before

    def chunk(self, paths: int) -> None:
        """A chunk of the pass came back with ``paths`` paths."""
        self.paths += paths
        self.activity({"stage": "trace", "pass": self.number, "spp": self.paths / self.pixels,
                       "spp_max": self.spp_max})


class PassSchedule:
    """The passes of one trace under a :class:`PassPolicy`: each pass's samples per pixel, and when to stop.

    Before each pass (:meth:`next_pass`) the pass gets n samples per pixel: the next size of
    :func:`pass_schedule` after the passes so far, cut to what the time budget leaves; the caller's
    ``pass_size`` may cut it further. They are spread over the pixels: n each, or, after the pilot, by the
    reported error (``adaptive``), or by the caller's ``allocate``. A :meth:`report` after a pass makes that
    decision at once, with the caller's measurements, so the caller learns whether the pass was the last.
    """

    def __init__(self, policy: PassPolicy, *, allocate=None, pass_size=None):
        self.policy = policy
        self.progressive = policy.progressive or policy.time_budget_s is not None or policy.target_error_m is not None
        self._allocate, self._pass_size = allocate, pass_size
        self.done: np.ndarray | None = None   # (P,) samples each pixel has so far (host), from the first pass on
        self.nominal = 0                      # samples per pixel the passes so far were asked for
        self.next_n = next_pass_size(0, policy.spp, self.progressive)  # the coming pass's; 0: the trace ends
        self._decided = True                  # next_n holds the decision for the coming pass
        self._error_m: np.ndarray | None = None  # the latest reported error, (H, W) m
        self._budget = None if policy.time_budget_s is None else TimeBudget(policy.time_budget_s)
        self._start_s = self._cycle_start_s = 0.0  # the trace's start; the current pass cycle's (time budget)
        self._traced = 0.0                    # mean samples per pixel traced before the current cycle

    def start(self) -> None:
        """The trace starts: a time budget counts from now."""
        self._start_s = self._cycle_start_s = _clock()

    def next_pass(self, transport: Transport) -> np.ndarray | None:
        """(P,) samples per pixel of the coming pass, or None where the trace ends."""
        if self.done is None:
            self.done = np.zeros(transport.width * transport.height, np.int64)
        if not self._decided:
            self._decide(None)
        n = self.next_n
        if self._pass_size is not None and n:
            n = _checked_pass_size(self._pass_size(transport, n), n)
        if n == 0:
            return None
        self.nominal, self._decided = self.nominal + n, False
        counts = self._allocate(transport, n) if self._allocate is not None else self._allocation(n)
        return np.full(self.done.size, n, np.int64) if counts is None else _checked_counts(counts, self.done.size)

    def add(self, counts: np.ndarray) -> None:
        """A pass has traced ``counts`` more samples per pixel."""
        self.done += counts

    def report(self, report: PassReport, distance_m: np.ndarray) -> bool:
        """Decide the coming pass from the caller's measurements of the pass just traced (``distance_m``: the
        first hits, (H, W), NaN where no surface); True when none follows."""
        if self._decided:
            raise ConfigError("trace: one pass report after each pass, got a second one")
        self._error_m = np.asarray(backend.to_host(report.error_m), np.float64)
        self._decide(report)
        target = self.policy.target_error_m
        counted = self._error_m if report.apart is None else np.where(backend.to_host(report.apart), np.nan,
                                                                      self._error_m)
        rms = None if target is None else rms_error(counted, distance_m)
        if rms is not None and rms <= target:
            self.next_n = 0
        elif rms is not None and math.isfinite(rms) and self.next_n:
            self.next_n = min(self.next_n, samples_to_target(self.nominal, rms, target))
        return self.next_n == 0

    def _decide(self, report: PassReport | None) -> None:
        """The coming pass's scheduled samples per pixel, cut to the time budget (0: the trace ends)."""
        spp = self.policy.spp
        n = next_pass_size(self.nominal, spp, self.progressive) if self.nominal < spp else 0
        if self._budget is not None and n:
            now, traced = _clock(), float(self.done.mean())
            if report is not None:
                self._budget.estimate_s, self._budget.frame_s = report.estimate_s, report.frame_s
            self._budget.record(traced - self._traced, now - self._cycle_start_s)
            self._cycle_start_s, self._traced = now, traced
            n = self._budget.next_pass(n, now - self._start_s)
        self.next_n, self._decided = n, True

    def _allocation(self, n: int) -> np.ndarray | None:
        """The policy's allocation of a pass of n samples per pixel (None: n everywhere)."""
        if not self.policy.adaptive or self._error_m is None:
            return None
        return allocate_samples(self._error_m, self.done, n)


_clock = time.perf_counter  # the time budget's clock (seconds); tests replace it to check the budgeted passes


def _execution(settings: TraceSettings, setup: TraceSetup) -> Execution:
    """How the chunks of the CPU's tracers run, checked (the GPU's wavefront traces a pass at once)."""
    chunk_size, workers = settings.chunk_size, settings.workers
    if chunk_size is None:
        chunk_size = parallel.CPU_CHUNK_PATHS
    if not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1:
        raise ConfigError(f"trace: chunk_size must be an integer >= 1, got {chunk_size!r}")
    workers = usable_cpus() if workers is None else workers
    if not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ConfigError(f"trace: workers must be an integer >= 1, got {workers!r}")
    limits.MAX_WORKERS.check(int(workers), "trace", "workers")
    return Execution(chunk_size=chunk_size, workers=workers, cancel=settings.cancel, activity=settings.activity)


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


def samples_to_target(done: int, error: float, target: float) -> int:
    r"""Samples per pixel a pass needs to bring the RMS error ``error`` of ``done`` samples per pixel down to
    ``target``, at the Monte Carlo rate :math:`\sigma \propto n^{-1/2}`:
    :math:`\lceil n (\sigma/\sigma_t)^2 \rceil - n`, at least 1. The rate is the slowest the estimator
    shows (adaptive sampling makes the error fall faster: the demo frame's fell as :math:`n^{-0.57}` to
    :math:`n^{-0.62}` from 16 to 48 spp), so the pass rarely falls short; where it does, the next (small) one
    follows. A target error's last pass is cut to this instead of overshooting by up to a whole scheduled
    pass of 16."""
    return max(1, math.ceil(done * (error / target) ** 2) - done)


def pass_schedule(spp: int, progressive: bool = True) -> list[int]:
    """Samples per pass summing to ``spp``: 1, 1, 2, 4, 8, 16, 16, … (progressive), else 16, 16, ….

    Progressive passes give early frames and error estimates (previews, time budgets, target errors);
    without them a render needs no small passes, and on a GPU every pass costs the same kernel
    launches whatever its size. Depends on spp and ``progressive`` only (never on chunk size or
    device), so results are reproducible, and the first passes of a longer render equal a shorter
    render of the same kind. A time budget cuts a pass short (:class:`PassSchedule`); the schedule then
    goes on from the samples traced.
    """
    passes, done = [], 0
    while done < spp:
        passes.append(next_pass_size(done, spp, progressive))
        done += passes[-1]
    return passes


_MAX_PASS = 16  # samples per pixel in the largest pass
