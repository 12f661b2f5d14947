"""The compiled tracer: the NumPy tracer's paths as compiled scalar code (optional; needs numba).

``pip install "tofcore[compiled]"`` adds numba; then :func:`tofcore.trace` and :func:`tofcore.render`
trace on the CPU with :mod:`tofcore.compiled.kernels` — one loop per path over compiled functions, every
pixel of a chunk on numba's threads — wherever the render uses only what those kernels implement, and
fall back to the NumPy reference otherwise, saying why in ``stats["transport"]["tracer_reason"]`` of
the frame (frame.json) and in ``tofcore render --verbose``. The frame is the NumPy frame up to the last
bits of transcendental functions (tests/tofcore/test_compiled.py states and tests the tolerance).

That choice is made in one place, :func:`tofcore.compiled.tracer.choose`, whose
:class:`~tofcore.compiled.tracer.CompiledTracer` then runs the passes; this module says what the machine
offers (numba, its CUDA target, the cached kernels), for the tracer, the CLI and the Blender add-on.

Environment: ``TOFCORE_TRACER=numpy`` forces the NumPy reference, ``compiled`` makes a render that
cannot use the compiled tracer an error instead of a fall-back, ``auto`` (default) picks it when it
can. The machine code is cached by numba in the user's cache folder
(``~/.cache/tofcore/numba-<hash>``, ``$XDG_CACHE_HOME`` where set; ``tofcore/compiled/__pycache__`` where
no home folder is writable; ``$NUMBA_CACHE_DIR/tofcore-<hash>`` where that variable is set), ``<hash>``
naming the kernels' source and constants, so a changed constant never loads stale code and a reinstall of
the same version loads what was compiled before (:mod:`tofcore.compiled._target`): the first render of a
fresh install compiles for 30–80 s (docs/benchmarks.md), later processes load the kernels in about a second.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

TRACER_ENV = "TOFCORE_TRACER"
TRACERS = ("auto", "numpy", "compiled")


def numba_version() -> str | None:
    """The installed numba's version, or None where it cannot be imported.

    The first call, before numba is imported, checks ``NUMBA_NUM_THREADS``: a value that is not a positive
    integer (``abc``, ``0``) is one note and is ignored (numba then uses every CPU), where numba itself would
    print a parse traceback or refuse to run parallel code."""
    if "numba" not in sys.modules:
        _check_thread_variable()
    try:
        import numba
    except Exception:  # ImportError, or a numba that does not work with this NumPy
        return None
    return numba.__version__


def cuda_unavailable() -> str:
    """Why numba cannot run the compiled tracer on this machine's GPU, or ""."""
    try:
        from numba import cuda
        available = cuda.is_available()
    except Exception as exc:  # numba without its CUDA target (numba-cuda), or a broken driver
        return f"numba's CUDA target cannot be loaded ({type(exc).__name__}: {str(exc).splitlines()[0][:120]})"
    return "" if available else "numba finds no CUDA GPU (install numba-cuda beside CuPy)"


def _check_thread_variable() -> None:
    """``NUMBA_NUM_THREADS`` that is not a positive integer: removed from the environment, with one note."""
    from ._target import note

    text = os.environ.get("NUMBA_NUM_THREADS")
    if text is None or (text.strip().isdigit() and int(text) > 0):
        return
    del os.environ["NUMBA_NUM_THREADS"]
    note(f"environment: NUMBA_NUM_THREADS must be a positive integer, got {text!r}: ignored (numba then uses its "
         f"default, one thread per CPU)")


def thread_count(workers: int) -> int:
    """numba threads a render with ``workers`` uses: at most numba's pool (``NUMBA_NUM_THREADS``)."""
    import numba

    return max(1, min(int(workers), numba.config.NUMBA_NUM_THREADS))


def cpu_kernels_cached() -> bool | None:
    """Whether the CPU build of the kernels is in numba's cache and can be loaded (a render then loads it in
    about a second); None where the compiled tracer will not run on the CPU (no numba, ``TOFCORE_TRACER=numpy``).

    True only when the drivers' (``kernels.trace_pixels``, ``kernels.first_hits``) index files are numba's, of this numba version and of
    these sources, and every data file it names is a whole pickle (:func:`tofcore.compiled._target.complete_pickle`):
    an emptied index, a truncated data file or a cache folder that cannot be used (the kernels are then compiled
    in every process) is False. A driver cached for other argument types still compiles."""
    if os.environ.get(TRACER_ENV, "").strip().lower() == "numpy" or numba_version() is None:
        return None
    from . import kernels  # decorating the kernels picks their cache folder; it compiles nothing
    from ._target import CACHE_FOLDERS

    if CACHE_FOLDERS.get(kernels.__name__) is None:
        return False
    return all(_index_is_whole(driver._cache) for driver in (kernels.trace_pixels, kernels.first_hits))


def cpu_warm() -> bool | None:
    """Whether ``tofcore warmup --device cpu`` would find everything a CPU render compiles in numba's cache: the
    kernels (:func:`cpu_kernels_cached`) and the compiled loops of the BVH's build, both builds of each
    (:func:`tofcore.scene.bvh_build.warm_up`, meshes of 4,096 triangles or more); None where the compiled tracer
    will not run on the CPU. A batch warms the cache once before its workers where this is False (batch/warmup.py)."""
    cached = cpu_kernels_cached()
    if not cached:
        return cached
    return bvh_build_cached()


def bvh_build_cached() -> bool:
    """Whether numba's cache holds every compiled loop of the BVH's build, both builds of each
    (:func:`tofcore.scene.bvh_build.warm_up`), whole."""
    from ..scene import bvh_build

    return all(hasattr(driver._cache, "_cache_file") and _index_is_whole(driver._cache)  # not numba's NullCache
               for driver in bvh_build.DRIVERS)


def _index_is_whole(cache) -> bool:
    """Whether a numba function cache's index loads (version, source stamp) and names only whole data files."""
    import pickle

    import numba

    cache_file = cache._cache_file
    try:
        with open(cache_file._index_path, "rb") as fh:
            version = pickle.load(fh)
            stamp, overloads = pickle.loads(fh.read())
    except Exception:  # missing, emptied, truncated: numba would fail or compile
        return False
    from ._target import complete_pickle

    return (version == numba.__version__ and stamp == cache._impl.locator.get_source_stamp() and bool(overloads)
            and all(complete_pickle(os.path.join(cache.cache_path, name)) for name in overloads.values()))


def cache_problem() -> str:
    """Why the CPU kernels cannot be cached (their folder cannot be used: they are compiled in every process), or
    "" (also where the compiled tracer does not run on the CPU)."""
    if cpu_kernels_cached() is None:
        return ""
    from ._target import unusable_reason

    return unusable_reason()


def cache_location() -> str:
    """Where numba keeps the compiled kernels: the CPU build's folder once the kernels are imported
    (:func:`tofcore.compiled._target.cache_folder`: the user's cache folder); before that ``NUMBA_CACHE_DIR``,
    else ``__pycache__`` beside the sources, else numba's user cache."""
    import numba

    from . import _target

    if _target.CACHE_FOLDERS.get(__name__ + ".kernels"):
        return str(_target.CACHE_FOLDERS[__name__ + ".kernels"])
    if numba.config.CACHE_DIR:
        return str(numba.config.CACHE_DIR)
    here = Path(__file__).resolve().parent
    return str(here / "__pycache__") if os.access(here, os.W_OK) else "numba's user cache (~/.cache/numba)"
