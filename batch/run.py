"""Running jobs: executors, resume logic, the index, progress and the summary.

Executors
---------
===================  ===========================================================================
``LocalExecutor``    ``--workers N`` processes ("spawn" context; the default), each its own
                     one-process pool taking the next view as soon as it reports one; with
                     ``--device gpu``/``auto`` one process per GPU, each pinned to its GPU
                     (``CUDA_VISIBLE_DEVICES``, set by the initializer); a worker that dies
                     fails only its own view and is replaced
``DaskExecutor``     ``distributed.Client(address)`` for an existing cluster (``--scheduler``;
                     each worker uses the GPU its environment shows), or a ``LocalCluster``
                     of worker processes (``--dask local``; one per GPU, each pinned, with a
                     GPU plan)
``InlineExecutor``   this process, one view after another (inside Blender, where bpy is
                     imported and no worker may be started)
===================  ===========================================================================

The process that runs :func:`run_jobs` with a pool must not have imported
``bpy``: a process that did hangs when it forks, and its spawned children
cannot import ``_bpy``. The workers import it themselves when a task needs it.

Where frames render (CPU, which GPUs) is decided once, before the dataset is
touched, by :func:`batch.devices.plan_devices`; a ``--device gpu`` run without
a usable GPU stops there with one line (exit code 2).

Before the workers start, the kernels they will use are compiled once by one
child process where the caches do not hold them yet (:mod:`batch.warmup`), so
that N workers do not compile the same kernels N times at once.

Every executor calls :func:`batch.worker.run_view` on :class:`~batch.jobs.ViewTask`
objects and yields their records; the parent, the index's only writer, indexes
each job once, as its published folder describes it (:meth:`Dataset.settle`,
:meth:`Dataset.append`; a duplicate result is dropped). Dask runs a task at
least once: results are released as soon as they are read, so a worker lost
later does not make Dask run finished views again, and a view that does run
twice cannot replace its published folders (:func:`batch.dataset.publish`).

Signals: on Ctrl-C or SIGTERM the parent stops the workers (they cancel their
render between ray chunks and remove their half-written folder), rewrites the
index, updates the card and exits with 130 / 143. Workers are started with
SIGINT blocked (:func:`sigint_held`) and then ignore it: the terminal sends
Ctrl-C to every process of the group, and only the parent acts on it. Starting
an executor is not cut in half: a signal meanwhile is acted on once it has
started (:func:`signals_deferred`).
"""

from __future__ import annotations

import concurrent.futures as cf
import math
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import TextIO

from tofcore.progress import tqdm_class, use_bar
from tofcore.limits import usable_cpus
from tofcore.tracer.workers import sigint_held

from .card import dataset_card
from .card_figures import diversity_section
from .dataset import FRAMES, RECORD, Dataset, differing_keys
from .devices import VISIBLE_ENV, cpu_frames_and_threads, plan_devices
from .jobs import Job, ViewTask, group_by_view
from .timing import timing_lines, worker_timing
from .warmup import plan_warmup, warm_up
from .worker import WorkerDied, failed_record, finish_writes, init_worker, run_view, start_view


