"""A stand-in for CuPy on machines without a GPU: NumPy arrays behind CuPy's rules.

CI has no GPU, yet the GPU path must be exercised there: every function that
builds arrays with ``np.zeros`` instead of ``xp.zeros``, or mixes a host table
into a device expression, breaks on a real GPU. This module wraps NumPy
arrays in a type that behaves as ``cupy.ndarray`` does where it matters:

* NumPy functions and ufuncs dispatch to it (NEP 13/18), as they do to CuPy;
* it refuses implicit conversion to NumPy (``np.asarray(x)`` raises TypeError,
  like CuPy) — the only way back is ``asnumpy``/``.get()``;
* it refuses to mix with NumPy arrays of one or more dimensions in any
  operation (CuPy raises TypeError there too); Python and NumPy scalars mix;
* reductions return 0-d device arrays, not scalars.

:func:`counting` counts what a real GPU would pay for: device arrays allocated (every new array an
operation or an upload makes; views are free) and host synchronisations (every value read back:
``bool()``/``float()``/``int()`` of a device array, ``.item()``, ``.tolist()``, ``.get()``,
``asnumpy``).

The CUDA kernels of :mod:`tofcore.gpu` cannot run here; tests replace them by
their NumPy twins through :func:`install` (with a host round trip), so the
rest of the GPU path is the code that runs on the GPU.
"""

from __future__ import annotations

import contextlib
import enum
import types
from collections import Counter

import numpy as np
from numpy.lib.mixins import NDArrayOperatorsMixin

__version__ = "fake"

_COUNTS: list[Counter] = []  # the open counting() blocks


@contextlib.contextmanager
def counting():
    """Count device arrays allocated (``"arrays"``, of which ``"uploads"``) and host syncs (``"syncs"``)
    inside the block: ``with counting() as counts: ...; counts["arrays"]``."""
    counts = Counter(arrays=0, uploads=0, syncs=0)
    _COUNTS.append(counts)
    try:
        yield counts
    finally:
        _COUNTS.remove(counts)


def _count(key: str) -> None:
    for counts in _COUNTS:
        counts[key] += 1


@contextlib.contextmanager
def _one_kernel():
    """A CUDA kernel's NumPy twin runs inside: its host round trip is not counted, its output is one array."""
    saved = list(_COUNTS)
    _COUNTS.clear()
    try:
        yield
    finally:
        _COUNTS.extend(saved)
        _count("arrays")


class ndarray(NDArrayOperatorsMixin):  # noqa: N801 - mirrors cupy.ndarray
    __array_priority__ = 1000

    def __init__(self, array: np.ndarray):
        self._a = array

    # -- protocol --------------------------------------------------------------
    def __array__(self, *args, **kwargs):
        raise TypeError("fakecupy: implicit conversion to a NumPy array is not allowed (use asnumpy)")

    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):
        where = f"np.{ufunc.__name__}"
        result = getattr(ufunc, method)(*_unwrap(inputs, where), **_unwrap(kwargs, where))
        out = kwargs.get("out")
        if out is not None:  # in-place: hand back the caller's device arrays
            return out[0] if len(out) == 1 else out
        return _wrap(result)

    def __array_function__(self, func, types_, args, kwargs):
        where = f"np.{func.__name__}"
        return _wrap(func(*_unwrap(args, where), **_unwrap(kwargs, where)))

    # -- indexing --------------------------------------------------------------
    def __getitem__(self, key):
        return _wrap(self._a[_unwrap(key, "indexing")])

    def __setitem__(self, key, value):
        self._a[_unwrap(key, "indexing")] = _unwrap(value, "assignment")

    # -- attributes --------------------------------------------------------------
    shape = property(lambda self: self._a.shape)
    dtype = property(lambda self: self._a.dtype)
    ndim = property(lambda self: self._a.ndim)
    size = property(lambda self: self._a.size)
    nbytes = property(lambda self: self._a.nbytes)
    T = property(lambda self: ndarray(self._a.T))

    def __len__(self):
        return len(self._a)

    def __iter__(self):
        return (_wrap(x) for x in self._a)

    def __bool__(self):
        _count("syncs")
        return bool(self._a)

    def __float__(self):
        _count("syncs")
        return float(self._a)

    def __int__(self):
        _count("syncs")
        return int(self._a)

    def __index__(self):
        _count("syncs")
        return self._a.__index__()

    def __repr__(self):
        return f"fakecupy.ndarray({self._a!r})"

    def get(self):
        _count("syncs")
        return self._a.copy()

    def __getattr__(self, name):
        if name.startswith("__"):  # no __array_interface__ & co.: NumPy must not read the data implicitly
            raise AttributeError(name)
        attr = getattr(self._a, name)
        if not callable(attr):
            return attr

        def method(*args, **kwargs):
            where = f"ndarray.{name}"
            if name in ("item", "tolist"):
                _count("syncs")
            return _wrap(attr(*_unwrap(args, where), **_unwrap(kwargs, where)))

        return method


