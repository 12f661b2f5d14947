"""The compiled tracer running a trace's passes, and the one place a trace's tracer is chosen (:func:`choose`).

:func:`tofcore.trace` and :func:`tofcore.render` hand :func:`choose` to the pass loop of
:func:`tofcore.tracer.trace.trace_progressive`, which calls it once per trace with the checked set-up: it
returns a :class:`CompiledTracer` wherever the compiled kernels can render the set-up on its device, else the
NumPy :class:`~tofcore.tracer.parallel.ReferenceTracer` with the reason (``TOFCORE_TRACER``, what the kernels
do not implement, no numba, no CUDA target). Both run passes through the one interface,
:class:`tofcore.tracer.trace.Tracer`; the pass loop, the pass sizes and the sample allocation stay with the
tracer (:mod:`tofcore.tracer.trace`). This module stands above the tracer package (it reuses its stages'
functions through :mod:`tofcore.compiled.kernels`), so every import between the two points down to the tracer.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..tracer.parallel import Execution, HostTracer, ReferenceTracer, chunks, collect
from ..tracer.setup import TraceSetup, on_host
from ..tracer import stages
from ..tracer.transport import FirstHit, TraceStats, Transport
from . import child_compile, setup
from . import TRACER_ENV, TRACERS, cuda_unavailable, numba_version, thread_count


def choose(trace_setup: TraceSetup, execution: Execution) -> CompiledTracer | ReferenceTracer | HostTracer:
    """The tracer for a trace: the compiled one wherever it can run the set-up, else the NumPy reference
    saying why (``ReferenceTracer.reason``). ``TOFCORE_TRACER=compiled`` makes the fall-back an error.

    On the GPU only the compiled wavefront traces paths: where it cannot (no numba-cuda, a correlation
    channel given as Python code, ``TOFCORE_TRACER=numpy``) the CPU's tracer — compiled where numba runs it,
    else the reference — traces them and its sums are copied to the device (:class:`HostTracer`)."""
    choice = _choice(trace_setup)
    if choice.packed is not None:
        return CompiledTracer(choice, execution)
    if not trace_setup.device.is_gpu:
        return ReferenceTracer(trace_setup, execution, reason=choice.reason)
    host_setup = on_host(trace_setup)
    host_choice = _choice(host_setup)
    inner = (CompiledTracer(host_choice, execution) if host_choice.packed is not None
             else ReferenceTracer(host_setup, execution, reason=host_choice.reason))
    return HostTracer(inner, trace_setup, why=choice.reason)


class CompiledTracer:
    """The compiled kernels running the passes of one trace (a :class:`tofcore.tracer.trace.Tracer`): on the
    CPU every pixel of a chunk on numba's threads (:mod:`tofcore.compiled.cpu`), on the GPU the whole pass as
    one wavefront (:mod:`tofcore.compiled.cuda`). Same sums as the NumPy reference, to the last bits of
    transcendental functions (tests/tofcore/test_compiled.py)."""

    name = "compiled"
    reason = ""

    def __init__(self, choice: Choice, execution: Execution):
        self.choice = choice
        self.execution = execution
        self._transport: Transport | None = None

    def start(self, stats: TraceStats) -> None:
        """Before the first hits: numba's compile cannot be cancelled, so a trace that can be has uncached CPU
        kernels compiled by a child process (:mod:`tofcore.compiled.child_compile`) and says how."""
        if self.choice.device_scene is None and self.execution.cancel is not None:
            stats.compile = child_compile.compile_aside(self.execution.cancel, self._tick)

    def first_hit(self, trace_setup: TraceSetup, stats: TraceStats) -> FirstHit:
        """The ground truth's rays: on the CPU by the kernels where they are compiled or cached (else the NumPy
        reference's traversal, while the kernels compile for the passes), on the GPU by the CUDA build's two
        kernels around the BVH's traversal (:func:`tofcore.compiled.cuda.first_hit`)."""
        if self.choice.device_scene is not None:
            from . import cuda

            return cuda.first_hit(self.choice.device_scene, trace_setup, stats)
        if not needs_compile():
            from . import cpu

            return cpu.first_hit(self.choice.packed, trace_setup, stats)
        return stages.first_hit(trace_setup, stats)

    def attach(self, transport: Transport) -> str:
        """The frame's sums exist: the passes add to them; returns how the kernels run (``stats.parallel``)."""
        self._transport = transport
        return parallel_label(self.choice, self.execution.workers)

    def run(self, done: np.ndarray, counts: np.ndarray) -> None:
        """Trace samples [done[p], done[p] + counts[p]) of every pixel; raises Cancelled when asked to stop."""
        run = self.execution
        if self.choice.device_scene is None and needs_compile():
            # An empty pixel range compiles the kernels for this trace's argument types and traces nothing.
            seconds = compile_in_thread(lambda: cpu_compile(self.choice.packed, self._transport, done, counts),
                                        self._tick)
            stats = self._transport.stats  # a child that could not compile said why (compile_aside)
            stats.compile = f"{stats.compile}, {seconds:.1f} s" if stats.compile else \
                f"compiled in this process in {seconds:.1f} s"
        pieces = pass_pieces(self.choice, counts, run.chunk_size, chunks)
        results = trace_pass(self.choice, self._transport, done, counts, pieces, run.workers, run.cancel)
        collect(results, len(pieces), self._transport.stats, run.on_chunk)

    def _tick(self, seconds: float) -> None:
        """The kernels compile: tell ``activity`` (about twice a second)."""
        if self.execution.activity is not None:
            self.execution.activity({"stage": "compile", "seconds": seconds})

    def close(self) -> None:
        """The trace has ended: its GPU arrays may serve the next trace."""
        release(self.choice)


