"""Which compiler a source module of this package is compiled by: the CPU (``numba.njit``) or CUDA, and
where the CPU's machine code is cached.

The scalar functions of :mod:`tofcore.compiled.kernels` are written once. Imported as usual they are
compiled for the CPU; :func:`tofcore.compiled.gpu.load_kernels` executes the same file again under the
module name ``tofcore.compiled.kernels_cuda``, and for that name :func:`device_function` returns
``numba.cuda.jit(device=True)`` instead (the one-source route of issue 21, as Mitsuba 3 builds its
scalar/LLVM/CUDA variants and pbrt-v4 marks shared code ``PBRT_CPU_GPU``).

Cache safety: numba reuses cached machine code while the source file's stamp (a hash of its bytes) and
the function's bytecode are unchanged, but the module's constants, read from other modules (rng, qmc,
bsdf, surface, sampler, layout), are frozen into that code, and numba's options are not part of its key
either. So the code is cached in a folder named after :func:`content_fingerprint` (a hash of the source
file's bytes, of every constant of the module and of :data:`CPU_DECORATORS`): changing a constant
anywhere, or an option, compiles anew instead of loading stale code, and each version of the kernels
keeps its own folder. That folder is in the user's cache folder (:func:`cache_folder`), not beside the
sources: reinstalling the same version (a Blender extension's zip replaces its whole folder) finds the
kernels compiled before.

A cache that cannot be used never stops a render (issue 35):

* a damaged file (a truncated ``.nbc``, an emptied ``.nbi``: a disk that filled up, a copy cut short) is
  set aside — the function's index and data files renamed ``*.damaged`` beside them, not deleted — and
  the function compiled anew and cached again (:func:`guarded_cache_class`);
* a cache that cannot be written (a full disk, a folder made read-only) leaves the kernels compiled in
  this process; the next process compiles them again;
* a folder that cannot be used at all (``NUMBA_CACHE_DIR`` read-only or under a regular file) is named
  with that cost: every process compiles the kernels again (:func:`cache_folder`).

Each of these is said once per process, as a :class:`CompiledWarning` (:func:`note`).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import sys
import tempfile
import warnings

import numpy as np

CUDA_SUFFIX = "_cuda"

CPU_OPTIONS = dict(nogil=True, error_model="numpy", fastmath=False)
"""numba options of every CPU function: ``nogil`` (threads run it in parallel), ``error_model="numpy"`` (a
division by zero gives inf/NaN as NumPy does, never an exception), no fast-math (IEEE rounding, as NumPy)."""


def constants_fingerprint(namespace: dict, options: dict | None = None) -> str:
    """16 hex digits of SHA-256 over the constants of a module namespace (and compiler ``options``).

    A constant is a global whose name does not start with ``__`` and whose value is a bool, int, float,
    str, NumPy scalar or array, or a tuple of those; functions, classes and modules are not hashed (numba
    keys a function's own bytecode itself). Names are hashed in sorted order with each value's type,
    dtype, shape and bytes, so any changed value, element or dtype changes the fingerprint.
    """
    digest = hashlib.sha256(repr(sorted((options or {}).items())).encode())
    for name in sorted(namespace):
        if name.startswith("__"):
            continue
        encoded = _encode(namespace[name])
        if encoded is not None:
            digest.update(name.encode() + b"=" + encoded + b";")
    return digest.hexdigest()[:16]


def content_fingerprint(namespace: dict, options: dict | None = None) -> str:
    """16 hex digits of SHA-256 over the bytes of the module's source file (``namespace["__file__"]``) and its
    :func:`constants_fingerprint`: what the machine code compiled from the module depends on."""
    digest = hashlib.sha256(constants_fingerprint(namespace, options).encode())
    with open(namespace["__file__"], "rb") as source:
        digest.update(source.read())
    return digest.hexdigest()[:16]


def _encode(value) -> bytes | None:
    """Bytes that identify a constant's value exactly, or None for anything that is not a constant."""
    if isinstance(value, (bool, int, float, str, np.generic)):
        return f"{type(value).__name__}:{value!r}".encode()
    if isinstance(value, np.ndarray):
        return f"ndarray:{value.dtype.str}:{value.shape}:".encode() + np.ascontiguousarray(value).tobytes()
    if isinstance(value, tuple):
        parts = [_encode(v) for v in value]
        return None if any(p is None for p in parts) else b"(" + b",".join(parts) + b")"
    return None


class CompiledWarning(UserWarning):
    """Something about the compiled tracer's environment a user should know (its cache, its threads); the
    render goes on. Each message is warned once per process (:func:`note`)."""


NOTES: list[str] = []
"""What :func:`note` has said in this process, in order."""


def note(message: str) -> None:
    """Warn ``message`` as a :class:`CompiledWarning`, once per process."""
    if message not in NOTES:
        NOTES.append(message)
        warnings.warn(message, CompiledWarning, stacklevel=2)


RECOMPILE_COST = "about 15 s on 2 cores"
"""What compiling the CPU kernels costs (docs/benchmarks.md), for the notes."""

UNUSABLE: dict[str, str] = {}
"""Cache folder (``NUMBA_CACHE_DIR``'s or the default ones) → why it cannot be used, for those tried and refused."""


def cache_folder(source_file: str, fingerprint: str) -> str | None:
    """The writable folder for the machine code of ``source_file`` compiled as ``fingerprint`` says.

    ``$NUMBA_CACHE_DIR/tofcore-<fingerprint>`` where that variable is set, else the user's cache folder
    ``$XDG_CACHE_HOME`` (``~/.cache``) ``/tofcore/numba-<fingerprint>``, which outlives a reinstall, else
    (no writable home) ``__pycache__/numba-<fingerprint>`` beside the source; None where none can be written
    (the functions are then compiled in each process, never loaded stale: said once, naming the folders
    and that cost, :func:`note`).
    """
    import numba

    if numba.config.CACHE_DIR:
        candidates = [os.path.join(numba.config.CACHE_DIR, f"tofcore-{fingerprint}")]
    else:
        user_cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        candidates = [os.path.join(user_cache, "tofcore", f"numba-{fingerprint}"),
                      os.path.join(os.path.dirname(os.path.abspath(source_file)), "__pycache__",
                                   f"numba-{fingerprint}")]
    for folder in candidates:
        try:
            os.makedirs(folder, exist_ok=True)
            with tempfile.TemporaryFile(dir=folder):
                return folder
        except OSError as exc:
            UNUSABLE[folder] = exc.strerror or str(exc)
    where = (f"NUMBA_CACHE_DIR={numba.config.CACHE_DIR}" if numba.config.CACHE_DIR
             else " and ".join(candidates))
    note(f"the compiled tracer's kernel cache {where} cannot be used ({UNUSABLE[candidates[-1]]}): the kernels are "
         f"compiled again in every process ({RECOMPILE_COST} each); point NUMBA_CACHE_DIR at a writable folder")
    return None


def unusable_reason() -> str:
    """Why the CPU kernels are compiled in every process (their cache folder cannot be used), or ""."""
    if "tofcore.compiled.kernels" in CACHE_FOLDERS and CACHE_FOLDERS["tofcore.compiled.kernels"] is None:
        return next((n for n in NOTES if "cannot be used" in n), "their cache folder cannot be used")
    return ""


def set_aside(paths: list[str]) -> list[str]:
    """Rename each existing file of ``paths`` to ``<name>.damaged`` (replacing an older one); the new names."""
    moved = []
    for path in paths:
        try:
            os.replace(path, path + ".damaged")
            moved.append(path + ".damaged")
        except FileNotFoundError:
            continue
        except OSError:  # a read-only folder: the damaged file stays, the function is compiled in each process
            continue
    return moved


def complete_pickle(path: str) -> bool:
    """Whether ``path`` holds a whole pickle as numba writes them (protocol 4+: its first frame's declared
    length fits in the file, and the file ends with the STOP opcode) — read in two small pieces, not loaded."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(11)
            size = os.fstat(fh.fileno()).st_size
            if len(head) < 3 or head[0] != 0x80:
                return False
            if head[2] == 0x95 and (len(head) < 11 or 11 + int.from_bytes(head[3:11], "little") > size):
                return False
            fh.seek(size - 1)
            return fh.read(1) == b"."
    except OSError:
        return False


@functools.cache
def guarded_cache_class():
    """numba's ``FunctionCache`` guarded against damaged and unwritable files (made on first use: numba is
    imported then)."""
    from numba.core.caching import FunctionCache

    class GuardedCache(FunctionCache):
        """numba's per-function cache, where a damaged file is set aside and compiled anew, and a file that
        cannot be written leaves the function compiled (module docstring)."""

        def load_overload(self, sig, target_context):
            try:
                return super().load_overload(sig, target_context)
            except Exception as exc:  # UnpicklingError, EOFError, ValueError, … of a damaged file
                cache_file = self._cache_file
                base = cache_file._index_path[:-len(".nbi")]
                folder = os.path.dirname(base)
                data = [os.path.join(folder, n) for n in os.listdir(folder)
                        if n.startswith(os.path.basename(base) + ".") and n.endswith(".nbc")] \
                    if os.path.isdir(folder) else []
                moved = set_aside([cache_file._index_path, *data])
                note(f"the compiled tracer's kernel cache {os.path.basename(base)}.* in {folder} was damaged "
                     f"({type(exc).__name__}: {str(exc)[:80]}); {len(moved)} file(s) set aside as *.damaged, "
                     f"compiled anew (up to {RECOMPILE_COST}) and cached again")
                return None

        def save_overload(self, sig, data):
            try:
                super().save_overload(sig, data)
            except OSError as exc:  # a full disk, a folder made read-only meanwhile
                note(f"the compiled tracer's kernel cache {self._cache_path} cannot be written "
                     f"({exc.strerror or exc}): the kernels are compiled in this process and again in the next "
                     f"({RECOMPILE_COST}); the render goes on")

    return GuardedCache


@contextlib.contextmanager
def _numba_cache_dir(folder: str):
    """numba's cache folder set to ``folder`` while functions are decorated (numba reads it then)."""
    import numba

    before = numba.config.CACHE_DIR
    numba.config.CACHE_DIR = folder
    try:
        yield
    finally:
        numba.config.CACHE_DIR = before


