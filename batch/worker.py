"""What a worker does with a view task: load or export the scene once, render every preset, write the frames.

:func:`run_view` is the function executors call (local process pool, Dask, or
in-process inside Blender). It never raises for a frame's failure: every job
gives a record (:mod:`batch.dataset`), ``status`` ``"ok"`` or ``"failed"``
with the error text.

Frame folders are written all or nothing, and published once: the frame is
rendered, then written into ``frames/.<job_id>.partial-XXXXXXXX/`` (``tofcore.write_frame``,
every file atomic, ``frame.json`` last), then ``record.json`` is written there,
then the folder is renamed to ``frames/<job_id>/`` by :func:`batch.dataset.publish`,
which never replaces a published folder. A folder named after a job is
therefore complete and written by exactly one execution of the job; a second
execution (a Dask retry, a duplicate task) deletes its own folder and reports
the published record. A killed worker leaves only a ``.partial-`` folder, which
the next run removes.

Writing is off the render's path: :func:`render_frame` renders, :func:`write_frame`
writes, and a worker hands each rendered frame to a writer thread (:class:`batch.writer.FrameWriter`,
a bounded queue: rendering waits when the writer falls behind) and renders the next
frame meanwhile. :func:`run_view` (Dask, in-process) returns when its view's frames
are written; the local pool's workers run :func:`start_view`, which returns as soon
as the view is rendered with the records written so far, and :func:`finish_writes`
at the end, so that a view's frames are written while the next view renders. The
parent indexes only records the worker reported, so a frame is indexed only once it
is published.

Devices (:mod:`batch.devices`): every render gets the task's ``device``
(``"cpu"``, ``"gpu"``, ``"auto"``; the CPU with the reason when the run's plan
fell back). A GPU worker of the local pool is pinned to one GPU by
:func:`init_worker`, which sets ``CUDA_VISIBLE_DEVICES`` first thing in the new
process (nothing has touched CUDA yet: CUDA reads the variable when it
initialises, at the first render). The record stores ``device`` (the frame's
``stats["device"]``: name, description, requested, fallback_reason) and
``cuda_visible_devices`` (this process's value, for GPU and auto renders). A GPU
failure (``GpuUnavailable``: no CuPy or device, out of memory, CUDA errors;
raw CuPy exceptions are converted) fails the frame with one line and no
traceback; with ``auto`` the frame is rendered again on the CPU and the reason
recorded.

Timing: every record has ``timing``, where its worker's time went (epoch seconds and durations):
``worker_started`` (the parent started the process), ``task_started`` (the worker took the view),
``load_s`` (scene load or export, with the first import of tofcore; 0 for the view's later frames),
``render_started``, ``render_s`` (``tofcore.render``: in a process's first GPU frame this includes
importing CuPy, the CUDA context and compiling or loading the kernels), ``handoff_wait_s`` (the
render thread waited for room in the writer's queue), ``write_started`` and ``write_s`` (on the
writer thread: error metrics and the frame's files, up to ``record.json``) and ``finished``.
:func:`batch.timing.worker_timing` sums them up per worker at the end of a run.

Fault injection for tests: ``TOF_BATCH_FAIL`` holds comma-separated
:mod:`fnmatch` patterns; a job whose id or label (``scene/view/preset``)
matches one raises before rendering. A pattern written ``gpu:PATTERN`` raises a
one-line ``GpuUnavailable`` instead, in place of a GPU or auto render (what an
out-of-memory GPU does), so the GPU failure paths run on machines without one
(with ``TOF_BATCH_FAKE_GPU``, :mod:`batch.devices`). ``write:PATTERN`` fails the
frame's writing with a full disk's ``OSError`` after its files are written (before
``record.json``), ``kill-write:PATTERN`` kills the worker there with SIGKILL (a crash
in the middle of writing a frame).
"""

from __future__ import annotations

import errno
import fnmatch
import functools
import gc
import json
import os
import secrets
import shutil
import signal
import socket
import sys
import threading
import time
import traceback
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from . import dataset as ds
from .devices import VISIBLE_ENV, gpu_error_line, is_gpu_error, render_device
from .file_hashes import file_sha256
from .jobs import Job, ViewTask
from .writer import FrameWriter

