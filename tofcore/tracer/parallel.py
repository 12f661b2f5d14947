"""Parallel execution of a trace: the NumPy reference tracer's chunks and worker processes.

:class:`ReferenceTracer` runs the passes that :mod:`tofcore.tracer.trace` decides. A pass's samples are cut
into chunks of whole pixels (:func:`chunks`), about ``chunk_size`` paths each and at least 4 per worker;
each chunk is traced by :func:`~tofcore.tracer.integrator.trace_chunk` on a worker process
(:mod:`tofcore.tracer.workers`: the set-up and the accumulators live once in shared memory), on a thread
where no process can start, or in this process. Chunks own disjoint pixels and sum their samples in order,
so the frame is the same bit for bit whatever the split or the worker count.

On the GPU only the compiled wavefront traces paths (:mod:`tofcore.compiled.tracer`); where it cannot, the
reference traces a GPU render's paths on the CPU and copies its sums to the device after each pass
(:class:`HostTracer`, :func:`reference`). The CuPy array program is retired as a tracer: CuPy keeps the
frame's arrays, the first hits and everything after the trace.
"""

from __future__ import annotations

import functools
import pickle
import uuid
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from .. import backend
from ..errors import Cancelled
from . import stages, workers
from .integrator import trace_chunk
from .setup import TraceSetup, on_host
from .transport import FirstHit, TraceStats, Transport
from .workers import process_support

_ACCUMULATORS = ("sample_count", "signal_sum", "correlation_sum", "ambient_sum", "replicate_sum", "transient_sum")


@dataclass
class SharedTrace:
    """A render's context and accumulators in shared memory, and the per-pass sample plan the workers read."""

    shared: workers.Shared
    key: str
    first: np.ndarray   # (P,) samples each pixel had before this pass (shared view)
    counts: np.ndarray  # (P,) samples each pixel gets in this pass (shared view)


def start_workers(n_workers: int) -> str:
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


def share(setup: TraceSetup, transport: Transport) -> tuple[SharedTrace | None, str]:
    """Put the context and the accumulators into shared memory; the transport then holds the shared views.

    Returns (None, why) where worker processes cannot run this trace: a correlation function that does
    not pickle (a lambda: use ``functools.partial`` of a module-level function, as
    :meth:`~tofcore.sensor.modulation.Modulation.correlations` does) or no room in /dev/shm.
    """
    n_pix = transport.width * transport.height
    first, counts = np.zeros(n_pix, np.int64), np.zeros(n_pix, np.int64)
    written = [getattr(transport, name) for name in _ACCUMULATORS if getattr(transport, name) is not None]
    try:
        shared = workers.Shared((setup, transport, first, counts), always=written + [first, counts])
    except (pickle.PicklingError, TypeError, AttributeError) as exc:
        return None, f"the trace context does not pickle for worker processes ({exc})"
    except OSError as exc:  # no room in /dev/shm
        return None, f"no shared memory for worker processes ({exc})"
    try:
        for name in _ACCUMULATORS:
            if getattr(transport, name) is not None:
                setattr(transport, name, shared.view(getattr(transport, name)))
        return SharedTrace(shared, uuid.uuid4().hex, shared.view(first), shared.view(counts)), ""
    except BaseException:  # Ctrl-C here: unlink the blocks, or the resource tracker reports them leaked
        shared.close()
        raise


def unshare(run: SharedTrace, transport: Transport) -> None:
    """Give the transport private copies of its sums and release the shared memory (also when the
    copying is interrupted)."""
    try:
        for name in _ACCUMULATORS:
            if getattr(transport, name) is not None:
                setattr(transport, name, np.array(getattr(transport, name)))
    finally:
        run.shared.close()


def run_in_processes(run: SharedTrace, n: int, done: np.ndarray, counts: np.ndarray, chunks, cancel):
    """Trace one pass's chunks on the worker processes; yields each chunk's TraceStats."""
    run.first[:] = done
    run.counts[:] = counts
    return workers.run(n, run.shared, run.key, _trace_shared_chunk, chunks, cancel)


def _trace_shared_chunk(shared_objects, p0: int, p1: int) -> TraceStats:
    """In a worker process: trace pixels [p0, p1) of the pass described in the shared memory."""
    setup, out, first, counts = shared_objects
    return trace_chunk(setup, out, p0, p1, first=first, counts=counts)