CPU_DECORATORS = {"device": dict(_nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True, **CPU_OPTIONS),
                  "parallel": dict(parallel=True, **CPU_OPTIONS)}
"""numba options of the scalar functions and of the driver. The scalar functions allocate nothing (no reference
counting) and are called only by compiled code, the drivers' or a test's jitted loop, never from Python: numba
builds them no CPython or C wrapper (which it would compile and optimise for every overload: the wrappers of
functions taking the scene's tuples of arrays are large), 30 % of the kernels' first compile (19.6 → 13.9 s
for the warm-up's frame on 2 cores)."""

CACHE_FOLDERS: dict[str, str | None] = {}
"""Module name → the cache folder of its CPU machine code (:func:`cache_folder`), once decorated."""


def _cpu_jit(module_name: str, kind: str):
    """``numba.njit`` with the options :data:`CPU_DECORATORS` ``[kind]``, cached in the module's folder."""
    import numba

    if module_name not in CACHE_FOLDERS:
        namespace = vars(sys.modules[module_name])
        CACHE_FOLDERS[module_name] = cache_folder(namespace["__file__"],
                                                  content_fingerprint(namespace, CPU_DECORATORS))
    folder, options = CACHE_FOLDERS[module_name], CPU_DECORATORS[kind]

    def decorate(function):
        if folder is None:
            dispatcher = numba.njit(**options)(function)
        else:
            with _numba_cache_dir(folder):
                dispatcher = numba.njit(cache=True, **options)(function)
            dispatcher._cache.__class__ = guarded_cache_class()  # same state, guarded load and save
        if options.get("no_cpython_wrapper"):
            dispatcher.__class__ = jitted_only_class(type(dispatcher))
        return dispatcher

    return decorate