def needs_compile() -> bool:
    """Whether this process's first call of the CPU kernels compiles them: not compiled here yet, and not in
    numba's cache (:func:`tofcore.compiled.cpu_kernels_cached`); loading the cache takes about a second."""
    from . import cpu_kernels_cached, kernels

    return not kernels.trace_pixels.overloads and cpu_kernels_cached() is False


TICK_S = 0.5
"""Seconds between two ``{"stage": "compile"}`` reports while the kernels compile."""


def compile_in_thread(compile_kernels, tick) -> float:
    """Run ``compile_kernels()`` on a thread of its own, calling ``tick(seconds)`` at once and every
    :data:`TICK_S` until it ends; its seconds. numba's compile holds the GIL only between its steps, so
    this thread keeps telling the caller (a progress bar whose clock moves) and takes Ctrl-C at once (the
    compile thread is a daemon: it ends with the process)."""
    failure: list[BaseException] = []

    def work() -> None:
        try:
            compile_kernels()
        except BaseException as exc:  # re-raised in the caller's thread
            failure.append(exc)

    start = time.perf_counter()
    thread = threading.Thread(target=work, name="tofcore-compile", daemon=True)
    thread.start()
    while thread.is_alive():
        tick(time.perf_counter() - start)
        thread.join(TICK_S)
    if failure:
        raise failure[0]
    return time.perf_counter() - start


def cpu_compile(packed, out, first: np.ndarray, counts: np.ndarray) -> None:
    """:func:`tofcore.compiled.cpu.compile_kernels` (imported when called: it imports the kernels)."""
    from . import cpu

    cpu.compile_kernels(packed, out, first, counts)


COMPILED_CHUNK_PATHS = 1 << 18
"""Paths per call of the compiled kernel: memory does not grow with it (no per-path arrays); it only
sets how often a render polls ``cancel`` (~0.1 s of tracing on two cores)."""


@dataclass(frozen=True)
class Choice:
    """Which tracer a render uses, and why."""

    tracer: str                 # "compiled" or "numpy"
    reason: str                 # why the NumPy tracer runs ("" for the compiled one)
    packed: setup.Packed | None  # the compiled tracer's arrays, None for NumPy
    device_scene: object = None  # those arrays on the GPU (tofcore.compiled.cuda.DeviceScene) for a GPU render