FAIL_ENV = "TOF_BATCH_FAIL"

# The last scene loaded in this process: views of the same demo/npz scene reuse it (and its BVH).
_SCENE_CACHE: dict = {}
# Sensors built in this process, by their JSON description (:func:`_sensor`); the oldest goes first.
_SENSOR_CACHE: dict = {}
_SENSOR_CACHE_SIZE = 8
# This process's frame writer for :func:`start_view` (the local pool), made at the first view.
_WRITER: FrameWriter | None = None
# How long a stopped worker waits for its writer to finish the frames it holds before it exits.
_STOP_WRITER_WAIT_S = 5.0
# Set by SIGTERM in a pool worker that is rendering: the render is cancelled between ray chunks, the
# half-written folder removed, and the process exits (nothing is recorded). An idle worker exits at once.
_STOP = threading.Event()
_BUSY = threading.Event()
_EXIT_STOPPED = 143
# When this process was started (epoch seconds; :func:`init_worker`): the start of the worker's timeline.
_WORKER_STARTED = time.time()


def _on_sigterm(signum, frame) -> None:
    if not _BUSY.is_set():
        _exit_stopped()
    _STOP.set()


def _exit_stopped() -> None:
    """Exit at once (code 143), first stopping this process's tracer pool if it has one.

    ``os._exit`` skips the pool's clean-up: its semaphores would stay registered, and Python's
    resource tracker would print a "leaked semaphore objects" warning on the run's stderr at the end.
    The frames handed to this process's writer are written first (at most a few seconds): they are
    rendered, and published they are indexed by the parent (or read back by the next run).
    """
    if _WRITER is not None and threading.current_thread() is not _WRITER.thread:
        _WRITER.drain(timeout=_STOP_WRITER_WAIT_S)
    workers = sys.modules.get("tofcore.tracer.workers")
    if workers is not None:
        def stop() -> None:
            workers.shutdown()
            gc.collect()  # the pool's queues are freed: their semaphores are unlinked and unregistered

        stopper = threading.Thread(target=stop, daemon=True)
        stopper.start()
        stopper.join(timeout=5.0)
    os._exit(_EXIT_STOPPED)


class JobError(RuntimeError):
    """A job cannot be rendered for a reason the user can fix (changed file, missing camera …)."""


class WorkerDied(RuntimeError):
    """A local pool's worker process ended while it rendered a view (``kill -9``, the out-of-memory killer).

    Raised in the parent (:class:`batch.run.LocalExecutor`); ``pid`` and ``gpu`` name the worker.
    """

    def __init__(self, message: str, *, pid: int | None = None, gpu: str | None = None):
        super().__init__(message)
        self.pid = pid
        self.gpu = gpu


# --------------------------------------------------------------------------- worker process set-up

def init_worker(parent_pid: int | None = None, gpu: str | None = None, launched: float | None = None) -> None:
    """Process-pool initializer: pin the worker to its GPU, leave Ctrl-C to the parent, exit if the parent dies.

    ``gpu`` (a ``CUDA_VISIBLE_DEVICES`` id, ``--device gpu``/``auto``): made
    this process's only visible GPU before anything in it uses CUDA (CUDA
    reads the variable when it initialises), so N workers render on N GPUs.
    ``launched``: when the parent started this process (epoch seconds), the
    start of the worker's timeline (its records' ``timing["worker_started"]``).

    The terminal sends SIGINT to the whole process group; the parent stops the
    workers itself. A parent killed with SIGKILL cannot: a watchdog thread
    ends the worker within a second of the parent's death, so no orphan keeps
    writing into the dataset.
    """
    global _WORKER_STARTED
    _WORKER_STARTED = time.time() if launched is None else launched
    if gpu is not None:
        os.environ[VISIBLE_ENV] = gpu
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # The parent starts workers with SIGINT blocked (batch.run.sigint_held), so that a Ctrl-C during
    # their start-up stays pending instead of printing a KeyboardInterrupt; ignored now, it is dropped.
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    signal.signal(signal.SIGTERM, _on_sigterm)
    if parent_pid is None:
        return

    def watch() -> None:
        while True:
            if os.getppid() != parent_pid:
                os._exit(3)
            time.sleep(0.5)

    threading.Thread(target=watch, name="parent-watchdog", daemon=True).start()


