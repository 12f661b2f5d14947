"""Worker processes for the CPU tracer: the scene, BVH and accumulators shared once, chunks traced in parallel.

NumPy releases the GIL only inside large operations, so tracer *threads* serialise on the Python between
them (1.45× from two threads on two cores; 16 threads were 2.8× slower than 2 on a 16-core machine).
Processes do not share a GIL. Each render:

1. pickles its trace context and accumulators once (:func:`share`): every NumPy array of 64 KiB or more
   goes into a ``multiprocessing.shared_memory`` block and the pickle holds only its name, shape and
   dtype — the scene, BVH and material tables exist once in memory, not once per worker;
2. sends each chunk as (render key, pixel range) to a persistent pool of ``spawn``-ed processes, which
   unpickle the context once per render onto views of the shared blocks and trace the chunk with the
   same function as the in-process path (:func:`tofcore.tracer.integrator.trace_chunk`);
3. chunks own disjoint pixels and write their sums straight into the shared accumulators, so the result
   is the same bit for bit whatever the number of workers.

``spawn`` (never ``fork``): a process that imported ``bpy`` must not fork. The children import only
``tofcore`` and NumPy, and do not re-run the parent's ``__main__`` script. Inside Blender,
``sys.executable`` may be the Blender binary; the children then start with the Python interpreter
bundled beside it (:func:`python_executable`), and where none is found the tracer uses threads and says
why (:func:`process_support`). Each worker's BLAS is limited to one thread (no oversubscription).

Memory per worker beyond the shared blocks: one chunk's path state (``chunk_size`` paths, ≈ 2 KiB each)
and the Python/NumPy runtime (≈ 60 MB).
"""

from __future__ import annotations

import atexit
import gc
import importlib
import io
import multiprocessing as mp
import os
import pickle
import shutil
import signal
import sys
import threading
from contextlib import contextmanager
from multiprocessing import shared_memory
from pathlib import Path

import numpy as np

SHARE_MIN_BYTES = 1 << 16
"""Arrays at least this large travel through shared memory; smaller ones are pickled by value."""

_BLAS_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS",
             "NUMEXPR_NUM_THREADS")


def python_executable() -> str | None:
    """The Python interpreter that worker processes start with; None where there is none to start.

    Normally ``sys.executable``. Blender's own binary is not a Python interpreter: inside Blender the
    bundled interpreter lives in ``sys.prefix/bin`` (``python3.11`` and the like on Linux and macOS,
    ``python.exe`` on Windows), which is what add-ons that start Python subprocesses use.
    """
    exe = sys.executable or ""
    if exe and not Path(exe).name.lower().startswith("blender"):
        return exe
    bindir = Path(sys.prefix) / "bin"
    version = f"{sys.version_info.major}.{sys.version_info.minor}"
    for name in (f"python{version}", f"python{sys.version_info.major}", "python", "python.exe"):
        if (bindir / name).is_file():
            return str(bindir / name)
    return None


def process_support() -> tuple[bool, str]:
    """(whether worker processes can be started here, the reason when not).

    ``TOFCORE_PARALLEL=threads`` in the environment asks for threads (comparisons, debugging, hosts where
    starting processes is not allowed).
    """
    if os.environ.get("TOFCORE_PARALLEL", "").lower() == "threads":
        return False, "TOFCORE_PARALLEL=threads"
    if mp.current_process().daemon:
        return False, "this is a daemonic process (a Dask or multiprocessing.Pool worker), which may not start others"
    if python_executable() is None:
        return False, (f"no Python interpreter to start worker processes with (sys.executable is "
                       f"{sys.executable!r}, none in {Path(sys.prefix) / 'bin'}); tracing with threads")
    return True, ""


# ----------------------------------------------------------------------------------- sharing
class _SharingPickler(pickle.Pickler):
    def __init__(self, file, shared: "Shared", always: set[int]):
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self.shared = shared
        self.always = always
        self.seen: dict[int, tuple] = {}

    def persistent_id(self, obj):
        if type(obj) is not np.ndarray or obj.dtype.hasobject:
            return None
        if obj.nbytes < SHARE_MIN_BYTES and id(obj) not in self.always:
            return None
        if id(obj) in self.seen:
            return self.seen[id(obj)][1]
        block = self.shared.new_block(obj.nbytes)
        view = np.ndarray(obj.shape, obj.dtype, buffer=block.buf)
        view[...] = obj
        ref = ("shm", block.name, obj.shape, obj.dtype.str)
        self.seen[id(obj)] = (obj, ref)  # keep obj alive so its id is not reused while pickling
        self.shared.views.append((view, obj))
        return ref