class Interrupted(BaseException):
    """Ctrl-C or SIGTERM: stop cleanly (not an Exception, so nothing catches it by accident)."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
        self.published: int | None = None  # frames this run published, once the run has begun

    def message(self) -> str:
        """The one line said when a run stops on this signal."""
        done = ("before any frame was rendered" if self.published is None
                else f"{self.published} frame{'s' if self.published != 1 else ''} published by this run")
        return f"interrupted ({self}): {done}; rerun the same command to resume"

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


def install_signal_handlers() -> None:
    """SIGINT and SIGTERM raise :class:`Interrupted` in the main thread."""
    def handler(signum, _frame):
        raise Interrupted(signum)

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)


@contextmanager
def signals_deferred():
    """Hold SIGINT/SIGTERM back for the duration; yields the list of the signals that came meanwhile.

    Used around what must not be cut in half: bookkeeping of a finished frame (index line and
    in-memory record) and the final index rewrite. The caller acts on the caught signals after.
    """
    caught: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield caught
        return
    previous = {sig: signal.signal(sig, lambda signum, _frame: caught.append(signum))
                for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield caught
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


# --------------------------------------------------------------------------- executors

Result = tuple[ViewTask, "list[dict] | BaseException"] | None


class InlineExecutor:
    """Run views in this process, one after another."""

    name = "in-process executor (no worker processes)"

    def results(self, tasks: list[ViewTask]) -> Iterator[Result]:
        for task in tasks:
            yield task, run_view(task)

    def close(self, kill: bool = False) -> None:
        pass


def _exit_code(process, timeout_s: float) -> int | None:
    """A dead worker's exit status, waiting up to ``timeout_s`` for it.

    The pool's manager thread reaps its broken workers too; when it wins the race for ``waitpid``, this
    thread's poll sees ``ECHILD`` and None for a moment, until the other has stored the status. So poll
    until a status appears rather than trust the first look.
    """
    deadline = time.monotonic() + timeout_s
    process.join(timeout=timeout_s)
    while (code := process.exitcode) is None and time.monotonic() < deadline:
        time.sleep(0.01)
    return code


@dataclass
class _Slot:
    """One worker process of the local pool: its own one-process pool, its GPU, the view it renders, and
    the jobs it was handed whose records it has not reported yet (rendering, or held by its writer)."""

    gpu: str | None
    pool: cf.ProcessPoolExecutor
    future: cf.Future | None = None
    task: ViewTask | None = None
    process: multiprocessing.Process | None = None
    unreported: dict[str, tuple[ViewTask, Job]] = field(default_factory=dict)


class LocalExecutor:
    """Worker processes ("spawn" context) that take the views one at a time from one queue.

    Each worker is its own one-process pool (a slot): the parent hands a slot the next view the moment
    it reports one, before it indexes the frames (so no worker waits for the parent's bookkeeping), and
    the last views go to whichever worker is free first. With ``gpus`` (``CUDA_VISIBLE_DEVICES`` ids)
    there is one slot per GPU, pinned to it by the initializer (:func:`batch.worker.init_worker`).

    A worker renders a view and hands its frames to its writer thread (:func:`batch.worker.start_view`):
    it reports a view as soon as it is rendered, with the records of the frames written so far, and
    renders the next view while the last one is written. A slot keeps the jobs it has not reported;
    when no view is left, it asks for the rest (:func:`batch.worker.finish_writes`).

    A worker that dies (``kill -9``, the out-of-memory killer) breaks only its own slot: every frame it
    had not reported (its view's, and those its writer held) fails with one line (:class:`WorkerDied`;
    ``--retry-failed`` renders them again; frames it had published are indexed as published), the slot
    gets a new process on the same GPU, and the other workers carry on.
    """

    def __init__(self, workers: int, gpus: tuple[str, ...] = ()):
        if "bpy" in sys.modules:
            raise RuntimeError("this process has imported bpy: it must not start worker processes (they could "
                               "not import bpy); run `python -m batch run` in a plain Python process")
        self.gpus = tuple(gpus)
        self.workers = len(self.gpus) if self.gpus else workers
        self.name = f"local pool, {self.workers} worker process{'es' if self.workers != 1 else ''}"
        if self.gpus:
            self.name += f" (one per GPU: {VISIBLE_ENV} {', '.join(self.gpus)})"
        self.slots: list[_Slot] = []

    def _new_slot(self, gpu: str | None) -> _Slot:
        context = multiprocessing.get_context("spawn")
        return _Slot(gpu, cf.ProcessPoolExecutor(max_workers=1, mp_context=context, initializer=init_worker,
                                                 initargs=(os.getpid(), gpu, time.time())))

    def _submit(self, slot: _Slot, task: ViewTask | None) -> None:
        """Hand ``task`` to the slot's worker (:func:`start_view`), or with None ask it for the records of the
        frames its writer still holds (:func:`finish_writes`)."""
        call = (start_view, task) if task is not None else (finish_writes,)
        with sigint_held():  # the first submit starts the slot's worker process
            try:
                slot.future = slot.pool.submit(*call)
            except BrokenProcessPool:  # the worker died between two views: a new one takes this view
                self._replace(slot)  # (its unreported jobs were failed when its future broke)
                slot.future = slot.pool.submit(*call)
        slot.task = task
        if task is not None:
            slot.unreported.update((job.job_id, (task, job)) for job in task.jobs)
        if slot.process is None:
            slot.process = next(iter((getattr(slot.pool, "_processes", None) or {}).values()), None)

    def _next(self, slot: _Slot, pending: deque) -> None:
        """Give a free slot the next view, or, with none left, ask it for the frames it still writes."""
        if slot.future is not None:
            return
        if pending:
            self._submit(slot, pending.popleft())
        elif slot.unreported:
            self._submit(slot, None)

    def _reported(self, slot: _Slot, task: ViewTask | None, outcome) -> tuple[ViewTask | None, list[dict] | BaseException]:
        """What a slot's finished call gives the run: its records, the slot's unreported jobs updated.

        A worker that died fails every job it had not reported; a view whose call raised fails its jobs;
        after :func:`finish_writes` (``task`` None) the worker holds nothing any more, so a job still
        unreported fails rather than wait for ever (none is, unless a record was lost).
        """
        if task is not None and not isinstance(outcome, WorkerDied):
            if isinstance(outcome, BaseException):
                for job in task.jobs:
                    slot.unreported.pop(job.job_id, None)
            else:
                for record in outcome:
                    slot.unreported.pop(record.get("job_id"), None)
            return task, outcome
        if isinstance(outcome, BaseException):
            records, lost = [], outcome
        else:
            records = outcome
            lost = WorkerDied("the worker wrote its frames but reported no record for this one; --retry-failed "
                              "renders it again", pid=slot.process.pid if slot.process is not None else None,
                              gpu=slot.gpu)
        for record in records:
            slot.unreported.pop(record.get("job_id"), None)
        held = list(slot.unreported.values())
        slot.unreported.clear()
        return task or (held[0][0] if held else None), records + [failed_record(job, job_task, lost)
                                                                  for job_task, job in held]

    def _replace(self, slot: _Slot) -> None:
        """A new worker process (pool) for a slot whose process died, pinned to the same GPU."""
        slot.pool.shutdown(wait=False, cancel_futures=True)
        slot.pool, slot.process = self._new_slot(slot.gpu).pool, None

    def _died(self, slot: _Slot) -> WorkerDied:
        """The one-line error of the view whose worker died; waits briefly for its exit status."""
        process, where = slot.process, f" for GPU {slot.gpu}" if slot.gpu is not None else ""
        code = None
        if process is not None:
            code = _exit_code(process, timeout_s=2.0)
        how = "ended" if code is None else f"exit code {code}"
        if code is not None and code < 0:
            try:
                how = f"killed by {signal.Signals(-code).name}"
            except ValueError:
                how = f"killed by signal {-code}"
        pid = f" (pid {process.pid})" if process is not None else ""
        return WorkerDied(f"the worker process{where}{pid} died while rendering or writing this frame ({how}); the other "
                          f"workers went on; --retry-failed renders its frames again",
                          pid=process.pid if process is not None else None, gpu=slot.gpu)

    def results(self, tasks: list[ViewTask]) -> Iterator[Result]:
        pending = deque(tasks)
        self.slots = [self._new_slot(gpu) for gpu in (self.gpus or [None] * self.workers)]
        while True:
            for slot in self.slots:  # every free worker takes the next view first: none waits for the parent
                self._next(slot, pending)
            busy = [slot.future for slot in self.slots if slot.future is not None]
            if not busy:
                return
            done, _ = cf.wait(busy, timeout=0.5, return_when=cf.FIRST_COMPLETED)
            if not done:
                yield None
                continue
            finished = []
            for slot in self.slots:
                if slot.future not in done:
                    continue
                future, task = slot.future, slot.task
                slot.future = slot.task = None
                try:
                    outcome = future.result()
                except BrokenProcessPool:  # this worker died: a new process on its GPU takes the next view
                    outcome = self._died(slot)
                    self._replace(slot)
                except Exception as exc:
                    outcome = exc
                finished.append(self._reported(slot, task, outcome))
            for slot in self.slots:  # refill before the parent indexes what came back
                self._next(slot, pending)
            yield from finished

    def close(self, kill: bool = False) -> None:
        """Stop the workers: idle ones at once (SIGTERM: an idle worker exits without the interpreter's
        teardown, which held the end of every run back by a second or more), busy ones too with ``kill``
        (they cancel their render and remove their partial folder), else they get 10 s to finish.

        The processes are taken from each pool, not from the slot: a signal right after a submit can
        stop the run before the slot has noted its new process. Each pool's manager thread is joined
        last, so that it has closed its wake-up pipe before the interpreter's exit hook writes to it
        (a race that printed ``OSError: Bad file descriptor`` at exit).
        """
        slots, self.slots = self.slots, []
        owned = [(slot, list((getattr(slot.pool, "_processes", None) or {}).values()),
                  getattr(slot.pool, "_executor_manager_thread", None)) for slot in slots]
        for slot, processes, _ in owned:
            for process in processes:
                if process.is_alive() and (kill or slot.future is None):
                    process.terminate()
        for slot in slots:
            slot.pool.shutdown(wait=False, cancel_futures=True)
        deadline = time.monotonic() + 10.0
        for _, processes, _ in owned:
            for process in processes:
                process.join(timeout=max(0.0, deadline - time.monotonic()))
                if process.is_alive():
                    process.kill()
                    process.join(timeout=5.0)
        for _, _, manager in owned:
            if manager is not None:
                manager.join(timeout=5.0)


class DaskExecutor:
    """A Dask distributed cluster: an existing scheduler, or a LocalCluster of worker processes.

    On an existing cluster this package's code is shipped to the scheduler and the workers
    (:mod:`batch.cluster`), which must have ``tofcore`` installed (checked: one line when not), and
    the dataset folder and scene files at the same paths (a shared file system).
    """

    def __init__(self, address: str | None = None, workers: int = 1, gpus: tuple[str, ...] = ()):
        try:
            import distributed  # noqa: F401
        except ImportError:
            raise RuntimeError("the Dask executor needs the distributed package: "
                               "pip install 'dask[distributed]'") from None
        self.cluster = None
        with sigint_held():  # the cluster's IO thread starts the worker processes: they inherit it
            self._start(address, workers, gpus)
        self.futures: dict = {}

    def _start(self, address: str | None, workers: int, gpus: tuple[str, ...]) -> None:
        import logging

        from distributed import Client, LocalCluster

        if address is None:
            self.cluster = LocalCluster(n_workers=0 if gpus else workers, threads_per_worker=1, processes=True,
                                        dashboard_address=None, silence_logs=logging.ERROR)
            if gpus:  # one worker per GPU, CUDA_VISIBLE_DEVICES in its environment (as dask-cuda does)
                template = self.cluster.new_spec
                for gpu in gpus:
                    options = dict(template["options"], env={VISIBLE_ENV: gpu})
                    self.cluster.worker_spec[f"gpu-{gpu}"] = {"cls": template["cls"], "options": options}
                self.cluster.scale(len(gpus))
                workers = len(gpus)
            self.client = Client(self.cluster)
            if gpus:
                self.client.wait_for_workers(workers, timeout=120)
            self.name = f"Dask LocalCluster, {workers} worker process{'es' if workers != 1 else ''}"
            if gpus:
                self.name += f" (one per GPU: {VISIBLE_ENV} {', '.join(gpus)})"
        else:
            from .cluster import check_imports, ship

            self.client = Client(address, timeout="30s")
            try:
                ship(self.client)  # the scheduler and workers unpickle tasks that name this package's modules
                check_imports(self.client, address)
            except BaseException:
                self.client.close(timeout=10)
                raise
            n = len(self.client.scheduler_info().get("workers", {}))
            self.name = f"Dask cluster at {address} ({n} workers now)"

    def results(self, tasks: list[ViewTask]) -> Iterator[Result]:
        from distributed import wait

        # pure=False: a rerun must execute; the key names the view for the Dask dashboard.
        self.futures = {self.client.submit(run_view, task, pure=False, key=f"tofbatch-{task.view_id}-{i}"): task
                        for i, task in enumerate(tasks)}
        pending = set(self.futures)
        while pending:
            try:
                done, pending = wait(pending, timeout=0.5, return_when="FIRST_COMPLETED")
            except TimeoutError:
                yield None
                continue
            for future in done:
                task = self.futures.pop(future)
                try:
                    outcome = future.result()
                except Exception as exc:  # KilledWorker, a worker that lost its connection, …
                    outcome = exc
                # Forget the result: Dask would run a finished view again if the worker holding its
                # result died later (the rerun cannot replace the published folders, but need not run).
                future.release()
                yield task, outcome

    def close(self, kill: bool = False) -> None:
        try:
            if kill and self.futures:
                self.client.cancel(list(self.futures), force=True)
            self.client.close(timeout=10)
        finally:
            if self.cluster is not None:
                self.cluster.close(timeout=10)


def make_executor(*, workers: int = 1, scheduler: str | None = None, dask_local: bool = False,
                  inline: bool = False, gpus: tuple[str, ...] = ()):
    """The executor for these options; ``gpus``: pin one local or LocalCluster worker to each."""
    if inline:
        return InlineExecutor()
    if scheduler is not None or dask_local:
        return DaskExecutor(scheduler, workers=workers, gpus=gpus if scheduler is None else ())
    return LocalExecutor(workers, gpus=gpus)


# --------------------------------------------------------------------------- progress

def _duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    seconds = int(round(seconds))
    if seconds < 60:
        return f"{seconds}s"
    if seconds < 3600:
        return f"{seconds // 60}m{seconds % 60:02d}s"
    return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m"


def _device_tag(record: dict) -> str:
    """``", GPU 1"`` / ``", CPU (auto fall-back)"`` for a frame's log line; nothing for a plain CPU frame."""
    device = record.get("device") or {}
    if device.get("name") == "gpu":
        visible = record.get("cuda_visible_devices")
        return f", GPU {visible}" if visible else ", GPU"
    if device.get("fallback_reason"):
        return f", CPU ({device.get('requested')} fall-back)"
    return ""


class Progress:
    """Frames done, failures, rate and ETA on stderr: a tqdm bar on a terminal, else one plain line per frame.

    The bar (:func:`tofcore.progress.use_bar`: a terminal and tqdm installed) is made at the first frame or
    heartbeat, so the run's opening lines come before it; failures are printed above it. In a log (a file
    or pipe, ``blender -b`` output), without tqdm, or with ``quiet``: one line per frame, no carriage returns.
    """

    def __init__(self, total: int, *, quiet: bool = False, stream: TextIO | None = None):
        self.total = total
        self.done = 0
        self.failed = 0
        self.stream = stream or sys.stderr
        self.bar = not quiet and use_bar(self.stream)
        self.start = time.monotonic()
        self._last_draw = 0.0
        self._tqdm = None

    def _rate(self) -> str:
        elapsed = time.monotonic() - self.start
        rate = self.done / elapsed * 60 if self.done and elapsed > 0 else 0.0
        return f"{self.failed} failed, {rate:.2f} frames/min"

    def record(self, record: dict) -> None:
        self.done += 1
        if record["status"] != "ok":
            self.failed += 1
        if self.bar:
            if record["status"] != "ok":
                self._write(f"FAILED {record['job_id']} {record['scene']}/{record['view']['label']}/"
                            f"{record['preset']}: {record['error']}")
            elif record.get("warning"):
                self._write(f"warning {record['job_id']} {record['scene']}/{record['view']['label']}/"
                            f"{record['preset']}: {record['warning']}")
            self.draw(force=True, step=1)
            return
        label = f"{record['scene']}/{record['view']['label']}/{record['preset']}"
        if record["status"] == "ok":
            rms = record.get("rms_depth_error_m")
            detail = (f"{record.get('render_seconds', 0):.1f} s, {record.get('spp')} spp, RMS error "
                      f"{'–' if rms is None else f'{rms * 1000:.1f}'} mm{_device_tag(record)}")
            self.stream.write(f"[{self.done}/{self.total}] ok      {record['job_id']} {label} ({detail})\n")
            if record.get("warning"):
                self.stream.write(f"    warning: {record['warning']}\n")
        else:
            self.stream.write(f"[{self.done}/{self.total}] FAILED  {record['job_id']} {label}: {record['error']}\n")
        self.stream.flush()

    def _write(self, line: str) -> None:
        """A line above the bar."""
        self._bar().write(line, file=self.stream)

    def _bar(self):
        if self._tqdm is None:
            self._tqdm = tqdm_class()(total=self.total, unit="frame", file=self.stream, dynamic_ncols=True,
                                      leave=True, mininterval=0.5, postfix=self._rate(),
                                      bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} frames "
                                                 "[{elapsed}<{remaining}{postfix}]")
        return self._tqdm

    def draw(self, force: bool = False, step: int = 0) -> None:
        """Redraw the bar (``step`` frames more); between frames at most every 0.5 s (elapsed time moves on)."""
        if not self.bar:
            return
        now = time.monotonic()
        if not force and now - self._last_draw < 0.5:
            return
        self._last_draw = now
        bar = self._bar()
        bar.set_postfix_str(self._rate(), refresh=False)
        if step:
            bar.update(step)
        bar.refresh()

    def close(self) -> None:
        if self.bar and self.total:
            self.draw(force=True)
            self._tqdm.close()
        self._tqdm, self.bar = None, False


