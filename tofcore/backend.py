"""Array backends: one simulator, NumPy on the CPU (the reference) or CuPy on an NVIDIA GPU.

Every stage of tofcore is written once, against the NumPy API. Functions take
the array module from their inputs (:func:`namespace`), the way NumPy's own
``__array_function__`` protocol (NEP 18) dispatches ``np.einsum(cupy_array)``
to CuPy: a CuPy array in gives a CuPy array out, the whole wavefront stays on
the GPU. Only code that exists for the GPU alone — CUDA kernels and device
memory handling — lives in :mod:`tofcore.gpu`, each kernel with a NumPy twin
that the tests compare it with (pbrt-v4 keeps ``src/pbrt/gpu`` beside one
shared code base in the same way).

The one dispatch point for those kernels is here: :data:`KERNELS` names each reference function that
has a CUDA twin (same signature, same values) and where the twin lives; the reference is marked
:func:`device_twin` and runs its twin when a device array reaches it. So the physics modules never
import :mod:`tofcore.gpu` (which sits above them: its kernels take their constants from the Python
source), and the CPU path never imports it or CuPy. ``tests/tofcore/test_kernels.py`` walks the table.

=============  ====================================================================================
``device``     meaning
=============  ====================================================================================
``"cpu"``      NumPy; always available (Blender's Python, CI, any laptop)
``"gpu"``      CuPy on the current CUDA device (``CUDA_VISIBLE_DEVICES`` picks which); a clear
               :class:`GpuUnavailable` error when CuPy or a usable device is missing
``"auto"``     the GPU when CuPy and a CUDA device are usable, else the CPU, saying why
=============  ====================================================================================

Rules the shared code follows so that it runs on both:

* create arrays with ``xp.zeros``/``xp.full``/… where ``xp = namespace(inputs)``; never mix host
  (NumPy) arrays into device expressions — small constant tables go through :func:`device_copy`;
* Python scalars and NumPy scalars mix freely with either;
* results leave the device only through :func:`to_host` (one explicit copy).
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import inspect
import os
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType

import numpy as np

from .errors import ConfigError, TofError

DEVICES = ("cpu", "gpu", "auto")

#: Device array types and their array modules; CuPy's is added when CuPy is loaded.
_ARRAY_MODULES: dict[type, ModuleType] = {}


class GpuUnavailable(TofError):
    """The GPU backend cannot run: no CuPy, no CUDA device, or a CUDA error; the message names the cause."""


@dataclass(frozen=True)
class Device:
    """Where a render runs.

    Attributes
    ----------
    name : ``"cpu"`` or ``"gpu"``.
    xp : the array module (``numpy`` or ``cupy``).
    description : one line for logs and ``frame.json``, e.g. ``"GPU 0: NVIDIA H100 80GB HBM3 (CuPy 14.2.0)"``.
    requested : what the caller asked for (``"cpu"``, ``"gpu"`` or ``"auto"``).
    fallback_reason : why ``"auto"`` chose the CPU (``None`` otherwise).
    """

    name: str
    xp: ModuleType
    description: str
    requested: str
    fallback_reason: str | None = None

    @property
    def is_gpu(self) -> bool:
        return self.name == "gpu"

    def as_dict(self) -> dict:
        return {"name": self.name, "description": self.description, "requested": self.requested,
                "fallback_reason": self.fallback_reason}

    def __reduce__(self):
        """Pickle by name: CPU worker processes (tofcore.tracer.workers) get their own NumPy module."""
        if self.is_gpu:
            raise TypeError("a GPU Device does not pickle: GPU renders run in one process")
        return cpu_device, (self.requested, self.fallback_reason)


def cpu_device(requested: str = "cpu", fallback_reason: str | None = None) -> Device:
    return Device("cpu", np, f"CPU (NumPy {np.__version__})", requested, fallback_reason)


def select_device(device: str | Device | None = "cpu") -> Device:
    """Resolve ``device`` (``"cpu"``, ``"gpu"``, ``"auto"`` or a :class:`Device`) to a :class:`Device`.

    Raises :class:`GpuUnavailable` for ``"gpu"`` when CuPy or a CUDA device is not usable, and
    :class:`~tofcore.errors.ConfigError` for any other value. ``"auto"`` never raises for a missing GPU:
    it returns the CPU with ``fallback_reason`` set.
    """
    if isinstance(device, Device):
        return device
    if device is None:
        device = "cpu"
    if device not in DEVICES:
        raise ConfigError(f"device must be one of {list(DEVICES)}, got {device!r}")
    if device == "cpu":
        return cpu_device()
    try:
        xp, description = _gpu_module()
    except GpuUnavailable as exc:
        if device == "auto":
            return cpu_device("auto", str(exc))
        raise
    return Device("gpu", xp, description, device)


_CHECKED_GPUS: dict[int, str] = {}
"""The description of each CUDA device this process has checked (:func:`_gpu_module`), by device id: a device
that answered once is not asked again (its properties and a test launch took 1.3 ms and a synchronisation of
every render, twice per preview frame: docs/benchmarks.md). A device that fails later fails in the render,
as any CUDA error there does (:func:`gpu_errors`)."""


def _gpu_module() -> tuple[ModuleType, str]:
    """Import CuPy, check that the current CUDA device answers (once per device and process), and return
    (cupy, description)."""
    cp = _load_cupy()
    try:
        dev = cp.cuda.Device()
        checked = _CHECKED_GPUS.get(dev.id)
        if checked is not None:
            return cp, checked
        props = cp.cuda.runtime.getDeviceProperties(dev.id)
        name = props["name"].decode() if isinstance(props["name"], bytes) else str(props["name"])
        cp.zeros(1).sum().item()  # a kernel launch proves the driver, the runtime and NVRTC work
    except GpuUnavailable:
        raise
    except Exception as exc:  # CUDARuntimeError, CompileException, driver too old, ...
        raise GpuUnavailable(f"GPU: CuPy {cp.__version__} found no usable CUDA device "
                             f"({type(exc).__name__}: {_first_line(exc)})") from None
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    where = f" (CUDA_VISIBLE_DEVICES={visible})" if visible is not None else ""
    description = _CHECKED_GPUS[dev.id] = f"GPU {dev.id}{where}: {name} (CuPy {cp.__version__})"
    return cp, description


def _load_cupy() -> ModuleType:
    """Import CuPy and register its array type; :class:`GpuUnavailable` if it is not installed."""
    try:
        import cupy
    except ImportError as exc:
        raise GpuUnavailable(f"GPU: CuPy is not installed ({_first_line(exc)}); "
                             f"install it with `pip install \"tofcore[gpu]\"`") from None
    except Exception as exc:  # a broken install: missing CUDA libraries
        raise GpuUnavailable(f"GPU: CuPy failed to import ({type(exc).__name__}: {_first_line(exc)})") from None
    register_array_module(cupy.ndarray, cupy)
    return cupy


def register_array_module(array_type: type, module: ModuleType) -> None:
    """Make :func:`namespace` map arrays of ``array_type`` to ``module`` (CuPy; test doubles)."""
    _ARRAY_MODULES[array_type] = module


def gpu_count() -> int:
    """Number of CUDA devices visible to this process (0 without CuPy or a driver); starts no context."""
    try:
        cp = _load_cupy()
        return int(cp.cuda.runtime.getDeviceCount())
    except Exception:
        return 0


def namespace(*arrays) -> ModuleType:
    """The array module of the inputs: the device module if any input is a device array, else NumPy."""
    for a in arrays:
        module = _ARRAY_MODULES.get(type(a))
        if module is not None:
            return module
    return np


def is_device_array(x) -> bool:
    return type(x) in _ARRAY_MODULES


def asarray(x, dtype=None):
    """``x`` as an array of its own module (device arrays stay on their device), optionally cast."""
    return namespace(x).asarray(x, dtype=dtype)


def to_host(x):
    """A NumPy copy of a device array; NumPy arrays and other objects pass through unchanged."""
    module = _ARRAY_MODULES.get(type(x))
    return module.asnumpy(x) if module is not None else x


_DEVICE_COPIES: dict[tuple[int, str], object] = {}


def device_copy(xp: ModuleType, host: np.ndarray):
    """``host`` on the device of ``xp``, uploaded once per host array (cached while it lives).

    For constant tables (BVH records, scene arrays, camera tables). NumPy returns ``host`` itself.
    """
    if xp is np:
        return host
    key = (id(host), xp.__name__)
    copy = _DEVICE_COPIES.get(key)
    if copy is None:
        copy = xp.asarray(host)
        _DEVICE_COPIES[key] = copy
        weakref.finalize(host, _DEVICE_COPIES.pop, key, None)
    return copy


def free_device_bytes(xp: ModuleType) -> int | None:
    """Free device memory in bytes (driver's free + CuPy's pool of cached blocks); None on the CPU."""
    if xp is np or not hasattr(xp, "cuda"):
        return None
    free, _total = xp.cuda.runtime.memGetInfo()
    pool = xp.get_default_memory_pool()
    return int(free + pool.free_bytes())


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


@contextlib.contextmanager
def gpu_errors():
    """Turn CuPy/CUDA exceptions (out of memory, CUDA runtime or driver errors, NVRTC compile errors)
    into one-line :class:`GpuUnavailable` errors naming the cause."""
    try:
        yield
    except TofError:
        raise
    except Exception as exc:
        module = type(exc).__module__ or ""
        if not (module.startswith("cupy") or module.startswith("cupy_backends")):
            raise
        if "OutOfMemory" in type(exc).__name__:
            raise GpuUnavailable(f"GPU: out of device memory ({_first_line(exc)}); lower chunk_size or "
                                 f"free the GPU, or use device='cpu'") from None
        raise GpuUnavailable(f"GPU: CUDA error ({type(exc).__name__}: {_first_line(exc)})") from None


def scatter_sum(index, weights, length: int):
    """``np.bincount(index, weights, minlength=length)`` with ``0 <= index < length``, on any backend.

    CuPy's ``bincount`` reads ``index.max()`` back to the host to size its output, a synchronisation
    per call; here the length is known, so the device adds with atomics (``cupyx.scatter_add``) and the
    host never waits. NumPy (and test doubles) sum in index order, as ``bincount`` does.
    """
    xp = namespace(index, weights)
    if xp is np:
        return np.bincount(index, weights, minlength=length)
    out = xp.zeros(length, np.float64)
    if xp.__name__ == "cupy":
        import cupyx

        cupyx.scatter_add(out, index, weights)
    else:
        np.add.at(out, index, weights)
    return out


# ------------------------------------------------------------------ device twins
KERNELS: dict[str, str] = {
    "tofcore.rng.uniform": "tofcore.fused:uniform",
    "tofcore.tracer.qmc.scrambled_2d": "tofcore.fused:scrambled_2d",
    "tofcore.tracer.qmc.scrambled_1d": "tofcore.fused:scrambled_1d",
    "tofcore.scene.fresnel.fresnel_dielectric": "tofcore.fused:fresnel_dielectric",
    "tofcore.scene.fresnel.fresnel_conductor": "tofcore.fused:fresnel_conductor",
    "tofcore.sensor.modulation.square_correlation": "tofcore.fused:square_correlation",
    "tofcore.sensor.noise.poisson": "tofcore.fused:poisson",
    "tofcore.scene.bvh.BVH.intersect": "tofcore.gpu.traversal:intersect",
    "tofcore.scene.bvh.BVH.occluded": "tofcore.gpu.traversal:occluded",
}
"""Reference function (``module.qualname``) → its device twin (``module:function``)."""


def reference_name(function: Callable) -> str:
    """The key of ``function`` in :data:`KERNELS`: its module and qualified name."""
    return f"{function.__module__}.{function.__qualname__}"


def twin(name: str) -> Callable:
    """The device kernel registered for reference ``name`` (its module is imported on first use)."""
    module, function = KERNELS[name].split(":")
    return getattr(importlib.import_module(module), function)


def device_twin(on: str) -> Callable[[Callable], Callable]:
    """Mark a reference function that has a kernel in :data:`KERNELS`: device arrays in argument ``on`` run it.

    The twin gets the same arguments; host arrays run the reference itself.
    """

    def mark(reference: Callable) -> Callable:
        name = reference_name(reference)
        if name not in KERNELS:
            raise KeyError(f"device_twin: {name} has no entry in tofcore.backend.KERNELS")
        position = list(inspect.signature(reference).parameters).index(on)

        @functools.wraps(reference)
        def dispatch(*args, **kwargs):
            value = args[position] if position < len(args) else kwargs.get(on)
            if is_device_array(value):
                return twin(name)(*args, **kwargs)
            return reference(*args, **kwargs)

        dispatch.device_twin = name  # type: ignore[attr-defined]
        return dispatch

    return mark
