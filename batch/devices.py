"""Render devices for a batch run: which GPUs are visible, one worker per GPU, and the CPU fall-back.

``tofcore-batch run --device cpu|gpu|auto`` (also ``compare`` and the Blender entry):

==========  ============================================================================================
``cpu``     NumPy in every worker (the default); ``--workers N`` processes
``gpu``     CuPy: one local worker process per visible GPU, each pinned to its GPU by
            ``CUDA_VISIBLE_DEVICES=<id>`` set in the worker before anything there touches CUDA;
            frames go to whichever GPU is free. No GPU, or no CuPy: a one-line error, exit code 2,
            nothing rendered. A GPU failure during a frame (out of memory, CUDA error) fails that
            frame with one line in its record; ``--retry-failed`` renders it again.
``auto``    as ``gpu`` when a GPU and CuPy are there; otherwise the CPU (``--workers`` processes),
            saying why, and every record stores the reason. A frame whose GPU render fails is
            rendered again on the CPU, the reason recorded.
==========  ============================================================================================

Finding the GPUs (:func:`visible_gpus`) never initialises CUDA in the batch process — it starts
workers, and a CUDA context there would be wasted memory on GPU 0 and unsafe to fork:
``CUDA_VISIBLE_DEVICES``, when set, gives the ids (:func:`parse_visible_devices`: ordinals or
``GPU-``/``MIG-`` UUIDs; empty = no GPU), and a short-lived child process checks them with
:func:`tofcore.backend.gpu_count` (no CuPy, or an id CUDA cannot find, is caught before any worker
starts); without the variable the child counts the devices (and, when it finds none, says why).
``--workers`` with a GPU plan defaults to the number of GPUs; a smaller value uses the first ones,
a larger one is clamped to one worker per GPU (with a message).

Executors: the local pool pins its workers (:func:`batch.worker.init_worker`); ``--dask local``
starts one LocalCluster worker per GPU with ``CUDA_VISIBLE_DEVICES`` in its environment (as
dask-cuda's ``LocalCUDACluster`` does); on an existing cluster (``--scheduler``) the device is only
passed through: start each Dask worker with its own GPU, e.g.
``CUDA_VISIBLE_DEVICES=1 dask worker tcp://HOST:8786 --nworkers 1 --nthreads 1`` (or
``dask cuda worker``, which does that for every GPU of a machine). In-process (Blender) the
process's own GPU is used.

Test stand-in: with ``TOF_BATCH_FAKE_GPU=1`` in the environment, no child process checks the GPUs
(``CUDA_VISIBLE_DEVICES`` must name them) and the workers render on the CPU (``device`` recorded as
the CPU, requested ``gpu``/``auto``, the reason naming the variable), while the parsing of
``CUDA_VISIBLE_DEVICES``, the clamping and the per-worker pinning run as on a GPU machine.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from tofcore.backend import DEVICES, GpuUnavailable
from tofcore.errors import ConfigError

VISIBLE_ENV = "CUDA_VISIBLE_DEVICES"
FAKE_GPU_ENV = "TOF_BATCH_FAKE_GPU"

_UUID = re.compile(r"^(GPU|MIG)-[0-9A-Za-z/\-]+$")

# Run in a child process: the parent must not create a CUDA context. Prints one JSON line. CuPy alone
# counts the devices (importing tofcore, a second or so, is left out of every GPU run's start); only when
# it finds none does tofcore's backend say why, in its words.
_PROBE = """
import json
try:
    import cupy
    count = int(cupy.cuda.runtime.getDeviceCount())
except Exception:
    count = 0
reason = None
if count == 0:
    from tofcore import backend
    try:
        backend.select_device("gpu")
        reason = "CUDA reports no device"
    except backend.GpuUnavailable as exc:
        reason = str(exc)
