"""The frame writer: a worker's frames are encoded and written on a thread of their own.

A worker renders a frame, hands it to its :class:`FrameWriter` and renders the next one while the
writer computes the frame's error metrics, encodes its files (EXR, PNG, PLY, JSON), checksums them,
writes ``record.json`` and publishes the folder (:mod:`batch.worker`). On a GPU the render is mostly
waiting for the device and the writing mostly NumPy, zlib, OpenCV and hashlib, which release the
interpreter's lock, so the two overlap.

The queue is bounded: at most ``depth`` frames wait for the writer besides the one it writes (a
Kinect v2 frame's arrays are tens of MB), and :meth:`FrameWriter.submit` blocks while the queue is
full: rendering waits when the writer falls behind, and the seconds it waited are returned (the
record's ``timing["handoff_wait_s"]``).

Nothing the writer does changes what a frame on disk means: a frame is written into its staging
folder and published by one rename, and the parent indexes only records the worker reported, so a
frame is indexed only when all its files are written. A worker that dies loses the frames it held
(queued, or half-written in a ``.partial-`` folder the next run removes): they are not indexed and
are rendered again on resume (or with ``--retry-failed`` when the parent recorded them as failed).

Every submitted frame gives exactly one record, in submission order: the write function's, or, when
it raises, the ``fail`` function's (the frame's failure, one line for a disk error).
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

#: Frames that may wait for the writer besides the one it writes (the bound of the queue).
DEFAULT_DEPTH = 1


@dataclass
class _Item:
    write: Callable[[float], dict]
    fail: Callable[[BaseException], dict]
    wait_s: float = 0.0
    handed: threading.Event = field(default_factory=threading.Event)  # set once wait_s is known


_CLOSE = object()


class FrameWriter:
    """One writer thread and its bounded queue; records come back in submission order.

    Parameters
    ----------
    depth : frames that may wait besides the one being written (>= 1); :meth:`submit` blocks beyond it.
    name : the thread's name (seen in tracebacks and ``py-spy``).
    """

    def __init__(self, depth: int = DEFAULT_DEPTH, name: str = "frame-writer"):
        if not isinstance(depth, int) or isinstance(depth, bool) or depth < 1:
            raise ValueError(f"FrameWriter: depth must be an integer >= 1, got {depth!r}")
        self.depth = depth
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._done: list[dict] = []
        self._lock = threading.Condition()
        self._submitted = 0       # frames handed over
        self._finished = 0        # frames whose record is in _done or was taken
        self.blocked = False      # True while submit waits for room in the queue (for tests and stats)
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    # ---------------------------------------------------------------- the render thread's side
    def submit(self, write: Callable[[float], dict], fail: Callable[[BaseException], dict]) -> float:
        """Hand a frame over; returns the seconds this call waited for room in the queue.

        ``write(wait_s)`` runs on the writer thread and returns the frame's record (``wait_s``: the
        seconds the render thread waited to hand it over); if it raises, ``fail(exc)`` gives the record.
        """
        if not self._thread.is_alive():
            raise RuntimeError("FrameWriter: the writer thread has stopped")
        started = time.perf_counter()
        item = _Item(write, fail)
        with self._lock:
            self._submitted += 1
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.blocked = True
            try:
                self._queue.put(item)
            finally:
                self.blocked = False
            item.wait_s = time.perf_counter() - started
        item.handed.set()
        return item.wait_s

    @property
    def in_flight(self) -> int:
        """Frames handed over whose record is not finished yet (queued or being written)."""
        with self._lock:
            return self._submitted - self._finished

    def take(self) -> list[dict]:
        """The records finished since the last call (submission order); does not wait."""
        with self._lock:
            done, self._done = self._done, []
        return done

    def drain(self, timeout: float | None = None) -> list[dict]:
        """Wait until every frame handed over is written (at most ``timeout`` s); the records not taken yet."""
        with self._lock:
            self._lock.wait_for(lambda: self._finished == self._submitted, timeout)
            done, self._done = self._done, []
        return done

    def close(self) -> None:
        """Finish what was handed over and stop the thread (its records stay for :meth:`take`)."""
        if self._thread.is_alive():
            self._queue.put(_CLOSE)
            self._thread.join()

    @property
    def thread(self) -> threading.Thread:
        """The writer thread."""
        return self._thread

    # ---------------------------------------------------------------- the writer thread
    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is _CLOSE:
                return
            item.handed.wait(1.0)  # set right after the put; the timeout only guards an interrupted submit
            try:
                record = item.write(item.wait_s)
            except BaseException as exc:  # noqa: BLE001 - every frame gives a record; the error is its failure
                try:
                    record = item.fail(exc)
                except BaseException as inner:  # noqa: BLE001 - never lose the frame's record silently
                    record = {"status": "failed", "error": f"{type(inner).__name__}: {inner} (while recording "
                                                           f"{type(exc).__name__}: {exc})"}
            item = None  # the frame's arrays are freed now, not when the next frame arrives
            with self._lock:
                self._done.append(record)
                self._finished += 1
                self._lock.notify_all()