def _check_room(nbytes: int) -> None:
    """Refuse a block that /dev/shm cannot hold (Linux: a container's default 64 MiB would end in SIGBUS
    on the first write past it, not in an error)."""
    if os.path.isdir("/dev/shm"):
        free = shutil.disk_usage("/dev/shm").free
        if nbytes > free:
            raise OSError(f"/dev/shm has {free / 2**20:.0f} MiB free, a shared array needs {nbytes / 2**20:.0f} MiB "
                          f"(raise it, e.g. docker run --shm-size)")


@contextmanager
def collector_held():
    """Hold the cyclic garbage collector off while this thread calls into multiprocessing's resource tracker.

    A pool that was stopped (a cancel, Ctrl-C, another worker count) is garbage in a reference cycle, and its
    six semaphores unregister themselves from the tracker when the collector frees them. A collection that
    starts inside another tracker call (a shared-memory block created or unlinked, a pool's semaphores
    registered) makes that a reentrant call, which Python 3.13 refuses: "ResourceTracker called
    reentrantly …; the semaphore object might leak" (once in CI, six warnings: one pool). Held off, the
    collection runs at a later allocation instead, outside the tracker.
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


class Shared:
    """A pickled object whose large arrays live in shared memory blocks owned by this (parent) process.

    ``always`` lists arrays to share whatever their size: those the workers write into (the parent
    reads the results through :meth:`view`). The pickle itself goes into a block too, so a task
    carries only names. A block is listed in ``blocks`` as soon as it exists, so whatever stops the
    construction (an error, Ctrl-C during a copy) unlinks every block made so far.
    """

    def __init__(self, obj, always=()):
        self.blocks: list[shared_memory.SharedMemory] = []
        self.views: list[tuple[np.ndarray, np.ndarray]] = []  # (shared view, original array)
        try:
            buffer = io.BytesIO()
            _SharingPickler(buffer, self, {id(a) for a in always}).dump(obj)
            payload = buffer.getvalue()
            block = self.new_block(len(payload))
            block.buf[:len(payload)] = payload
        except BaseException:
            self.close()
            raise
        self.ref = (block.name, len(payload))

    def new_block(self, nbytes: int) -> shared_memory.SharedMemory:
        """A new block of ``nbytes`` (at least 1), listed for :meth:`close` at once."""
        _check_room(nbytes)
        with collector_held():
            block = shared_memory.SharedMemory(create=True, size=max(1, nbytes))
        self.blocks.append(block)
        return block

    def view(self, array: np.ndarray) -> np.ndarray:
        """The shared copy of ``array`` (one of the arrays that was shared), writable by the workers."""
        for view, original in self.views:
            if original is array:
                return view
        raise KeyError("array was not shared")

    def close(self) -> None:
        """Release and unlink the blocks (the workers' views close when they load the next render).

        A block is unlinked even where it cannot be closed: an array still viewing it (after Ctrl-C, in
        the frames of the traceback) keeps its mapping until the process ends, but its name must go now,
        or the resource tracker reports it leaked at exit."""
        self.views = []
        for block in self.blocks:
            try:
                block.close()
            except BufferError:
                pass
            try:
                with collector_held():
                    block.unlink()
            except FileNotFoundError:
                pass
        self.blocks = []


class _AttachingUnpickler(pickle.Unpickler):
    def __init__(self, file, blocks: list):
        super().__init__(file)
        self.blocks = blocks

    def persistent_load(self, ref):
        _, name, shape, dtype = ref
        block = shared_memory.SharedMemory(name=name)
        self.blocks.append(block)
        return np.ndarray(shape, np.dtype(dtype), buffer=block.buf)


# ----------------------------------------------------------------------------------- the pool
_STATE: dict = {"key": None, "value": None, "blocks": []}  # in each worker: the render it holds


def _init_worker(warm_up: str) -> None:
    # The parent's resource tracker owns the blocks; a worker attaching to one must not register it too
    # (Python < 3.13 would unlink it when the worker exits).
    from multiprocessing import resource_tracker

    def no_register(name, rtype):
        return None

    resource_tracker.register = no_register  # type: ignore[assignment]
    # Ctrl-C reaches the whole process group: the parent stops the workers (terminate), a worker never
    # prints a KeyboardInterrupt traceback. SIGINT was blocked since the worker started (sigint_held).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    # Import the caller's module (the tracer) now, while the parent traces the first hits, not on the first
    # chunk. A failure here must not kill the worker (the pool would restart it forever): the first task
    # reports it.
    if warm_up:
        try:
            importlib.import_module(warm_up)
        except Exception:
            pass


def _load(key: str, ref: tuple[str, int]):
    if _STATE["key"] != key:
        _STATE["value"] = None
        for block in _STATE["blocks"]:
            try:
                block.close()
            except BufferError:
                pass
        name, size = ref
        block = shared_memory.SharedMemory(name=name)
        payload = bytes(block.buf[:size])
        block.close()
        blocks: list = []
        _STATE["value"] = _AttachingUnpickler(io.BytesIO(payload), blocks).load()
        _STATE["blocks"], _STATE["key"] = blocks, key
    return _STATE["value"]


def _run(task):
    key, ref, function, args = task
    return function(_load(key, ref), *args)


@contextmanager
def sigint_held():
    """Hold Ctrl-C (SIGINT) back for the duration, then raise it: around starting worker processes and sharing.

    The terminal sends SIGINT to the whole process, and the kernel hands such a signal to any thread that
    does not block it (NumPy's BLAS threads, for one). So two holds, both needed:

    * this thread blocks it, and the worker processes it starts inherit that mask through exec: a Ctrl-C
      during a worker's start-up stays pending there (:func:`_init_worker` then ignores it) instead of
      printing a KeyboardInterrupt traceback from the child;
    * Python's handler only records it, whichever thread received it. A mask alone is not enough: with the
      signal delivered to another thread, this one raised KeyboardInterrupt between spawning a worker and
      sending it its start-up data, and the worker printed ``EOFError: Ran out of input``.

    On leaving, the previous handler is back and a recorded signal is raised again, so the caller's
    KeyboardInterrupt comes right after the block. Threads other than the main one only run the body; where
    the SIGINT handler was not installed from Python (inside Blender), only the mask applies. Also used by
    ``batch.run`` around starting its worker processes and Dask workers. The pool's own threads, started
    meanwhile, keep the mask, so workers they start later are covered too.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    from multiprocessing import resource_tracker

    with collector_held():
        resource_tracker.ensure_running()  # starting its process unblocks SIGINT here: start it first
    caught: list[int] = []
    handler = signal.getsignal(signal.SIGINT)
    if handler is not None:
        signal.signal(signal.SIGINT, lambda signum, _frame: caught.append(signum))
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # first: a pending SIGINT is recorded, not raised here
        if handler is not None:
            signal.signal(signal.SIGINT, handler)
    if caught:
        signal.raise_signal(signal.SIGINT)  # now with the caller's handler: KeyboardInterrupt for the CLI


class _Pool:
    def __init__(self, n: int, warm_up: str):
        ctx = mp.get_context("spawn")
        ctx.set_executable(python_executable())
        saved = {k: os.environ.get(k) for k in _BLAS_ENV}
        main = sys.modules.get("__main__")
        main_file = getattr(main, "__file__", None)
        try:
            os.environ.update({k: "1" for k in _BLAS_ENV})
            if main_file is not None:  # children must not re-run the parent's script
                del main.__file__
            with sigint_held(), collector_held():  # workers start with SIGINT blocked and ignore it (_init_worker)
                self.pool = ctx.Pool(n, initializer=_init_worker, initargs=(warm_up,))
        finally:
            if main_file is not None:
                main.__file__ = main_file
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        self.n = n

    def close(self) -> None:
        self.pool.terminate()
        self.pool.join()


_POOL: _Pool | None = None
_POOL_LOCK = threading.Lock()


def pool(n: int, warm_up: str = "") -> _Pool:
    """The persistent pool of ``n`` worker processes (created on first use, replaced when n changes).

    ``warm_up`` names a module the new workers import as they start (the caller's own, which its tasks need).
    """
    global _POOL
    with _POOL_LOCK:
        if _POOL is None or _POOL.n != n:
            if _POOL is not None:
                _POOL.close()
            _POOL = _Pool(n, warm_up)
        return _POOL


def shutdown() -> None:
    """Stop the worker processes (also at interpreter exit)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is not None:
            _POOL.close()
            _POOL = None


atexit.register(shutdown)


def run(n: int, shared: Shared, key: str, function, arg_list, cancel=None):
    """Apply ``function(shared object, *args)`` for each args in ``arg_list`` on n worker processes.

    Yields the results as they finish (any order). When ``cancel()`` turns True, the pool is stopped
    (restarted on the next use) and the generator ends early; the caller raises.
    """
    p = pool(n)
    tasks = [(key, shared.ref, function, tuple(args)) for args in arg_list]
    try:
        for result in p.pool.imap_unordered(_run, tasks):
            yield result
            if cancel is not None and cancel():
                shutdown()
                return
    except BaseException:
        shutdown()  # a worker error or an interrupt leaves tasks in flight: start afresh next time
        raise