@functools.cache
def jitted_only_class(dispatcher_class):
    """``dispatcher_class`` (numba's ``CPUDispatcher``) for functions built without a CPython wrapper
    (:data:`CPU_DECORATORS`): called from Python, one of them raises a TypeError that says so, where numba
    would jump to the missing wrapper and crash the interpreter. Calls from jitted code do not pass here."""

    class JittedOnly(dispatcher_class):
        def __call__(self, *args, **kwargs):
            raise TypeError(f"tofcore.compiled: {self.py_func.__name__} is compiled for calls from jitted code only "
                            f"(no Python wrapper, _target.CPU_DECORATORS); call it from a numba.njit function")

    return JittedOnly


def device_function(module_name: str):
    """The decorator that compiles the scalar functions of module ``module_name`` (call it below the
    module's constants: they are hashed then, see :func:`constants_fingerprint`).

    CPU: ``njit`` with :data:`CPU_OPTIONS` and without numba's reference counting (``_nrt=False``: these
    functions allocate nothing, and the atomic increments and decrements of every array passed took ≈ 7 %
    of a thread's profile, on counters that all threads write), cached in :func:`cache_folder`. CUDA:
    ``cuda.jit(device=True)``.
    """
    if module_name.endswith(CUDA_SUFFIX):
        from numba import cuda
        return cuda.jit(device=True)
    return _cpu_jit(module_name, "device")


