"""Counter-based random numbers: one uniform per (seed, pixel, sample, dimension).

A path's random numbers must not depend on which chunk, pass or worker traces
it, or the same seed would give different frames for different chunk sizes.
So instead of drawing from a stateful stream, every uniform is a hash of its
coordinates — the approach of counter-based generators (Salmon et al. 2011,
"Parallel random numbers: as easy as 1, 2, 3"; Philox is what
``numpy.random.Philox`` implements). The hash here is SplitMix64's finaliser
(Steele et al. 2014) applied twice to a linear mix of the coordinates; the
64-bit key comes from ``numpy.random.SeedSequence(seed)`` so that nearby seeds
give unrelated streams.

Dimensions are allocated by the sampler (:mod:`tofcore.tracer.sampler`, one table); they never
collide because each consumer owns a fixed range.
"""

from __future__ import annotations

import numpy as np

from .backend import device_twin

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX_PIXEL = np.uint64(0xD1B54A32D192ED03)
_MIX_SAMPLE = np.uint64(0xAEF17502108EF2D9)
_MIX_DIM = np.uint64(0xDB4F0B9175AE2165)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11)


def seed_key(seed: int) -> np.uint64:
    """The 64-bit key of a user seed (any non-negative int)."""
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return np.uint64(np.random.SeedSequence(int(seed)).generate_state(1, np.uint64)[0])


def _splitmix(x: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser, in place on ``x`` (an array of the caller's own): z ← z + φ,
    z ← (z ⊕ z ≫ 30)·M1, z ← (z ⊕ z ≫ 27)·M2, z ⊕ z ≫ 31 (mod 2⁶⁴); in place it allocates one temporary
    per shift instead of one per operation."""
    x += _GOLDEN
    x ^= x >> _S30
    x *= _M1
    x ^= x >> _S27
    x *= _M2
    x ^= x >> _S31
    return x


def bits(key: np.uint64, pixel, sample, dim: int):
    """64 random bits (uint64), one per (pixel, sample) pair, for dimension ``dim``: the hash of the coordinates.

    Array code only (NumPy or CuPy); :func:`uniform` and :mod:`tofcore.tracer.qmc` take their numbers from it.
    """
    with np.errstate(over="ignore"):
        x = pixel.astype(np.uint64) * _MIX_PIXEL  # a new array: the hash runs in place on it
        x ^= sample.astype(np.uint64) * _MIX_SAMPLE
        x ^= key ^ (np.uint64(dim) * _MIX_DIM)
        return _splitmix(_splitmix(x))


@device_twin(on="pixel")
def uniform(key: np.uint64, pixel: np.ndarray, sample: np.ndarray, dim: int) -> np.ndarray:
    """Uniform floats in [0, 1), one per (pixel, sample) pair, for dimension ``dim``.

    Parameters
    ----------
    key : the stream key from :func:`seed_key`.
    pixel, sample : integer arrays of equal shape (flat pixel index, sample index); on the host ``sample``
        may be a NumPy integer scalar, broadcast over ``pixel``.
    dim : the random dimension (which decision of the path this number drives).

    Returns
    -------
    float64 array of the shape of ``pixel``, 53 random bits each; on the GPU (CuPy arrays) one fused
    kernel (:func:`tofcore.fused.uniform`) computes the same bits.
    """
    x = bits(key, pixel, sample, dim)
    x >>= _S11
    u = x.astype(np.float64)
    u *= 1.0 / 9007199254740992.0
    return u