# --------------------------------------------------------------------------- the run

@dataclass
class RunResult:
    """What a run did; ``exit_code`` 0 when every frame of the set is ok, 1 when some failed."""

    jobs: int = 0
    done_before: int = 0
    rendered: int = 0
    failed: int = 0                   # frames of the set whose record is failed at the end
    skipped_failed: int = 0           # failed earlier and not retried (no --retry-failed)
    redone: int = 0                   # recorded ok but their files did not verify
    recovered: int = 0                # index line lost, taken from the frame's record.json
    duplicates: int = 0               # results of a job indexed already in this run (dropped)
    pending: int = 0                  # not rendered (interrupted)
    outside_set: int = 0              # indexed frames not in this set (an earlier version of it, another set): kept
    seconds: float = 0.0
    interrupted: Interrupted | None = None
    failures: list[dict] = field(default_factory=list)
    warned: list[dict] = field(default_factory=list)  # ok frames of the set with a warning (few valid pixels)
    executor: str = ""
    workers: list[dict] = field(default_factory=list)  # per worker process: where its time went (batch.timing)

    @property
    def exit_code(self) -> int:
        if self.interrupted is not None:
            return self.interrupted.exit_code
        return 1 if self.failed or self.pending else 0


def _log(message: str, stream: TextIO | None = None) -> None:
    stream = stream or sys.stderr
    stream.write(message + "\n")
    stream.flush()