def cpu_parallel_function(module_name: str):
    """The decorator of the CPU driver that runs paths on numba's threads (``prange``); for CUDA the
    function stays plain Python, never called (:mod:`tofcore.compiled.cuda` has its own kernel).

    It lives in the same file as the functions it calls: numba's cache checks only the stamp of a
    function's own source file, so a driver cached in another file would keep stale inlined kernels.
    """
    if module_name.endswith(CUDA_SUFFIX):
        return lambda function: function
    return _cpu_jit(module_name, "parallel")


def gpu_kernel_function(module_name: str):
    """The decorator of a CUDA kernel written beside the functions it calls: ``numba.cuda.jit`` with the
    machine code cached in the folder of the module's source and constants (:func:`cache_folder` of
    :func:`content_fingerprint`, as for the CPU build: a changed constant compiles anew); for the CPU
    build the function stays plain Python and is never called."""
    if not module_name.endswith(CUDA_SUFFIX):
        return lambda function: function
    from numba import cuda

    namespace = vars(sys.modules[module_name])
    folder = cache_folder(namespace["__file__"], content_fingerprint(namespace, {"target": "cuda"}))
    try:
        from numba.cuda.core import config  # numba-cuda keeps its own copy of numba's settings
    except ImportError:
        config = None

    def decorate(function):
        if folder is None:
            return cuda.jit(function)
        if config is None:
            return cuda.jit(cache=True)(function)
        before = config.CACHE_DIR
        config.CACHE_DIR = folder  # read when the kernel's cache is made, that is now
        try:
            return cuda.jit(cache=True)(function)
        finally:
            config.CACHE_DIR = before

    return decorate


def numba_cuda():
    """``numba.cuda``, imported after giving NumPy 2.5 back ``np.row_stack`` (removed there; numba-cuda 0.30 still
    registers an overload for it, and its import fails without it)."""
    if not hasattr(np, "row_stack"):
        np.row_stack = np.vstack
    from numba import cuda

    return cuda


_CUDA_BUILDS: dict[str, object] = {}
"""Source file → its CUDA build (:func:`load_cuda_build`), once per process."""


def load_cuda_build(source_module_name: str, source_file: str):
    """The module ``source_file`` compiled for CUDA: the file executed again under the name
    ``source_module_name + CUDA_SUFFIX``, for which the decorators above return numba.cuda's (once per process)."""
    if source_file not in _CUDA_BUILDS:
        import importlib.util

        numba_cuda()

        name = source_module_name + CUDA_SUFFIX
        spec = importlib.util.spec_from_file_location(name, source_file)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        _CUDA_BUILDS[source_file] = module
    return _CUDA_BUILDS[source_file]


def gpu_module(module_name: str):
    """``numba.cuda`` for the CUDA build of a module (its kernels read ``cuda.grid``, ``cuda.local``), else None
    (the CPU build never imports numba's CUDA target)."""
    if module_name.endswith(CUDA_SUFFIX):
        from numba import cuda
        return cuda
    return None