# --------------------------------------------------------------------------- scenes

def _load_scene(task: ViewTask):
    """(scene, world_from_sensor, ambient, warnings) of a view; demo and npz scenes are cached per process."""
    import tofcore

    source = task.source
    ambient = tofcore.Ambient(radiance_w_m2_sr=task.ambient_w_m2_sr) if task.ambient_w_m2_sr else None
    pose = None if task.world_from_sensor is None else np.asarray(task.world_from_sensor, dtype=np.float64)
    if source["kind"] == "blend":
        _check_unchanged(source)
        scene, camera_pose, file_ambient, warnings = _export_blend(
            source["path"], camera=task.view.get("camera"), frame=task.view.get("frame"))
        if pose is None:
            if camera_pose is None:
                raise JobError(f"{source['path']}: the exporter gave no camera pose for {task.view['label']}")
            pose = np.asarray(camera_pose, dtype=np.float64)
        if task.ambient_w_m2_sr is None:
            ambient = file_ambient
        return scene, pose, ambient, warnings
    key = (source["kind"], source.get("name"), source.get("sha256"))
    if key not in _SCENE_CACHE:
        _SCENE_CACHE.clear()
        if source["kind"] == "demo":
            _SCENE_CACHE[key] = tofcore.demo_scene(source["name"])
        elif source["kind"] == "mesh":
            from tofcore.scene.mesh_files import load_mesh

            _check_unchanged(source)
            _SCENE_CACHE[key] = load_mesh(source["path"])
        else:
            _check_unchanged(source)
            _SCENE_CACHE[key] = tofcore.Scene.load(source["path"])
    return _SCENE_CACHE[key], pose, ambient, []


def _export_blend(path: str, *, camera: str | None, frame: int | None):
    """The add-on's export of one view: in this process when bpy may be used here, else in a child process.

    bpy works only from a process's main thread (elsewhere it crashes the
    process): a local pool worker exports in-process and keeps the file open
    for the next view; a Dask worker, whose tasks run on other threads,
    starts ``python -m batch.blend export`` and reads back the pickled result.
    """
    if threading.current_thread() is threading.main_thread():
        from . import blend

        return blend.export_view(path, camera=camera, frame=frame)
    import pickle
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory(prefix="tofbatch-export-") as tmp:
        out = Path(tmp) / "export.pickle"
        cmd = [sys.executable, "-m", f"{__package__}.blend", "export", path, "--out", str(out)]
        if camera is not None:
            cmd += ["--camera", camera]
        if frame is not None:
            cmd += ["--frame", str(frame)]
        env = dict(os.environ)
        root = str(Path(__file__).resolve().parents[1])
        env["PYTHONPATH"] = os.pathsep.join([root] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if proc.returncode != 0 or not out.is_file():
            tail = "\n".join(proc.stderr.strip().splitlines()[-5:]) or f"exit code {proc.returncode}"
            raise JobError(f"{path}: exporting {camera or 'the view'} at frame {frame} failed:\n{tail}")
        return pickle.loads(out.read_bytes())


def _check_unchanged(source: dict) -> None:
    path = source["path"]
    if not os.path.isfile(path):
        raise JobError(f"{path}: scene file not found (is the dataset's file system shared with this worker?)")
    if file_sha256(path) != source["sha256"]:
        raise JobError(f"{path}: the file changed after the set was read (SHA-256 differs); rerun to "
                       f"render the new version as new jobs")


# --------------------------------------------------------------------------- one job

def _maybe_fail(job: Job, gpu: bool = False, write: bool = False) -> None:
    """Raise for a job matched by ``TOF_BATCH_FAIL``.

    A plain pattern raises before the render. ``gpu:``-patterns (checked with ``gpu=True``, inside a
    GPU or auto render) raise a one-line ``GpuUnavailable``, as a failing GPU does. The write
    patterns are checked with ``write=True``, after the frame's files are written and before its
    ``record.json`` and the publishing rename: ``write:`` raises a full disk's ``OSError``,
    ``kill-write:`` kills the worker process with SIGKILL (a crash in the middle of writing).
    """
    from tofcore.backend import GpuUnavailable

    patterns = [p.strip() for p in os.environ.get(FAIL_ENV, "").split(",") if p.strip()]
    for pattern in patterns:
        kind, _, glob = pattern.partition(":")
        if kind not in ("gpu", "write", "kill-write"):
            kind, glob = "", pattern
        if (kind == "gpu") != gpu or (kind in ("write", "kill-write")) != write \
                or not (fnmatch.fnmatchcase(job.job_id, glob) or fnmatch.fnmatchcase(job.label, glob)):
            continue
        if kind == "gpu":
            raise GpuUnavailable(f"GPU: fault injected by {FAIL_ENV}={pattern!r}")
        if kind == "write":
            raise OSError(errno.ENOSPC, f"No space left on device (fault injected by {FAIL_ENV}={pattern!r})")
        if kind == "kill-write":
            os.kill(os.getpid(), signal.SIGKILL)
        raise RuntimeError(f"fault injected by {FAIL_ENV}={pattern!r}")


def _rms(values: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(np.square(values, dtype=np.float64)))) if values.size else None


