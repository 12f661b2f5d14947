"""Fused elementwise kernels: hot chains of NumPy-style operations as one CUDA kernel each.

On the GPU every NumPy-style operation is a kernel launch and a pass over device memory; a chain
of them is launch- and bandwidth-bound. The chains here are the ones the GPU profile found hot,
each bit-identical to its NumPy twin (integer arithmetic; float operations in the same order).

* :func:`uniform` — :func:`tofcore.rng.uniform`: two SplitMix64 finalisers over a mix of
  (key, pixel, sample, dimension), 53 bits → [0, 1); 14 array operations in NumPy, one kernel here.
"""

from __future__ import annotations

import functools

from .. import backend
from .. import rng as _rng

_MASK64 = (1 << 64) - 1


@functools.lru_cache(maxsize=None)
def _uniform_kernel(cp):
    c = {k: f"{int(getattr(_rng, k)):#x}ULL" for k in ("_GOLDEN", "_MIX_PIXEL", "_MIX_SAMPLE", "_M1", "_M2")}
    return cp.ElementwiseKernel(
        "int64 pixel, int64 sample, uint64 key, uint64 dim_mix", "float64 u",
        f"""
        unsigned long long x = key ^ ((unsigned long long)pixel * {c['_MIX_PIXEL']})
                                   ^ ((unsigned long long)sample * {c['_MIX_SAMPLE']}) ^ dim_mix;
        for (int round = 0; round < 2; ++round) {{
            x += {c['_GOLDEN']};
            x = (x ^ (x >> 30)) * {c['_M1']};
            x = (x ^ (x >> 27)) * {c['_M2']};
            x = x ^ (x >> 31);
        }}
        u = (double)(x >> 11) * (1.0 / 9007199254740992.0);
        """,
        "tofcore_uniform")


def uniform(key, pixel, sample, dim: int):
    """:func:`tofcore.rng.uniform` for CuPy ``pixel`` and ``sample`` arrays, bit for bit."""
    cp = backend.namespace(pixel, sample)
    dim_mix = (int(dim) * int(_rng._MIX_DIM)) & _MASK64
    return _uniform_kernel(cp)(pixel.astype(cp.int64, copy=False), sample.astype(cp.int64, copy=False),
                               cp.uint64(int(key)), cp.uint64(dim_mix))