print(json.dumps({"count": count, "reason": reason}))
"""


def parse_visible_devices(value: str) -> list[str]:
    """The GPUs a ``CUDA_VISIBLE_DEVICES`` value makes visible, as the ids to pin workers with.

    CUDA's rules: comma-separated ordinals (``"0,2"``) or UUIDs (``"GPU-8a1b…"``, ``"MIG-…"``);
    an empty value hides every GPU; the list ends at the first invalid entry (``"-1"``, ``"none"``,
    an empty item), which is how ``"-1"`` hides them all. Spaces around entries are ignored and a
    repeated entry is kept once (one worker per GPU).
    """
    ids: list[str] = []
    for item in value.split(","):
        entry = item.strip()
        if not (entry.isdigit() or _UUID.match(entry)):
            break
        if entry not in ids:
            ids.append(entry)
    return ids


@dataclass(frozen=True)
class VisibleGpus:
    """GPU ids a worker can be pinned to, where they came from, why there are none, and a note for the log."""

    ids: tuple[str, ...]
    source: str
    reason: str | None = None
    note: str | None = None
    probe_s: float | None = None   # seconds the child process took (None: no child was asked)


def fake_gpu(env: Mapping[str, str] | None = None) -> bool:
    """Whether the test stand-in is on (``TOF_BATCH_FAKE_GPU`` set and not ``0``/empty)."""
    value = (os.environ if env is None else env).get(FAKE_GPU_ENV, "")
    return value.strip() not in ("", "0")


def visible_gpus(env: Mapping[str, str] | None = None, probe_timeout_s: float = 120.0) -> VisibleGpus:
    """The GPUs this process's children can use, found without initialising CUDA in this process.

    With ``CUDA_VISIBLE_DEVICES`` set, its entries are the ids (:func:`parse_visible_devices`; an
    empty value or ``-1``: none, and no child process is needed); a short-lived child process then
    checks them with CUDA: no CuPy or no device gives none, with the reason; fewer devices than
    entries keeps the first ones (CUDA stops at the first entry it cannot find, or that names a GPU
    already listed: ``"0,GPU-<uuid of 0>"`` is one GPU). Without the variable, the child counts the
    devices: ordinals ``0 … n−1``. The test stand-in asks no child.
    """
    env = os.environ if env is None else env
    value = env.get(VISIBLE_ENV)
    started = time.perf_counter()
    if value is None:
        count, reason = _probe(env, probe_timeout_s)
        return VisibleGpus(tuple(str(i) for i in range(count)), f"a CuPy probe ({VISIBLE_ENV} not set)",
                           reason if count == 0 else None, probe_s=time.perf_counter() - started)
    ids = tuple(parse_visible_devices(value))
    if not ids:
        reason = f"{VISIBLE_ENV} is empty" if not value.strip() else f"{VISIBLE_ENV}={value!r} names no GPU"
        return VisibleGpus((), VISIBLE_ENV, reason)
    if fake_gpu(env):
        return VisibleGpus(ids, VISIBLE_ENV)
    count, reason = _probe(env, probe_timeout_s)
    source = f"{VISIBLE_ENV}, checked by a CuPy probe"
    probe_s = time.perf_counter() - started
    if count == 0:
        return VisibleGpus((), source, f"{VISIBLE_ENV}={value!r}: {reason}", probe_s=probe_s)
    note = None
    if count < len(ids):
        note = (f"{VISIBLE_ENV}={value!r}: CUDA uses {count} of its {len(ids)} entries (it stops at the first "
                f"it cannot find or already has): using {', '.join(ids[:count])}")
    return VisibleGpus(ids[:count], source, note=note, probe_s=probe_s)


def _probe(env: Mapping[str, str], timeout_s: float) -> tuple[int, str | None]:
    """(CUDA devices a child process with ``env`` sees, why none when 0); this process touches no CUDA."""
    child_env = dict(env)
    root = str(Path(__file__).resolve().parents[1])
    child_env["PYTHONPATH"] = os.pathsep.join([root] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    try:
        proc = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, env=child_env,
                              timeout=timeout_s)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return 0, f"GPU discovery failed ({type(exc).__name__}: {exc})"
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        detail = (proc.stderr.strip().splitlines() or [f"exit code {proc.returncode}"])[-1]
        return 0, f"GPU discovery failed ({detail})"
    answer = json.loads(lines[-1])
    return int(answer["count"]), answer.get("reason")


@dataclass(frozen=True)
class DevicePlan:
    """How a run uses devices; made by :func:`plan_devices`, carried to the workers by the view tasks.

    Attributes
    ----------
    requested : ``"cpu"``, ``"gpu"`` or ``"auto"`` (what the user asked for).
    render : the ``device`` each worker passes to ``tofcore.render`` (``"cpu"``, ``"gpu"``, ``"auto"``).
    gpus : ``CUDA_VISIBLE_DEVICES`` ids, one pinned worker each; empty: no pinning.
    fallback_reason : ``"auto"`` chose the CPU for the whole run, and why (workers record it).
    workers : worker processes (local pool or LocalCluster).
    notes : lines for the log (where the GPUs came from, a clamped ``--workers``, the fall-back).
    """

    requested: str
    render: str
    gpus: tuple[str, ...] = ()
    fallback_reason: str | None = None
    workers: int = 1
    notes: tuple[str, ...] = ()


CPU_THREADS_PER_FRAME = 4
"""Tracer threads per frame when a CPU batch chooses its own frames × threads (``--workers`` not given).

