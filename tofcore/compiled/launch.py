"""Kernel launches whose arguments are marshalled once: a launch is then one driver call.

numba-cuda types and marshals every argument of every launch (``typeof`` over the nested tuples, then
one value per array field and shape entry): ≈ 270 µs a launch of a wavefront stage kernel on the H200
host, more than most stages' own device time (docs/benchmarks.md, issue 21). The wavefront's buffers stay
the same from group to group and from pass to pass, so :class:`PreparedKernel` types and marshals a
kernel's arguments once, into one parameter block, and keeps each argument that changes per launch (a
depth, a group's bounds: a :class:`Slot`) in a ctypes cell of that block, set before the launch. A launch
is then ``cuLaunchKernel`` (CuPy's binding) on the legacy default stream, the stream numba and CuPy use
here, so launches stay in order with CuPy's work.

Under numba's CUDA simulator (tests) :meth:`PreparedKernel.launch` calls the kernel as numba does.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass

import numpy as np

DEFAULT_STREAM = 0
"""The legacy default stream (numba's stream 0, CuPy's null stream)."""


@dataclass(frozen=True)
class Slot:
    """A scalar kernel argument given later: ``PreparedKernel(k, (a, Slot("depth")))`` then
    ``.launch(n, depth=2)`` or ``.set(depth=2)``; int64 unless ``dtype`` says otherwise."""

    name: str
    dtype: type = np.int64


class PreparedKernel:
    """A numba.cuda kernel with fixed arguments, typed and marshalled once (see the module docstring)."""

    def __init__(self, dispatcher, args: tuple, threads_per_block: int):
        from numba import config

        self.dispatcher = dispatcher
        self.args = args
        self.threads_per_block = threads_per_block
        self.simulated = bool(config.ENABLE_CUDASIM)
        self.slots: dict = {}  # a Slot's name → its value (typed as the Slot says)
        self.slot_cells: dict = {}  # a Slot's name → its cells in the parameter block
        typed = fill_slots(args, self.slots)
        if self.simulated:
            return
        kernel = dispatcher.compile(tuple(dispatcher.typeof_pyval(a) for a in typed))
        self.handle = int(kernel._codelibrary.get_cufunc().handle)
        self.cells: list = []      # one ctypes value per kernel parameter, kept alive with the block
        for ty, a in zip(kernel.argument_types, args):
            self._marshal(kernel, ty, a)
        self.block = (ctypes.c_void_p * len(self.cells))(*(ctypes.addressof(c) for c in self.cells))

    def _marshal(self, kernel, ty, arg) -> None:
        """Append ``arg``'s parameters (numba's own marshalling, tuples element by element) to the block."""
        if isinstance(arg, tuple):
            for t, a in zip(ty, arg):
                self._marshal(kernel, t, a)
            return
        raw: list = []
        kernel._prepare_args(ty, arg.dtype(0) if isinstance(arg, Slot) else arg, DEFAULT_STREAM, [], raw)
        cells = [_cell(v) for v in raw]
        if isinstance(arg, Slot):
            self.slot_cells.setdefault(arg.name, []).append(cells[0])
        self.cells.extend(cells)

    def set(self, **slots) -> None:
        """Give the :class:`Slot` arguments ``slots`` (name=value) their values for the next launches."""
        for name, value in slots.items():
            if name not in self.slots:
                raise KeyError(f"{self.dispatcher.py_func.__name__} has no argument slot {name!r}")
            self.slots[name] = type(self.slots[name])(value)
            for cell in self.slot_cells.get(name, ()):
                cell.value = int(value)

    def launch(self, n_threads: int, **slots) -> None:
        """Launch over ``n_threads`` threads, with the :class:`Slot` arguments ``slots`` set first (:meth:`set`)."""
        self.set(**slots)
        if n_threads <= 0:
            return
        blocks = (n_threads + self.threads_per_block - 1) // self.threads_per_block
        if self.simulated:
            self.dispatcher[blocks, self.threads_per_block](*fill_slots(self.args, self.slots))
            return
        from cupy.cuda import driver

        driver.launchKernel(self.handle, blocks, 1, 1, self.threads_per_block, 1, 1, 0, DEFAULT_STREAM,
                            ctypes.addressof(self.block), 0)


def fill_slots(args: tuple, slots: dict) -> tuple:
    """``args`` with each :class:`Slot` (in nested tuples too) replaced by its value in ``slots`` (0 where
    it has none yet, which it then gets)."""
    out = []
    for a in args:
        if isinstance(a, tuple):
            out.append(fill_slots(a, slots))
        elif isinstance(a, Slot):
            out.append(slots.setdefault(a.name, a.dtype(0)))
        else:
            out.append(a)
    return tuple(out)


def _cell(value):
    """The ctypes value of one marshalled parameter (numba's kernel ABI: array fields and pointers are
    pointer-sized integers, a boolean one byte)."""
    if isinstance(value, ctypes._SimpleCData):
        return value
    if isinstance(value, (bool, np.bool_)):
        return ctypes.c_uint8(int(value))
    if isinstance(value, (int, np.integer)):
        return ctypes.c_int64(int(value))
    raise TypeError(f"cannot marshal a kernel parameter of type {type(value).__name__}")
