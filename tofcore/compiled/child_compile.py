"""The CPU kernels compiled by a child process, so that a render that can be cancelled is never stuck in numba.

numba compiles the kernels on their first call (30 s to 3 min, once per install; the machine code is
cached, :func:`tofcore.compiled.cache_location`), and nothing interrupts that call. A trace with a
``cancel`` callback (the Blender add-on's renders and live previews) therefore has them compiled by a
child process, ``python -m tofcore warmup --device cpu``, waits for it while polling ``cancel`` (:func:`wait`),
and then loads the cache in about a second.

A cancel ends the wait (:class:`tofcore.Cancelled`), not the child: the compile goes on in the
background, and the next render — a live preview restarted at every edit, for one — waits for the same
child instead of starting over. :func:`start` begins it ahead (the add-on, right after installing numba).
The child is stopped when this process exits; numba writes its cache files by atomic renames, so a stopped
compile leaves nothing half-written. Where the child cannot run or fails, :func:`wait` says why and the
render compiles in its own process, as without a ``cancel``.
"""

from __future__ import annotations

import atexit
import os
import subprocess
import sys
import tempfile
import threading
import time

from ..errors import Cancelled

POLL_S = 0.1
"""How often :func:`wait` asks ``cancel`` (seconds)."""

TICK_S = 0.5
"""Seconds between two ``tick`` calls of :func:`wait`."""

_child: dict = {}  # the last compile: {"process": Popen, "log": file with its stderr, "started"/"ended": perf_counter}
_lock = threading.Lock()


def command(python: str) -> list[str]:
    """The child's command line: tofcore's warm-up on the CPU (a tiny frame that compiles and caches the kernels)."""
    return [python, "-m", "tofcore", "warmup", "--device", "cpu"]


def child_environment() -> dict:
    """This process's environment with ``PYTHONPATH`` = its ``sys.path``, so the child imports the same tofcore
    and numba (inside Blender these come from the extension's and the add-on's own folders)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
    env["TOFCORE_TRACER"] = "compiled"  # the child must compile, or fail saying why
    return env


def start() -> str:
    """Start compiling the CPU kernels in a child process unless they are cached or a child already compiles.

    Returns '' when a child compiles now or none is needed, else why none could start.
    """
    from . import cache_problem, cpu_kernels_cached
    from ..tracer.workers import python_executable

    with _lock:
        if running() or cpu_kernels_cached() is not False:
            return ""
        if cache_problem():  # a child's compile could not be kept for this process
            return cache_problem()
        python = python_executable()
        if python is None:
            return f"no Python interpreter beside {sys.executable!r} to compile in"
        if _child.get("log") is not None:
            _child["log"].close()
        log = tempfile.TemporaryFile("w+", encoding="utf-8", errors="replace")
        try:
            process = subprocess.Popen(command(python), env=child_environment(), stdin=subprocess.DEVNULL,
                                       stdout=subprocess.DEVNULL, stderr=log)
        except OSError as err:
            log.close()
            _child.clear()
            return f"{python} could not be started ({err})"
        _child.clear()
        _child.update(process=process, log=log, started=time.perf_counter())
        threading.Thread(target=_note_end, args=(process,), name="tof-compile-child", daemon=True).start()
        return ""


def _note_end(process: subprocess.Popen) -> None:
    """Wait for the child in a thread and note when it ended (for :func:`state`)."""
    process.wait()
    if _child.get("process") is process:
        _child["ended"] = time.perf_counter()


def state() -> tuple[str, float, str] | None:
    """The last child's ``(state, seconds, line)`` for a status display: ``"running"`` (seconds so far),
    ``"done"`` (the kernels are cached; its run time) or ``"failed"`` (its run time and why, one line); None
    before the first child of this process."""
    process, started = _child.get("process"), _child.get("started")
    if process is None or started is None:
        return None
    if process.poll() is None:
        return "running", time.perf_counter() - started, ""
    seconds = _child.get("ended", time.perf_counter()) - started
    if "outcome" not in _child:  # read once: the preferences ask at every redraw
        _child["outcome"] = _outcome()
    why = _child["outcome"]
    return ("failed", seconds, why) if why else ("done", seconds, "")


def running() -> bool:
    """Whether a child is compiling the kernels now."""
    process = _child.get("process")
    return process is not None and process.poll() is None


def wait(cancel, tick=None) -> str:
    """Have the CPU kernels compiled by a child process (started here if need be) and wait for it, calling
    ``tick(seconds waited)`` about every :data:`TICK_S` when given.

    Returns '' once they are cached (the caller loads them in about a second), else why no child cached
    them (the caller then compiles in its own process). Raises :class:`tofcore.Cancelled` as soon as
    ``cancel()`` turns True; the child goes on compiling.
    """
    why_not = start()
    if why_not:
        return why_not
    start_s, told = time.perf_counter(), -TICK_S
    while running():
        waited = time.perf_counter() - start_s
        if tick is not None and waited - told >= TICK_S:
            tick(waited)
            told = waited
        if cancel():
            raise Cancelled("cancelled while the compiled tracer compiles (the compile goes on in the "
                            "background, for the next render)")
        time.sleep(POLL_S)
    return _outcome()


def compile_aside(cancel, tick=None) -> str:
    """For a trace with ``cancel``: uncached CPU kernels compiled by the child (:func:`wait`, ``tick`` as there);
    what happened, in words for ``stats["transport"]["compile"]`` ('' when they were cached)."""
    from . import cpu_kernels_cached

    if cpu_kernels_cached() is not False:
        return ""
    start_s = time.perf_counter()
    why_not = wait(cancel, tick)
    if why_not:
        return f"compiled in this process: {why_not}"
    return f"compiled by a child process in {time.perf_counter() - start_s:.1f} s"


def _outcome() -> str:
    """'' when the kernels are cached now, else the finished child's exit status and last line of stderr."""
    from . import cpu_kernels_cached

    if cpu_kernels_cached() is not False:
        return ""
    process, log = _child["process"], _child.get("log")  # wait() started it, or found the kernels cached
    lines = []
    if log is not None:
        log.seek(0)
        lines = [line.strip() for line in log.read().splitlines() if line.strip()]
    return (f"`{' '.join(command('python'))}` ended with exit status {process.returncode}"
            + (f": {lines[-1]}" if lines else ""))


def stop() -> None:
    """Stop a running child and close its log (this process's exit does it too)."""
    process = _child.get("process")
    if process is not None and process.poll() is None:
        process.terminate()
        try:
            process.wait(5)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    log = _child.pop("log", None)
    if log is not None:
        log.close()


atexit.register(stop)