def _choice(ctx) -> Choice:
    """Whether the compiled tracer can run a trace set-up (:class:`tofcore.tracer.setup.TraceSetup`), and why not."""
    wanted = os.environ.get(TRACER_ENV, "auto").strip().lower() or "auto"
    if wanted not in TRACERS:
        raise ConfigError(f"{TRACER_ENV} must be one of {list(TRACERS)}, got {wanted!r}")
    if wanted == "numpy":
        return Choice("numpy", f"{TRACER_ENV}=numpy", None)
    why = setup.unsupported(ctx)
    if not why and numba_version() is None:
        why = 'numba is not installed (pip install "tofcore[compiled]")'
    if not why and ctx.device.is_gpu:
        why = cuda_unavailable()
    if why:
        if wanted == "compiled":
            raise ConfigError(f"{TRACER_ENV}=compiled, but the compiled tracer cannot render this: {why}")
        return Choice("numpy", why, None)
    packed = setup.pack(ctx)
    if not ctx.device.is_gpu:
        return Choice("compiled", "", packed)
    from . import cuda
    return Choice("compiled", "", packed, cuda.upload(packed, ctx.scene.bvh))


def release(choice: Choice) -> None:
    """The trace of ``choice`` has ended: its GPU arrays may serve the next trace (tofcore.compiled.cuda.release)."""
    if choice.device_scene is not None:
        from . import cuda
        cuda.release(choice.device_scene)


def parallel_label(choice: Choice, workers: int) -> str:
    """How the compiled tracer runs, for TraceStats.parallel."""
    if choice.device_scene is not None:
        return "CUDA (numba), one path per thread"
    return f"numba threads: {thread_count(workers)}"


def pass_pieces(choice: Choice, counts: np.ndarray, chunk_size: int, chunks) -> list[tuple[int, int]]:
    """The pixel ranges a pass is traced in: one launch sequence for the whole pass on the GPU, else
    ranges of ``max(chunk_size, COMPILED_CHUNK_PATHS)`` paths (``chunks``: tofcore.tracer.parallel.chunks)."""
    if choice.device_scene is not None:
        return [(0, int(counts.size))]
    return chunks(counts, max(chunk_size, COMPILED_CHUNK_PATHS))


def trace_pass(choice: Choice, out, done: np.ndarray, counts: np.ndarray, chunks, threads: int, cancel):
    """Trace one pass's pixel ranges with the compiled kernel on ``threads`` threads; yields TraceStats per
    range, or None where ``cancel`` asked to stop."""
    if choice.device_scene is not None:
        yield _gpu_pass(choice, out, done, counts, cancel)
        return
    import numba

    from . import cpu

    numba.set_num_threads(thread_count(threads))
    for p0, p1 in chunks:
        if cancel is not None and cancel():
            yield None
            return
        start = time.perf_counter()
        n = cpu.trace_chunk(choice.packed, out, p0, p1, done, counts)
        yield TraceStats(camera_rays=int(n[0]), bounce_rays=int(n[1]), shadow_rays=int(n[2]), light_rays=int(n[3]),
                         skipped_shadow_rays=int(n[4]), chunk_seconds=time.perf_counter() - start)


def _gpu_pass(choice: Choice, out, done: np.ndarray, counts: np.ndarray, cancel) -> TraceStats | None:
    """The whole pass on the GPU (tofcore.compiled.cuda.trace_pass), or None where ``cancel`` asked to stop."""
    from . import cuda

    if cancel is not None and cancel():
        return None
    start = time.perf_counter()
    n = cuda.trace_pass(choice.device_scene, out, done, counts)
    return TraceStats(camera_rays=int(n[0]), bounce_rays=int(n[1]), shadow_rays=int(n[2]), light_rays=int(n[3]),
                      skipped_shadow_rays=int(n[4]), chunk_seconds=time.perf_counter() - start)