def report_index(data: Dataset, info: dict, log, shown: int = 10) -> None:
    """Say what :meth:`Dataset.read_index` left out, one line each, and keep the ignored lines.

    Lines that are not records are copied to ``index.jsonl.rejected`` (the index rewritten next
    leaves them out); their frames are taken from their folders when those verify, else rendered.
    """
    problems = info["problems"]
    for number, why, _ in problems[:shown]:
        log(f"warning: {data.index_path}:{number}: ignored ({why}); its frame, if any, is checked from its folder")
    if len(problems) > shown:
        log(f"warning: {data.index_path}: {len(problems) - shown} more line(s) ignored")
    if problems:
        path = data.reject(problems)
        log(f"warning: {len(problems)} ignored index line(s) kept in {path}")
    if info["truncated"] is not None:
        log(f"note: {data.index_path}:{info['truncated']}: incomplete last line (a run stopped while writing "
            f"it) dropped")
    if info["duplicates"]:
        log(f"note: {data.index_path}: {info['duplicates']} record(s) superseded by a later line of the same "
            f"frame dropped")


def report_outside_set(records: dict[str, dict], jobs: list[Job], set_file: str | None, result: RunResult,
                       log) -> None:
    """Warn, once, how many indexed frames are not in this set: an edited set file gives its frames new job ids,
    and the frames of the earlier version stay in the index and in ``frames/`` (counted in ``result``)."""
    in_set = {job.job_id for job in jobs}
    outside = [r for job_id, r in records.items() if job_id not in in_set]
    result.outside_set = len(outside)
    if outside:
        first = outside[0]  # a record (Dataset.read_index): scene, view label and preset are there
        log(f"warning: {len(outside)} indexed frame(s) are not in {set_file or 'this set'} (e.g. {first['job_id']} "
            f"{first['scene']}/{first['view']['label']}/{first['preset']}): frames of an earlier version of the set "
            f"file or of "
            f"another set, kept in the index and frames/; `tofcore-batch verify` lists them, "
            f"Dataset(root, current_set=True) reads only this set's frames")