@dataclass(frozen=True)
class Execution:
    """How the chunks of a trace run, checked (``trace_progressive``'s ``chunk_size``, ``workers``, ``cancel``)."""

    chunk_size: int                      # paths per chunk at most
    workers: int                         # processes (NumPy) or threads (compiled) tracing chunks at once
    cancel: Callable[[], bool] | None    # polled before every chunk
    activity: Callable[[dict], None] | None = None  # told what a pass does meanwhile (trace_progressive)
    on_chunk: Callable[[int], None] | None = None   # called with each finished chunk's paths


class ReferenceTracer:
    """The NumPy reference tracer, the one that defines the frame: a :class:`~tofcore.tracer.trace.Tracer`.

    Each pass is cut into chunks of whole pixels (:func:`chunks`), each traced by
    :func:`~tofcore.tracer.integrator.trace_chunk`: on the worker processes over shared memory, on threads
    where no process can start, or in this process when a pass has one chunk. As a class it is also the
    tracer choice that always picks the reference: ``trace_progressive(tracer=ReferenceTracer)``.
    """

    name = "numpy"

    def __init__(self, setup: TraceSetup, execution: Execution, reason: str = ""):
        self.setup = setup
        self.execution = execution
        self.reason = reason                      # why the reference runs where another tracer was asked for
        self._why_not = "one"                     # why the chunks do not run on worker processes ("" once they may)
        self._shared: SharedTrace | None = None
        self._threads: ThreadPoolExecutor | None = None
        self._transport: Transport | None = None

    def start(self, stats: TraceStats) -> None:
        """Before the first hits: start the worker processes, which boot and import tofcore meanwhile."""
        if self.execution.workers > 1:
            self._why_not = start_workers(self.execution.workers)

    def first_hit(self, setup: TraceSetup, stats: TraceStats) -> FirstHit:
        """The pixel-centre rays traced by the reference (:func:`~tofcore.tracer.stages.first_hit`)."""
        return stages.first_hit(setup, stats)

    def attach(self, transport: Transport) -> str:
        """The frame's sums exist: put them into shared memory for the workers; returns how chunks run."""
        self._transport = transport
        self._threads = ThreadPoolExecutor(max_workers=self.execution.workers)
        with workers.sigint_held():  # a Ctrl-C meanwhile is raised once `_shared` holds what to release
            if not self._why_not:
                self._shared, self._why_not = share(self.setup, transport)
        if self._shared is not None:
            return "processes"
        return "one" if self._why_not == "one" else f"threads: {self._why_not}"

    def run(self, done: np.ndarray, counts: np.ndarray) -> None:
        """Trace samples [done[p], done[p] + counts[p]) of every pixel; raises Cancelled when asked to stop."""
        xp, n_workers, cancel = self.setup.xp, self.execution.workers, self.execution.cancel
        pieces = chunks(counts, pass_chunk_paths(int(counts.sum()), self.execution.chunk_size, n_workers))
        if self._shared is not None and len(pieces) > 1:
            results = run_in_processes(self._shared, n_workers, done, counts, pieces, cancel)
        else:
            run = functools.partial(trace_chunk, self.setup, self._transport, first=xp.asarray(done),
                                    counts=xp.asarray(counts))

            def job(chunk: tuple[int, int]) -> TraceStats | None:
                return None if cancel is not None and cancel() else run(*chunk)

            results = self._threads.map(job, pieces) if self._shared is None else map(job, pieces)
        collect(results, len(pieces), self._transport.stats, self.execution.on_chunk)

    def close(self) -> None:
        """The trace has ended: stop the threads, give the transport private copies of the shared sums."""
        if self._threads is not None:
            self._threads.shutdown()
        if self._shared is not None:
            shared, self._shared = self._shared, None
            unshare(shared, self._transport)


def reference(setup: TraceSetup, execution: Execution, reason: str = "") -> ReferenceTracer | HostTracer:
    """The NumPy reference for a trace (the default choice of ``trace_progressive``). On the GPU only the
    compiled wavefront traces paths: a GPU render's paths are traced here on the CPU (:class:`HostTracer`)."""
    if not setup.device.is_gpu:
        return ReferenceTracer(setup, execution, reason)
    return HostTracer(ReferenceTracer(on_host(setup), execution, reason), setup, why=reason)