def frame_metrics(frame) -> dict:
    """Error figures of a frame against its ground truth (metres; None where nothing is valid).

    ``rms_depth_error_m`` and ``median_abs_depth_error_m``: depth − gt_depth over
    the valid pixels with a ground truth; ``multipath_rms_m``: RMS of
    distance − direct_distance (what multipath adds, noise included) over the
    valid pixels; ``valid_fraction``: share of valid pixels.
    """
    valid = np.asarray(frame.valid, dtype=bool)
    depth = np.asarray(frame.depth, dtype=np.float64)
    error = depth - np.asarray(frame.gt_depth, dtype=np.float64)
    with_gt = valid & np.isfinite(error)
    multipath = np.asarray(frame.distance, np.float64) - np.asarray(frame.direct_distance, np.float64)
    with_direct = valid & np.isfinite(multipath)
    return {
        "valid_fraction": float(valid.mean()),
        "rms_depth_error_m": _rms(error[with_gt]),
        "median_abs_depth_error_m": float(np.median(np.abs(error[with_gt]))) if with_gt.any() else None,
        "multipath_rms_m": _rms(multipath[with_direct]),
    }


def _base_record(job: Job, task: ViewTask) -> dict:
    return {
        "job_id": job.job_id, "status": None, "scene": job.scene, "source": job.source, "view": job.view,
        "preset": job.preset, "sensor_name": job.sensor.get("name"), "seed": job.seed, "set_seed": job.set_seed,
        "settings": {**job.quality, "resolution_scale": job.resolution_scale,
                     "ambient_w_m2_sr": job.ambient_w_m2_sr, "formats": list(job.formats), **job.output,
                     "width": job.sensor["camera"]["width"], "height": job.sensor["camera"]["height"]},
        "world_from_sensor": job.world_from_sensor, "host": socket.gethostname(), "pid": os.getpid(),
        # Replaced by the frame's stats["device"] once rendered; what was asked for until then.
        "device": {"name": None, "description": None, "requested": task.device,
                   "fallback_reason": task.fallback_reason},
        "cuda_visible_devices": None if task.device == "cpu" else os.environ.get(VISIBLE_ENV),
    }


def _sensor(job: Job):
    """The job's ``tofcore.Sensor``, built once per process and preset description.

    Building a sensor checks its camera's distortion over the whole image (the Kinect v2's undistortion
    table: about 0.4 s on a 2-core machine); the jobs of a set share a few sensor descriptions.
    """
    import tofcore

    key = json.dumps(job.sensor, sort_keys=True)
    sensor = _SENSOR_CACHE.get(key)
    if sensor is None:
        if len(_SENSOR_CACHE) >= _SENSOR_CACHE_SIZE:
            _SENSOR_CACHE.pop(next(iter(_SENSOR_CACHE)))
        sensor = _SENSOR_CACHE[key] = tofcore.Sensor.from_dict(job.sensor, where=f"preset {job.preset!r}")
    return sensor