def plan(jobs: list[Job], data: Dataset, records: dict[str, dict], *, retry_failed: bool, verify: str,
         result: RunResult, log) -> list[Job]:
    """Jobs to render now; ``records`` is updated (recovered records added, records of frames to redo removed).

    A folder left under the name of a job to render (it failed verification, or its ``record.json``
    is unreadable) is deleted here, before any worker starts: publishing never replaces a folder.
    """
    todo: list[Job] = []
    redone: set[str] = set()
    for job in jobs:
        record = records.get(job.job_id)
        if record is None or record.get("status") != "ok":
            folder = data.published_record(job.job_id)
            if folder is not None:
                records[job.job_id] = record = folder
                result.recovered += 1
        if record is None:
            todo.append(job)
        elif record.get("status") == "failed":
            if retry_failed:
                todo.append(job)
            else:
                result.skipped_failed += 1
        else:
            published = data.published_record(job.job_id) if "record_file" in record else None
            if published is not None and published["record_file"] == record["record_file"] \
                    and differing_keys(record, published):
                log(f"note: {job.job_id} ({job.label}): the index line differed from its {RECORD} in "
                    f"{', '.join(differing_keys(record, published))}; taken from {RECORD}")
                records[job.job_id] = record = published
            problem = data.verify(record, verify)
            if problem is None:
                result.done_before += 1
                if "record_file" not in record:  # indexed before record.json had a checksum: add it
                    records[job.job_id] = data.published_record(job.job_id) or record
            else:
                log(f"redo {job.job_id} ({job.label}): {problem}")
                del records[job.job_id]
                result.redone += 1
                redone.add(job.job_id)
                todo.append(job)
    if retry_failed:
        todo = [job for job in todo if job.job_id in records and records[job.job_id].get("status") == "failed"]
    for job in todo:
        if data.discard(job.job_id) and job.job_id not in redone:
            log(f"redo {job.job_id} ({job.label}): {FRAMES}/{job.job_id}/ has no readable {RECORD}; deleted")
    return todo


