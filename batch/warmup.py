"""The kernels a run's workers use, compiled once before they start (issue 33, item 3, "Cold start").

A worker process loads the tracer's compiled kernels from the caches (numba's for the CPU kernels and the BVH
build, numba-cuda's and CuPy's on a GPU), or, where they are not there yet, compiles them itself: on a cold
cache every worker of a run compiled the same kernels at the same time (2 H100s: 31 s per worker, 1.28× instead
of 1.7× from the second GPU; a CPU run with several local workers ~40 s of compile each on 2 cores). So before
the workers start, :func:`warm_up` has them compiled once, by one child process running
``python -m tofcore warmup --device cpu|gpu`` (:func:`tofcore.cli.cmd_warmup`), and the workers load them.

When (:func:`plan_warmup`):

=========================  ===================================================================================
GPU workers                always, on the run's first GPU (the child's ``CUDA_VISIBLE_DEVICES``; this process
                           initialises no CUDA). Whether the caches hold this GPU's kernels cannot be told
                           without CUDA: numba-cuda's index keys each kernel by the GPU's compute capability and
                           CuPy names its files by a hash of the kernel's source and architecture. With filled
                           caches the child loads them and ends (a fresh process's first frame, GPU: to be
                           measured), against the ~31 s it saves each worker of a cold one.
CPU workers                only where :func:`tofcore.compiled.cpu_warm` is False (the cache's index files read
                           here: numba imported, nothing compiled, ~0.7 s on 2 cores).
one worker                 skipped: it compiles what it needs once anyway; a child first would share nothing.
``TOFCORE_TRACER=numpy``,  skipped on the CPU: nothing compiles (a GPU still compiles CuPy's kernels).
no numba (CPU)
a cache that cannot be     skipped, one line: numba keeps nothing, each worker compiles again whatever the
used (CPU)                 child does.
a Dask cluster             skipped (``--scheduler`` or a caller's executor): its workers run on other machines
                           with their own caches; run ``tofcore warmup`` on each.
in-process (Blender)       skipped: one process renders; its first render compiles what it needs.
=========================  ===================================================================================

A warm-up that fails (exit status, timeout, no Python) costs one line and the run goes on: the workers compile
for themselves. The lines say what is compiled, for how many workers, and how long it took.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from .devices import VISIBLE_ENV, DevicePlan, fake_gpu

WARMUP_TIMEOUT_S = 900.0
"""Seconds the warm-up child may take (the CPU kernels compiled in 128–183 s on a busy 2-core machine in
Blender's Python, docs/blender.md): past them it is stopped and the workers compile for themselves."""


def warmup_command(python: str, device: str) -> list[str]:
    """The child's command line: tofcore's warm-up of ``device`` (``"cpu"`` or ``"gpu"``)."""
    return [python, "-m", "tofcore", "warmup", "--device", device]


@dataclass(frozen=True)
class WarmUp:
    """The warm-up child to run: its device, command line, environment and the workers it serves."""

    device: str                       # "cpu" or "gpu"
    command: tuple[str, ...]
    env: dict
    workers: int
    gpu: str | None = None            # the CUDA_VISIBLE_DEVICES id it runs on (a GPU warm-up)

    def start_line(self) -> str:
        where = f" on GPU {self.gpu}" if self.gpu is not None else ""
        what = "the GPU kernels (numba-cuda and CuPy)" if self.device == "gpu" else "the CPU kernels (numba)"
        return (f"kernel warm-up: compiling {what} once for the {self.workers} workers (`python -m tofcore "
                f"warmup --device {self.device}`{where}); the workers then load them …")


def cpu_warmup_needed(env: Mapping[str, str]) -> tuple[bool, str]:
    """(whether the CPU workers' kernels need compiling, a line saying why they cannot be cached, or '')."""
    if env.get("TOFCORE_TRACER", "").strip().lower() == "numpy":
        return False, ""  # the NumPy tracer on the CPU compiles nothing
    from tofcore import compiled

    warm = compiled.cpu_warm()
    if warm is None or warm:
        return False, ""  # no numba (nothing compiles), or everything is cached
    problem = compiled.cache_problem()  # numba keeps nothing: each worker compiles whatever a child does
    return not problem, (f"kernel warm-up skipped: {problem}" if problem else "")


def plan_warmup(devices: DevicePlan, *, executor: str, workers: int,
                env: Mapping[str, str] | None = None) -> tuple[WarmUp | None, str]:
    """The warm-up a run needs before its workers start (module docstring), or None; and a line to log when the
    reason for none is worth saying ('' otherwise).

    ``executor``: ``"local"``, ``"dask-local"``, ``"cluster"`` or ``"inline"`` (as :func:`batch.devices.plan_devices`
    takes it); ``workers``: the worker processes that will render (no more than the views to render).
    """
    env = dict(os.environ if env is None else env)
    if executor not in ("local", "dask-local"):
        return None, ""  # a cluster's workers are other machines (their own caches); in-process: one process
    if workers < 2:
        return None, ""  # one worker compiles once anyway
    gpu = devices.gpus[0] if devices.gpus and not fake_gpu(env) else None  # the stand-in's workers use the CPU
    if gpu is None:
        needed, why_not = cpu_warmup_needed(env)
        if not needed:
            return None, why_not
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join([root] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    if gpu is not None:
        env[VISIBLE_ENV] = gpu
    device = "gpu" if gpu is not None else "cpu"
    return WarmUp(device, tuple(warmup_command(sys.executable, device)), env, workers, gpu), ""


def warm_up(warm: WarmUp, log: Callable[[str], None], *, timeout_s: float = WARMUP_TIMEOUT_S) -> bool:
    """Run the warm-up child and wait for it, saying what it does and how it ended; whether it succeeded.

    A Ctrl-C or SIGTERM meanwhile (the run's :class:`batch.run.Interrupted`) stops the child and goes on up.
    """
    log(warm.start_line())
    started = time.perf_counter()
    try:
        proc = subprocess.run(list(warm.command), env=warm.env, stdin=subprocess.DEVNULL, capture_output=True,
                              text=True, errors="replace", timeout=timeout_s)
    except subprocess.TimeoutExpired:
        why = f"it took more than {timeout_s:.0f} s and was stopped"
    except OSError as exc:
        why = f"{warm.command[0]} could not be started ({exc.strerror or exc})"
    else:
        seconds = time.perf_counter() - started
        said = [line.strip() for line in proc.stdout.splitlines() if line.strip()]
        if proc.returncode == 0:
            log(f"kernel warm-up done in {seconds:.1f} s" + (f": {said[-1]}" if said else ""))
            return True
        errors = [line.strip() for line in proc.stderr.splitlines() if line.strip()]
        why = f"exit status {proc.returncode}" + (f": {errors[-1]}" if errors else "")
    log(f"kernel warm-up failed after {time.perf_counter() - started:.1f} s ({why}): each worker compiles the "
        f"kernels itself")
    return False