def _render(job: Job, task: ViewTask, scene, pose: np.ndarray, ambient):
    """``tofcore.render`` on the task's device; for ``auto``, a GPU failure renders again on the CPU.

    CuPy exceptions that reach here are turned into one-line ``GpuUnavailable`` errors (the core
    does so too; this is the second line of defence), so no partial frame is ever written.
    """
    import tofcore
    from tofcore.backend import cpu_device, gpu_errors

    sensor = _sensor(job)
    q = job.quality
    settings = dict(spp=q["spp"], max_depth=q["max_depth"], seed=job.seed, time_budget_s=q["time_budget_s"],
                    target_error_m=q["target_error_m"], ambient=ambient, workers=task.render_threads,
                    cancel=_STOP.is_set, transient_bin_m=job.output.get("transient_bin_m"),
                    transient_max_m=job.output.get("transient_max_m"))
    device = render_device(task.device, task.fallback_reason)
    try:
        with gpu_errors():
            if task.device != "cpu" and task.fallback_reason is None:
                _maybe_fail(job, gpu=True)
            return tofcore.render(scene, sensor, pose, device=device, **settings)
    except Exception as exc:
        if task.device != "auto" or not is_gpu_error(exc):
            raise
        reason = gpu_error_line(exc).removeprefix("GpuUnavailable: ")
    return tofcore.render(scene, sensor, pose, device=cpu_device("auto", reason), **settings)


def render_frame(job: Job, task: ViewTask, scene, pose: np.ndarray, ambient, warnings: list[str],
                 timing: dict | None = None, drawn: dict | None = None) -> tuple[object | None, dict]:
    """Render one job: ``(frame, record so far)``, or ``(None, failed record)``; the render phase only.

    ``timing``: the record's ``timing`` so far (``worker_started``, ``task_started``, ``load_s``);
    ``render_started`` and ``render_s`` are added here. Stopped by the parent (SIGTERM), the process
    exits here; a KeyboardInterrupt or SystemExit is raised on, anything else gives the failed record.
    ``drawn``: what a randomized view drew (:mod:`batch.randomize`); the job's sensor unit is drawn here,
    and both go into the record and ``frame.json`` (``randomization``).
    """
    if drawn is not None and job.randomize and job.randomize.get("sensor"):
        from .randomize import vary_sensor

        sensor, unit = vary_sensor(job.sensor, job.randomize["sensor"], job.seed)
        job, drawn = replace(job, sensor=sensor), {**drawn, "sensor": unit}
    record = _base_record(job, task)
    timing = dict(timing or {"worker_started": _WORKER_STARTED, "task_started": time.time(), "load_s": 0.0})
    record["timing"] = timing
    started = time.perf_counter()
    try:
        _maybe_fail(job)
        timing["render_started"] = time.time()
        frame = _render(job, task, scene, pose, ambient)
        timing["render_s"] = time.perf_counter() - started
    except BaseException as exc:
        if _STOP.is_set():  # stopped by the parent: not the frame's fault, nothing recorded
            _exit_stopped()
        if not isinstance(exc, Exception):  # KeyboardInterrupt, SystemExit: stop, do not record
            raise
        return None, failed_record(job, task, exc, time.perf_counter() - started, record)
    frame.metadata["batch"] = {"job_id": job.job_id, "scene": job.scene, "view": job.view,
                               "preset": job.preset, "seed": job.seed, "set_seed": job.set_seed,
                               "source": job.source, "export_warnings": warnings}
    if drawn is not None:
        frame.metadata["randomization"] = record["randomization"] = drawn
    if job.output.get("labels"):
        from .labels import material_table

        record["materials"] = material_table(scene)
    return frame, record