One frame does not keep a many-core machine busy: on the 16-core GPU host a frame on 16 numba threads ran
at 71 % parallel efficiency, on 4 threads at 78 % (docs/benchmarks.md, "CPU tracer"), and part of every
frame (set-up, decoding, writing) runs on one thread. So a batch renders ``cpus // 4`` frames at once
with 4 threads each (measured on that host: docs/benchmarks.md, "Batch")."""


def cpu_frames_and_threads(cpus: int, frames: int) -> tuple[int, int]:
    """Frames rendered at once and tracer threads each, for a CPU batch that chooses them itself.

    ``workers = clamp(cpus // CPU_THREADS_PER_FRAME, 1, frames)``, ``threads = max(1, cpus // workers)``:
    2 cores → 1 frame × 2 threads; 16 cores → 4 × 4; 16 cores and 2 frames → 2 × 8.
    """
    workers = max(1, min(cpus // CPU_THREADS_PER_FRAME, frames))
    return workers, max(1, cpus // workers)


def plan_devices(device: str, *, executor: str, workers: int | None = None,
                 env: Mapping[str, str] | None = None) -> DevicePlan:
    """Decide where frames render.

    Parameters
    ----------
    device : ``"cpu"``, ``"gpu"`` or ``"auto"``.
    executor : ``"local"`` (process pool), ``"dask-local"`` (LocalCluster), ``"cluster"`` (an existing
        Dask scheduler or a caller's executor: the device is passed through) or ``"inline"`` (this process).
    workers : ``--workers``; None: 1 on the CPU, one per GPU with a GPU plan.

    Raises
    ------
    GpuUnavailable : ``device="gpu"`` and no usable GPU (one line naming the cause).
    """
    if device not in DEVICES:
        raise ConfigError(f"--device must be one of {list(DEVICES)}, got {device!r}")
    cpu_workers = workers or 1
    if device == "cpu":
        return DevicePlan("cpu", "cpu", workers=cpu_workers)
    if executor == "cluster":
        return DevicePlan(device, device, workers=cpu_workers, notes=(
            f"device {device}: each Dask worker renders on the GPU its own {VISIBLE_ENV} shows; start one "
            f"worker per GPU (e.g. `{VISIBLE_ENV}=0 dask worker ADDRESS --nworkers 1 --nthreads 1`, or "
            f"`dask cuda worker ADDRESS`)",))
    if executor == "inline":
        return _plan_inline(device, cpu_workers)
    found = visible_gpus(env)
    if not found.ids:
        if device == "gpu":
            raise GpuUnavailable(f"--device gpu: no usable GPU: {found.reason}; use --device cpu or auto")
        return DevicePlan("auto", "auto", fallback_reason=found.reason, workers=cpu_workers,
                          notes=(f"device auto: no usable GPU ({found.reason}); rendering on the CPU",))
    gpus = found.ids
    notes = ([found.note] if found.note else []) + [
        f"device {device}: {len(gpus)} GPU(s) visible ({VISIBLE_ENV} {', '.join(gpus)}; from {found.source}"
        f"{'' if found.probe_s is None else f' in {found.probe_s:.1f} s'}): one worker process per GPU"]
    if workers is not None and workers < len(gpus):
        notes.append(f"--workers {workers}: using the first {workers} of {len(gpus)} GPU(s)")
        gpus = gpus[:workers]
    elif workers is not None and workers > len(gpus):
        notes.append(f"--workers {workers} clamped to {len(gpus)}: one worker per GPU")
    if fake_gpu(env):
        notes.append(f"{FAKE_GPU_ENV} is set: a test stand-in, the workers render on the CPU")
    return DevicePlan(device, device, gpus=tuple(gpus), workers=len(gpus), notes=tuple(notes))


def _plan_inline(device: str, workers: int) -> DevicePlan:
    """This process renders (Blender): it may use CUDA itself, so ask the backend directly."""
    from tofcore.backend import select_device

    if fake_gpu():
        return DevicePlan(device, device, workers=workers,
                          notes=(f"{FAKE_GPU_ENV} is set: a test stand-in, rendering on the CPU",))
    try:
        chosen = select_device(device)
    except GpuUnavailable as exc:
        raise GpuUnavailable(f"--device gpu: no usable GPU: {exc}; use --device cpu or auto") from None
    if chosen.fallback_reason is not None:
        return DevicePlan(device, device, fallback_reason=chosen.fallback_reason, workers=workers,
                          notes=(f"device auto: no usable GPU ({chosen.fallback_reason}); rendering on the CPU",))
    return DevicePlan(device, device, workers=workers, notes=(f"device {device}: {chosen.description}",))


def render_device(requested: str, fallback_reason: str | None = None, env: Mapping[str, str] | None = None):
    """What a worker passes to ``tofcore.render``: the requested name, or the CPU with a reason.

    The CPU when the run's plan fell back (``fallback_reason``) or under the test stand-in.
    """
    from tofcore.backend import cpu_device

    if requested == "cpu":
        return "cpu"
    if fallback_reason is not None:
        return cpu_device(requested, fallback_reason)
    if fake_gpu(env):
        return cpu_device(requested, f"{FAKE_GPU_ENV} is set: a test stand-in for the GPU, rendered on the CPU")
    return requested


def is_gpu_error(exc: BaseException) -> bool:
    """A GPU failure: :class:`~tofcore.backend.GpuUnavailable`, or a raw CuPy/CUDA exception."""
    module = type(exc).__module__ or ""
    return isinstance(exc, GpuUnavailable) or module.startswith(("cupy", "cupy_backends", "cupyx"))


def gpu_error_line(exc: BaseException) -> str:
    """One line naming a GPU failure (no traceback): what the record's ``error`` says."""
    text = str(exc).strip()
    first = text.splitlines()[0] if text else ""
    if isinstance(exc, GpuUnavailable):
        return f"{type(exc).__name__}: {first}"
    if "OutOfMemory" in type(exc).__name__:
        return f"GpuUnavailable: GPU: out of device memory ({first or type(exc).__name__})"
    return f"GpuUnavailable: GPU: CUDA error ({type(exc).__name__}: {first})"
