"""The one dispatch point for device kernels: which reference function has a CUDA twin, and where it lives.

The NumPy functions are the reference: they define the frame bit for bit. A few of them have a kernel in
:mod:`tofcore.gpu` that computes the same values on CuPy arrays with the same signature. Such a reference
function is marked :func:`device_twin`; called with a device array in its argument ``on``, it runs its
twin instead. :data:`KERNELS` is the table of all of them, so the physics modules never import
:mod:`tofcore.gpu` (which sits above them: its kernels take their constants from the Python source) and the
CPU path never imports it or CuPy. ``tests/tofcore/test_kernels.py`` walks the table: every reference is
marked, every twin exists and, on a GPU, agrees with its reference; docs/architecture.md lists the table.
"""

from __future__ import annotations

import functools
import importlib
import inspect
from collections.abc import Callable

from .backend import is_device_array

KERNELS: dict[str, str] = {
    "tofcore.tracer.rng.uniform": "tofcore.gpu.fused:uniform",
    "tofcore.tracer.qmc.scrambled_2d": "tofcore.gpu.fused:scrambled_2d",
    "tofcore.tracer.qmc.scrambled_1d": "tofcore.gpu.fused:scrambled_1d",
    "tofcore.scene.fresnel.fresnel_dielectric": "tofcore.gpu.fused:fresnel_dielectric",
    "tofcore.scene.fresnel.fresnel_conductor": "tofcore.gpu.fused:fresnel_conductor",
    "tofcore.sensor.modulation.square_correlation": "tofcore.gpu.fused:square_correlation",
    "tofcore.scene.bvh.BVH.intersect": "tofcore.gpu.traversal:intersect",
    "tofcore.scene.bvh.BVH.occluded": "tofcore.gpu.traversal:occluded",
}
"""Reference function (``module.qualname``) → its device twin (``module:function``)."""


def reference_name(function: Callable) -> str:
    """The key of ``function`` in :data:`KERNELS`: its module and qualified name."""
    return f"{function.__module__}.{function.__qualname__}"


@functools.cache
def twin(name: str) -> Callable:
    """The device kernel registered for reference ``name`` (imports its module on first use)."""
    module, function = KERNELS[name].split(":")
    return getattr(importlib.import_module(module), function)


def device_twin(on: str) -> Callable[[Callable], Callable]:
    """Mark a reference function that has a kernel in :data:`KERNELS`: device arrays in argument ``on`` run it.

    The twin gets the same arguments; host arrays run the reference itself.
    """

    def mark(reference: Callable) -> Callable:
        name = reference_name(reference)
        if name not in KERNELS:
            raise KeyError(f"device_twin: {name} has no entry in tofcore.kernels.KERNELS")
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
