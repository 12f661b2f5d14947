"""Which compiler a source module of this package is compiled by: the CPU (``numba.njit``) or CUDA.

The scalar functions of :mod:`tofcore.compiled.kernels` are written once. Imported as usual they are
compiled for the CPU; :func:`tofcore.compiled.gpu.load_kernels` executes the same file again under the
module name ``tofcore.compiled.kernels_cuda``, and for that name :func:`device_function` returns
``numba.cuda.jit(device=True)`` instead (the one-source route of issue 21, as Mitsuba 3 builds its
scalar/LLVM/CUDA variants and pbrt-v4 marks shared code ``PBRT_CPU_GPU``).
"""

from __future__ import annotations

CUDA_SUFFIX = "_cuda"


def device_function(module_name: str):
    """The decorator that compiles the scalar functions of module ``module_name``.

    CPU: ``njit`` with ``cache=True`` (the machine code is kept in ``__pycache__`` beside the source, else in
    ``~/.cache/numba``, or under ``NUMBA_CACHE_DIR``), ``nogil`` (threads run it in parallel), ``error_model="numpy"`` (a division
    by zero gives inf/NaN as NumPy does, never an exception), no fast-math (IEEE rounding, as NumPy).
    """
    if module_name.endswith(CUDA_SUFFIX):
        from numba import cuda
        return cuda.jit(device=True)
    import numba
    return numba.njit(cache=True, nogil=True, error_model="numpy", fastmath=False)


def cpu_parallel_function(module_name: str):
    """The decorator of the CPU driver that runs paths on numba's threads (``prange``); for CUDA the
    function stays plain Python, never called (:mod:`tofcore.compiled.cuda` has its own kernel).

    It lives in the same file as the functions it calls: numba's cache checks only the stamp of a
    function's own source file, so a driver cached in another file would keep stale inlined kernels.
    """
    if module_name.endswith(CUDA_SUFFIX):
        return lambda function: function
    import numba
    return numba.njit(parallel=True, cache=True, nogil=True, error_model="numpy", fastmath=False)



def gpu_kernel_function(module_name: str):
    """The decorator of a CUDA kernel written beside the functions it calls: ``numba.cuda.jit`` with the
    machine code cached (``cache=True``: numba's cache beside the source or under ``NUMBA_CACHE_DIR``) for
    the CUDA build; for the CPU build the function stays plain Python and is never called."""
    if module_name.endswith(CUDA_SUFFIX):
        from numba import cuda
        return cuda.jit(cache=True)
    return lambda function: function


def gpu_module(module_name: str):
    """``numba.cuda`` for the CUDA build of a module (its kernels read ``cuda.grid``, ``cuda.local``), else None
    (the CPU build never imports numba's CUDA target)."""
    if module_name.endswith(CUDA_SUFFIX):
        from numba import cuda
        return cuda
    return None