def write_frame(job: Job, task: ViewTask, frame, record: dict, warnings: list[str], handoff_wait_s: float = 0.0) -> dict:
    """Write a rendered frame: metrics, files, ``record.json``, the publishing rename; the record to index.

    Runs on the worker's writer thread (:mod:`batch.writer`) or inline. Raises when the frame cannot
    be written (its staging folder is removed first; :func:`failed_record` makes the failure's record).
    Adds to ``record["timing"]``: ``handoff_wait_s`` (the render thread waited this long for room in
    the writer's queue), ``write_started`` (epoch s), ``write_s`` (metrics and files up to
    ``record.json``) and ``finished``.
    """
    import tofcore
    from tofcore.output.coverage import low_coverage

    timing = record["timing"]
    timing["handoff_wait_s"] = handoff_wait_s
    timing["write_started"] = time.time()
    begun = time.perf_counter()
    frames_dir = Path(task.dataset) / ds.FRAMES
    partial = frames_dir / f".{job.job_id}.partial-{secrets.token_hex(4)}"
    try:
        partial.mkdir(parents=True)
        formats = (*job.formats, "transient") if "transient_bin_m" in job.output else job.formats
        written = tofcore.write_frame(frame, partial, formats=formats, exr_half=job.output.get("exr_half", False),
                                      exr_channels=job.output.get("exr_channels"))
        if job.output.get("labels"):
            from .labels import write_labels

            written["labels"] = write_labels(frame, partial)
        _maybe_fail(job, write=True)
        stats = frame.stats
        convergence = stats.get("convergence", [])
        record = {**record, **{
            "status": "ok", "error": None, "device": stats.get("device", record["device"]),
            "dir": f"{ds.FRAMES}/{job.job_id}",
            "files": [ds.file_entry(kind, path) for kind, path in written.items()],
            "world_from_sensor": np.asarray(frame.world_from_sensor).tolist(),
            "render_seconds": stats.get("seconds"), "trace_seconds": stats.get("trace_seconds"),
            "spp": stats.get("spp"), "passes": len(convergence),
            "est_depth_error_m": convergence[-1].get("est_depth_error_m") if convergence else None,
            "convergence": [{k: row.get(k) for k in ("pass", "seconds", "spp", "est_depth_error_m")}
                            for row in convergence],
            "rays_per_second": stats.get("transport", {}).get("rays_per_second"),
            **frame_metrics(frame),
            "warning": low_coverage(frame),
            "objects": frame.metadata.get("objects", []),
            "export_warnings": warnings,
            # from the start of the render to record.json, waits for the writer included
            "seconds": time.time() - timing["render_started"],
            "finished": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        }}
        # The write phase ends with the publishing rename; record.json holds the time up to its own
        # writing (what is measured after it is a few system calls).
        timing["write_s"] = time.perf_counter() - begun
        timing["finished"] = time.time()
        record = ds.write_record(partial, record)
        if ds.publish(partial, frames_dir / job.job_id):
            return record
        # Published already by another execution of this job (Dask ran the view again after a worker
        # died, a duplicate task): that folder stays; this one is discarded, the published one reported.
        shutil.rmtree(partial, ignore_errors=True)
        published = ds.Dataset(task.dataset).published_record(job.job_id)
        if published is None:
            raise JobError(f"{ds.FRAMES}/{job.job_id} is already published but its {ds.RECORD} is unreadable; "
                           f"it was left as it is (the next run verifies it)")
        return published
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        timing.setdefault("write_s", time.perf_counter() - begun)
        timing.setdefault("finished", time.time())
        raise


def _write_failed(job: Job, task: ViewTask, record: dict, exc: BaseException) -> dict:
    """The record of a frame whose writing raised ``exc`` (one line for a disk error: :func:`failed_record`)."""
    seconds = time.time() - record["timing"].get("render_started", time.time())
    return failed_record(job, task, exc, seconds, record)


def render_job(job: Job, task: ViewTask, scene, pose: np.ndarray, ambient, warnings: list[str],
               timing: dict | None = None) -> dict:
    """Render and write one job in this thread; return its record (never raises for the job's own failure).

    ``timing``: the record's ``timing`` so far (``worker_started``, ``task_started``, ``load_s``); the
    render and write phases are added here.
    """
    frame, record = render_frame(job, task, scene, pose, ambient, warnings, timing)
    if frame is None:
        return record
    try:
        return write_frame(job, task, frame, record, warnings)
    except BaseException as exc:
        if _STOP.is_set():
            _exit_stopped()
        if not isinstance(exc, Exception):
            raise
        return _write_failed(job, task, record, exc)


