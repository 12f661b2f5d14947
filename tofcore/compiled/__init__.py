"""The compiled tracer: the NumPy tracer's paths as compiled scalar code (optional; needs numba).

``pip install "tofcore[compiled]"`` adds numba; then :func:`tofcore.trace` and :func:`tofcore.render`
trace on the CPU with :mod:`tofcore.compiled.kernels` — one loop per path over compiled functions, every
pixel of a chunk on numba's threads — wherever the render uses only what those kernels implement, and
fall back to the NumPy reference otherwise, saying why in ``stats["transport"]["tracer_reason"]`` of
the frame (frame.json) and in ``tofcore render --verbose``. The frame is the NumPy frame up to the last
bits of transcendental functions (tests/tofcore/test_compiled.py states and tests the tolerance).

Environment: ``TOFCORE_TRACER=numpy`` forces the NumPy reference, ``compiled`` makes a render that
cannot use the compiled tracer an error instead of a fall-back, ``auto`` (default) picks it when it
can. The machine code is cached by numba beside the sources (``tofcore/compiled/__pycache__/numba-<hash>``;
``~/.cache/tofcore/numba-<hash>`` where that folder is not writable; ``$NUMBA_CACHE_DIR/tofcore-<hash>``
where that variable is set), ``<hash>`` naming the kernels' constants, so a changed constant never loads
stale code (:mod:`tofcore.compiled._target`): the first render of a fresh install compiles for 30–80 s
(docs/benchmarks.md), later processes load the kernels in about a second.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..tracer.transport import TraceStats
from . import setup

TRACER_ENV = "TOFCORE_TRACER"
TRACERS = ("auto", "numpy", "compiled")

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


def numba_version() -> str | None:
    """The installed numba's version, or None where it cannot be imported."""
    try:
        import numba
    except Exception:  # ImportError, or a numba that does not work with this NumPy
        return None
    return numba.__version__


def choose(ctx) -> Choice:
    """The tracer for a trace set-up (:class:`tofcore.tracer.setup.TraceSetup`): compiled wherever it can be, else NumPy."""
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


def cuda_unavailable() -> str:
    """Why numba cannot run the compiled tracer on this machine's GPU, or ""."""
    try:
        from numba import cuda
        available = cuda.is_available()
    except Exception as exc:  # numba without its CUDA target (numba-cuda), or a broken driver
        return f"numba's CUDA target cannot be loaded ({type(exc).__name__}: {str(exc).splitlines()[0][:120]})"
    return "" if available else "numba finds no CUDA GPU (install numba-cuda beside CuPy)"


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


def thread_count(workers: int) -> int:
    """numba threads a render with ``workers`` uses: at most numba's pool (``NUMBA_NUM_THREADS``)."""
    import numba

    return max(1, min(int(workers), numba.config.NUMBA_NUM_THREADS))


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


def cpu_kernels_cached() -> bool | None:
    """Whether the CPU build of the kernels is in numba's cache (a render then loads it in about a second);
    None where the compiled tracer will not run on the CPU (no numba, ``TOFCORE_TRACER=numpy``).

    It looks for the index file numba writes for the driver, ``kernels.trace_pixels-*.nbi``, in the cache
    folder of these kernels' constants; a driver cached for other argument types still compiles."""
    if os.environ.get(TRACER_ENV, "").strip().lower() == "numpy" or numba_version() is None:
        return None
    from . import kernels  # decorating the kernels picks their cache folder; it compiles nothing

    folder = cache_location()
    return any(Path(folder).glob("**/kernels.trace_pixels-*.nbi"))


def cache_location() -> str:
    """Where numba keeps the compiled kernels: the CPU build's folder once the kernels are imported
    (:func:`tofcore.compiled._target.cache_folder`); else, as for the CUDA build, ``NUMBA_CACHE_DIR``, else
    ``__pycache__`` beside the sources (also in a Blender extension: its site-packages is in the user's
    folder), else (a read-only install) numba's user cache."""
    import numba

    from . import _target

    if _target.CACHE_FOLDERS.get(__name__ + ".kernels"):
        return str(_target.CACHE_FOLDERS[__name__ + ".kernels"])
    if numba.config.CACHE_DIR:
        return str(numba.config.CACHE_DIR)
    here = Path(__file__).resolve().parent
    return str(here / "__pycache__") if os.access(here, os.W_OK) else "numba's user cache (~/.cache/numba)"