def _unwrap(x, where: str):
    if isinstance(x, ndarray):
        return x._a
    if isinstance(x, np.ndarray):
        raise TypeError(f"fakecupy: a NumPy array of shape {x.shape} in {where} (host data in a device expression)")
    if isinstance(x, enum.Enum):  # CuPy takes exact Python/NumPy scalars only, not IntEnum members
        raise TypeError(f"fakecupy: an enum member {x!r} in {where} (use int(...))")
    if isinstance(x, tuple):
        return tuple(_unwrap(v, where) for v in x)
    if isinstance(x, list):
        return [_unwrap(v, where) for v in x]
    if isinstance(x, dict):
        return {k: _unwrap(v, where) for k, v in x.items()}
    return x


def _wrap(x):
    if isinstance(x, np.ndarray):
        if x.base is None:  # a new array, not a view
            _count("arrays")
        return ndarray(x)
    if isinstance(x, np.generic) and not isinstance(x, (np.str_, np.bytes_)):
        _count("arrays")
        return ndarray(np.asarray(x))  # CuPy reductions give 0-d device arrays
    if isinstance(x, tuple):
        return type(x)(*(_wrap(v) for v in x)) if hasattr(x, "_fields") else tuple(_wrap(v) for v in x)
    if isinstance(x, list):
        return [_wrap(v) for v in x]
    return x


# -- the module's functions ---------------------------------------------------------
def asarray(x, dtype=None, order=None):
    """Upload: NumPy arrays are accepted here, as by ``cupy.asarray``."""
    if isinstance(x, ndarray):
        if dtype is None or x._a.dtype == np.dtype(dtype):
            return x
        _count("arrays")
        return ndarray(x._a.astype(dtype))
    _count("arrays")
    _count("uploads")
    return ndarray(np.array(x, dtype=dtype, order=order, copy=True))


array = asarray


def asnumpy(x):
    if isinstance(x, ndarray):
        _count("syncs")
        return x._a.copy()
    return np.asarray(x)


def ascontiguousarray(x, dtype=None):
    return asarray(x, dtype=dtype)


def _device_function(fn):
    def call(*args, **kwargs):
        where = f"fakecupy.{getattr(fn, '__name__', fn)}"
        return _wrap(fn(*_unwrap(args, where), **_unwrap(kwargs, where)))

    return call


class _Submodule:
    def __init__(self, module):
        self._module = module

    def __getattr__(self, name):
        attr = getattr(self._module, name)
        return _device_function(attr) if callable(attr) else attr


fft = _Submodule(np.fft)
linalg = _Submodule(np.linalg)


def __getattr__(name):
    attr = getattr(np, name)
    if isinstance(attr, (types.FunctionType, types.BuiltinFunctionType, np.ufunc)) or (
            callable(attr) and not isinstance(attr, type)):
        return _device_function(attr)
    return attr  # dtypes, constants


def install(monkeypatch) -> None:
    """Make ``device="gpu"`` run on this fake, with the CUDA kernels replaced by their NumPy twins."""
    import sys

    from tofcore import backend
    from tofcore import rng
    from tofcore.scene import bvh, fresnel
    from tofcore.sensor import modulation, noise
    from tofcore.tracer import qmc
    from tofcore import fused
    from tofcore.gpu import traversal

    module = sys.modules[__name__]
    backend.register_array_module(ndarray, module)
    monkeypatch.setattr(backend, "_gpu_module", lambda: (module, "fake GPU (NumPy behind CuPy's rules)"))

    def host(x):
        return None if x is None else asnumpy(x)

    def intersect(tree, origins, directions, t_max=None, ignore_prim=None, *, workers=2, counters=None):
        hits = tree._run(host(origins), host(directions), host(t_max), host(ignore_prim), False, 1, None)
        return bvh.Hits(*(asarray(x) for x in (hits.t, hits.prim, hits.u, hits.v)))

    def occluded(tree, origins, directions, t_max, ignore_prim=None, *, workers=2, counters=None):
        return asarray(tree._run(host(origins), host(directions), host(t_max), host(ignore_prim), True, 1, None))

    def uniform(key, pixel, sample, dim):
        with _one_kernel():
            return asarray(rng.uniform(key, asnumpy(pixel), asnumpy(sample), dim))

    def scrambled_2d(key, pixel, sample, dim):
        return tuple(asarray(v) for v in qmc.scrambled_2d(key, asnumpy(pixel), asnumpy(sample), dim))

    def scrambled_1d(key, pixel, sample, dim):
        return asarray(qmc.scrambled_1d(key, asnumpy(pixel), asnumpy(sample), dim))

    def twin(numpy_function):  # the kernel's NumPy twin, through a host round trip
        def run(*args, **kwargs):
            with _one_kernel():
                return asarray(numpy_function(*(asnumpy(a) if isinstance(a, ndarray) else a for a in args),
                                              **kwargs))
        return run

    monkeypatch.setattr(traversal, "intersect", intersect)
    monkeypatch.setattr(traversal, "occluded", occluded)
    monkeypatch.setattr(fused, "uniform", uniform)
    monkeypatch.setattr(fused, "scrambled_2d", scrambled_2d)
    monkeypatch.setattr(fused, "scrambled_1d", scrambled_1d)
    monkeypatch.setattr(fused, "fresnel_dielectric", twin(fresnel.fresnel_dielectric))
    monkeypatch.setattr(fused, "fresnel_conductor", twin(fresnel.fresnel_conductor))
    monkeypatch.setattr(fused, "square_correlation", twin(modulation.square_correlation))
    monkeypatch.setattr(fused, "poisson", twin(noise.poisson))