def failed_record(job: Job, task: ViewTask, exc: BaseException, seconds: float = 0.0,
                  record: dict | None = None) -> dict:
    """The record of a job that raised ``exc``: the message, and the traceback's last lines.

    A GPU failure (:func:`batch.devices.is_gpu_error`) gives one line naming the cause and no traceback;
    so does a problem of the input or the disk (a :class:`tofcore.TofError` naming the file and key, an
    ``OSError`` such as a full disk) and a worker that died (:class:`WorkerDied`, whose record names the
    dead worker's pid and GPU): the line says it all, a traceback would only bury it.
    """
    from tofcore.errors import TofError

    record = dict(record or _base_record(job, task))
    if is_gpu_error(exc):
        error, tb = gpu_error_line(exc), None
    elif isinstance(exc, (TofError, OSError, WorkerDied)):
        error, tb = f"{type(exc).__name__}: {exc}", None
    else:
        error = f"{type(exc).__name__}: {exc}"
        tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))[-4000:]
    if isinstance(exc, WorkerDied):  # the parent makes this record: the worker's pid and GPU, not the parent's
        record.update({"pid": exc.pid, "cuda_visible_devices": exc.gpu})
    record.update({"status": "failed", "error": error,
                   "traceback": tb, "dir": None, "files": [], "seconds": seconds,
                   "finished": datetime.now(timezone.utc).isoformat(timespec="seconds")})
    return record


# --------------------------------------------------------------------------- one view

def _render_view(task: ViewTask, writer: FrameWriter) -> list[dict]:
    """Load or export the view's scene once, render each job and hand the frame to ``writer``.

    Returns the records of the jobs that failed before they reached the writer (scene load, render);
    the writer gives the others' records.
    """
    task_started = time.time()
    started = time.perf_counter()
    drawn = None
    try:
        scene, pose, ambient, warnings = _load_scene(task)
        if task.randomize is not None:
            from .randomize import build_view

            scene, pose, drawn_ambient, drawn = build_view(scene, task.randomize, task.view["randomize_seed"])
            ambient = drawn_ambient or ambient
    except Exception as exc:
        return [failed_record(job, task, exc, time.perf_counter() - started) for job in task.jobs]
    load_s = time.perf_counter() - started
    failed = []
    for job in task.jobs:
        timing = {"worker_started": _WORKER_STARTED, "task_started": task_started, "load_s": load_s}
        load_s = 0.0
        frame, record = render_frame(job, task, scene, pose, ambient, warnings, timing, drawn)
        if frame is None:
            failed.append(record)
        else:
            writer.submit(functools.partial(write_frame, job, task, frame, record, warnings),
                          functools.partial(_write_failed, job, task, record))
            del frame  # the writer holds the only reference: its arrays go when it is written
        if _STOP.is_set():  # the frames handed over are written first (their record.json is read back next run)
            writer.drain(timeout=_STOP_WRITER_WAIT_S)
            _exit_stopped()
    return failed


def run_view(task: ViewTask) -> list[dict]:
    """Render a view's jobs and write them; one record per job, every frame written when it returns.

    The frames are written on a writer thread while the next job of the view renders (a view has one
    job per preset); the call waits for the last one. Executors that can collect records later (the
    local pool) use :func:`start_view` and :func:`finish_writes`, which overlap across views too.
    """
    _BUSY.set()
    writer = FrameWriter(name="frame-writer-view")
    try:
        failed = _render_view(task, writer)
        records = failed + writer.drain()
        sys.stdout.flush()
        if _STOP.is_set():  # stopped while the last frames were written: they are published, the parent
            _exit_stopped()  # or the next run reads them back
        return records
    finally:
        writer.close()
        _BUSY.clear()


def start_view(task: ViewTask) -> list[dict]:
    """Render a view's jobs, handing each frame to this process's writer; return the records finished so far.

    The records are those of this view's jobs that failed before writing and of every frame (of this
    view or earlier ones) whose writing has finished; frames still being written are reported by a
    later call or by :func:`finish_writes`. The local pool's workers run this, so that a frame is
    written while the next view renders.
    """
    global _WRITER
    _BUSY.set()
    try:
        if _WRITER is None:
            _WRITER = FrameWriter()
        failed = _render_view(task, _WRITER)
        sys.stdout.flush()
        if _STOP.is_set():  # stopped after the view's last render: its frames are written first
            _exit_stopped()
        return failed + _WRITER.take()
    finally:
        _BUSY.clear()


def finish_writes() -> list[dict]:
    """Wait for this process's writer to write every frame handed to it; their records not reported yet."""
    return [] if _WRITER is None else _WRITER.drain()