def _ordered(records: dict[str, dict], jobs: list[Job]) -> list[dict]:
    """The set's records in set order, then records of jobs not in this set (kept) in their old order."""
    ids = [job.job_id for job in jobs]
    in_set = set(ids)
    return [records[i] for i in ids if i in records] + [r for i, r in records.items() if i not in in_set]


def run_jobs(jobs: list[Job], dataset: str | os.PathLike, *, executor=None, workers: int | None = None,
             threads_per_worker: int | None = None, scheduler: str | None = None, dask_local: bool = False,
             inline: bool = False, device: str = "cpu", retry_failed: bool = False, verify: str = "sha256",
             quiet: bool = False, set_file: str | None = None, description: str = "",
             stream: TextIO | None = None) -> RunResult:
    """Render the jobs not yet done into ``dataset``; see the module docstring.

    Parameters
    ----------
    jobs : from :func:`batch.jobs.expand`, in set order.
    dataset : the dataset folder (created if needed).
    workers : local worker processes, or LocalCluster workers with ``dask_local`` (default on the CPU:
        :func:`batch.devices.cpu_frames_and_threads` of the usable CPUs and the frames to render, with
        that many tracer threads each; with a GPU plan one per GPU, and never more).
    threads_per_worker : tracer worker processes per render (threads inside a Dask worker, which may not
        start processes; default: usable CPUs / workers, at least 1, so frames × tracer workers never
        exceed the CPUs; on a remote cluster: each worker machine's CPU count).
    scheduler, dask_local, inline : the executor (default: the local pool).
    device : ``"cpu"``, ``"gpu"`` or ``"auto"`` (:mod:`batch.devices`); raises
        :class:`~tofcore.backend.GpuUnavailable` for ``"gpu"`` without a usable GPU, before anything
        is written.
    retry_failed : render only the frames recorded as failed.
    verify : ``"sha256"`` (default) or ``"size"``: how finished frames are checked before they are skipped.
    quiet : plain log lines instead of the progress bar.
    """
    stream = stream or sys.stderr
    log = (lambda message: _log(message, stream))
    where = ("inline" if inline else "cluster" if executor is not None or scheduler is not None
             else "dask-local" if dask_local else "local")
    devices = plan_devices(device, executor=where, workers=workers)
    workers_given, workers = workers, devices.workers
    for note in devices.notes:
        log(note)
    result = RunResult(jobs=len(jobs))
    started = time.monotonic()
    data = Dataset(dataset)
    with data.locked():
        records, info = data.read_index()
        report_index(data, info, log)
        report_outside_set(records, jobs, set_file, result, log)
        data.write_current_set(set_file, [job.job_id for job in jobs])
        removed = data.clean_partials()
        if removed:
            log(f"removed {removed} half-written frame folder(s) left by an interrupted run")
        todo = plan(jobs, data, records, retry_failed=retry_failed, verify=verify, result=result, log=log)
        data.rewrite_index(_ordered(records, jobs))
        if (workers_given is None and threads_per_worker is None and not devices.gpus
                and where in ("local", "dask-local") and todo):
            workers, threads_per_worker = cpu_frames_and_threads(usable_cpus(), len(todo))
            log(f"{workers} frame(s) at once × {threads_per_worker} tracer thread(s) each, for "
                f"{usable_cpus()} CPUs (--workers and --threads-per-worker set them)")
        if threads_per_worker is None and scheduler is None:
            threads_per_worker = max(1, usable_cpus() // max(1, workers if not inline else 1))
        tasks = group_by_view(todo, dataset=str(data.root), render_threads=threads_per_worker,
                              device=devices.render, fallback_reason=devices.fallback_reason)
        if result.recovered:
            log(f"{result.recovered} finished frame(s) taken from their record.json (index line missing)")
        progress = Progress(len(todo), quiet=quiet, stream=stream)
        reported: list[dict] = []  # the records the workers reported in this run
        try:
            if not todo:
                log(f"{len(jobs)} frames in the set: nothing to render"
                    + (f" ({result.skipped_failed} failed earlier; --retry-failed retries them)"
                       if result.skipped_failed else ""))
            else:
                warm, why_not = plan_warmup(devices, executor=where, workers=min(workers, len(tasks)))
                if warm is not None:  # the workers' kernels compiled once, before any worker starts
                    warm_up(warm, log)
                elif why_not:
                    log(why_not)
                with signals_deferred() as caught:  # an executor is not left half-started (a Dask cluster)
                    executor = executor or make_executor(workers=workers, scheduler=scheduler,
                                                         dask_local=dask_local, inline=inline, gpus=devices.gpus)
                result.executor = executor.name
                skipped = f", {result.skipped_failed} failed earlier (--retry-failed retries them)" \
                    if result.skipped_failed else ""
                log(f"{len(jobs)} frames in the set: {result.done_before} done{skipped}; rendering {len(todo)} "
                    f"({len(tasks)} view{'s' if len(tasks) != 1 else ''}) with the {executor.name}, "
                    f"{threads_per_worker or 'default'} tracer worker(s) each")
                try:
                    if caught:
                        raise Interrupted(caught[0])
                    for item in executor.results(tasks):
                        if item is None:
                            progress.draw()
                            continue
                        task, outcome = item
                        if isinstance(outcome, BaseException):
                            outcome = [failed_record(job, task, outcome) for job in task.jobs]
                        with signals_deferred() as caught:  # a record is kept whole: index and memory
                            for record in outcome:
                                record = data.settle(record)  # what the published folder says
                                if not data.append(record):  # indexed already in this run: a duplicate
                                    result.duplicates += 1
                                    log(f"duplicate result of {record['job_id']} dropped (the frame is "
                                        f"indexed already; its folder was not replaced)")
                                    continue
                                records[record["job_id"]] = record
                                reported.append(record)
                                result.rendered += record["status"] == "ok"
                                progress.record(record)
                        if caught:
                            raise Interrupted(caught[0])
                    executor.close()
                except Interrupted as exc:
                    result.interrupted = exc
                    progress.close()
                    log(f"{exc}: stopping the workers …")
                    executor.close(kill=True)
                except BaseException:
                    executor.close(kill=True)
                    raise
                else:
                    progress.close()
                result.workers = worker_timing(reported)
        finally:
            with signals_deferred() as caught:
                data.clean_partials()  # folders of workers stopped or lost (no worker of ours writes now)
                if todo:  # frames published by workers stopped before they reported them
                    for job in todo:
                        record = records.get(job.job_id)
                        if (record is None or record["status"] != "ok") \
                                and (published := data.published_record(job.job_id)) is not None:
                            records[job.job_id] = published
                            result.rendered += 1
                ordered = _ordered(records, jobs)
                data.rewrite_index(ordered)
                set_ids = {job.job_id for job in jobs}
                set_records = [r for r in ordered if r["job_id"] in set_ids]
                result.failures = [r for r in set_records if r.get("status") == "failed"]
                result.warned = [r for r in set_records if r.get("status") == "ok" and r.get("warning")]
                result.failed = len(result.failures)
                result.pending = len(jobs) - len(set_records)
                card = dataset_card(ordered, set_file=set_file, description=description, jobs_in_set=len(jobs))
                figures = diversity_section(ordered, data.root)
                data.write_card(card + "".join(line + "\n" for line in figures))
                result.seconds = time.monotonic() - started
            if caught and result.interrupted is None:
                result.interrupted = Interrupted(caught[0])
            if result.interrupted is not None:
                result.interrupted.published = result.rendered
    return result


def summary(result: RunResult, dataset: str | os.PathLike) -> str:
    """The lines printed at the end of a run."""
    rate = result.rendered / result.seconds * 60 if result.seconds > 0 and result.rendered else 0.0
    ok = result.jobs - result.failed - result.pending
    lines = [f"{result.jobs} frames: {ok} ok ({result.rendered} rendered now in {_duration(result.seconds)}"
             f"{f', {rate:.2f} frames/min' if result.rendered else ''}; {result.done_before} already done"
             f"{f', {result.recovered} recovered' if result.recovered else ''}"
             f"{f', {result.redone} redone after failed verification' if result.redone else ''}), "
             f"{result.failed} failed, {result.pending} not rendered"]
    for record in result.failures[:10]:
        lines.append(f"  failed {record['job_id']} {record['scene']}/{record['view']['label']}/{record['preset']}: "
                     f"{record.get('error')}")
    if len(result.failures) > 10:
        lines.append(f"  … and {len(result.failures) - 10} more (see index.jsonl)")
    if result.failures:
        lines.append("  retry them with --retry-failed once the cause is fixed")
    if result.warned:
        first = result.warned[0]
        lines.append(f"{len(result.warned)} frame(s) ok but with few valid pixels ('warning' in index.jsonl), e.g. "
                     f"{first['scene']}/{first['view']['label']}/{first['preset']}: {first['warning']}")
    if result.interrupted is not None:
        lines.append(result.interrupted.message())
    if result.outside_set:
        lines.append(f"  the index also holds {result.outside_set} frame(s) not in this set (see the warning above)")
    lines += timing_lines(result.workers)
    lines.append(f"dataset: {os.fspath(dataset)} (index.jsonl, README.md, frames/)")
    return "\n".join(lines)