SUMS = ("signal_sum", "correlation_sum", "replicate_sum", "ambient_sum", "transient_sum")
"""The sums of a :class:`~tofcore.tracer.transport.Transport` a tracer adds its paths to."""


class HostTracer:
    """A CPU tracer (``inner``, on :func:`~tofcore.tracer.setup.on_host`'s set-up) tracing a GPU render's paths
    where the compiled wavefront cannot (no numba-cuda, a correlation channel given as Python code,
    ``TOFCORE_TRACER=numpy``): its sums are the CPU's, copied into the device frame after every pass, so the
    first hits and everything after the trace stay on the GPU. A :class:`~tofcore.tracer.trace.Tracer`."""

    def __init__(self, inner, device_setup: TraceSetup, why: str = ""):
        self.inner = inner
        self.name = inner.name
        self.reason = f"{why}: the paths traced on the CPU" if why else "the paths traced on the CPU"
        self._xp = device_setup.xp
        self._device: Transport | None = None
        self._host: Transport | None = None

    def start(self, stats: TraceStats) -> None:
        self.inner.start(stats)

    def first_hit(self, setup: TraceSetup, stats: TraceStats) -> FirstHit:
        """On the device, as the frame's other buffers (:func:`~tofcore.tracer.stages.first_hit`)."""
        return stages.first_hit(setup, stats)

    def attach(self, transport: Transport) -> str:
        """The device frame exists: the CPU tracer gets host sums of the same shapes."""
        self._device = transport
        host = {name: np.zeros(getattr(transport, name).shape) for name in SUMS if getattr(transport, name) is not None}
        self._host = replace(transport, sample_count=np.zeros(transport.sample_count.shape, np.int64), first_hit=None,
                             **host)  # the first hits stay on the device: the paths do not read them
        return f"{self.inner.attach(self._host)}, on the CPU; sums copied to the GPU after each pass"

    def run(self, done: np.ndarray, counts: np.ndarray) -> None:
        self.inner.run(done, counts)
        for name in SUMS:
            target = getattr(self._device, name)
            if target is not None:
                target[...] = self._xp.asarray(getattr(self._host, name))

    def close(self) -> None:
        self.inner.close()


def collect(results: Iterable[TraceStats | None], n_chunks: int, stats: TraceStats,
            on_chunk: Callable[[int], None] | None = None) -> None:
    """Add each chunk's statistics to the trace's, and tell ``on_chunk`` its paths (its camera rays) as it
    comes back; raises Cancelled where a chunk was cancelled (None) or fewer than ``n_chunks`` came back."""
    finished = 0
    for chunk_stats in results:
        if chunk_stats is None:
            raise Cancelled("trace: cancelled")
        stats.add(chunk_stats)
        finished += 1
        if on_chunk is not None:
            on_chunk(chunk_stats.camera_rays)
    if finished < n_chunks:
        raise Cancelled("trace: cancelled")


MIN_CHUNK_PATHS = 1 << 13
"""Paths per chunk at least, when a pass is split finer to keep every worker busy (NumPy's per-call
overhead grows below a few thousand elements)."""


def pass_chunk_paths(pass_paths: int, chunk_size: int, workers: int) -> int:
    """Paths per chunk for a pass: ``chunk_size``, or less so that the pass has ≥ 4 chunks per worker.

    A 1-spp pass of a 512 × 424 frame is 217 k paths: 4 chunks of 65 k would leave 12 of 16 workers idle.
    The frame does not depend on the split (chunks hold whole pixels).
    """
    if workers == 1:
        return chunk_size
    return max(min(chunk_size, MIN_CHUNK_PATHS), min(chunk_size, -(-pass_paths // (4 * workers))))


def chunks(counts: np.ndarray, chunk_size: int) -> list[tuple[int, int]]:
    """Pixel ranges [p0, p1) of about ``chunk_size`` paths each (whole pixels; at least one pixel)."""
    ends = np.cumsum(counts)
    out, p0 = [], 0
    while p0 < len(counts):
        before = ends[p0 - 1] if p0 else 0
        p1 = max(p0 + 1, int(np.searchsorted(ends, before + chunk_size, side="right")))
        out.append((p0, min(p1, len(counts))))
        p0 = p1
    return out


CPU_CHUNK_PATHS = 1 << 16
"""Paths per chunk on the CPU: the per-bounce temporaries of 65,536 paths stay in L2/L3."""

