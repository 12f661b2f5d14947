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

_child: dict = {}  # the running compile: {"process": Popen, "log": file with its stderr}
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
        _child.update(process=process, log=log)
        return ""


def running() -> bool:
    """Whether a child is compiling the kernels now."""
    process = _child.get("process")
    return process is not None and process.poll() is None


def wait(cancel) -> str:
    """Have the CPU kernels compiled by a child process (started here if need be) and wait for it.

    Returns '' once they are cached (the caller loads them in about a second), else why no child cached
    them (the caller then compiles in its own process). Raises :class:`tofcore.Cancelled` as soon as
    ``cancel()`` turns True; the child goes on compiling.
    """
    why_not = start()
    if why_not:
        return why_not
    while running():
        if cancel():
            raise Cancelled("cancelled while the compiled tracer compiles (the compile goes on in the "
                            "background, for the next render)")
        time.sleep(POLL_S)
    return _outcome()


def compile_aside(cancel) -> str:
    """For a trace with ``cancel``: uncached CPU kernels compiled by the child (:func:`wait`); what happened,
    in words for ``stats["transport"]["compile"]`` ('' when they were cached)."""
    from . import cpu_kernels_cached

    if cpu_kernels_cached() is not False:
        return ""
    start_s = time.perf_counter()
    why_not = wait(cancel)
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
