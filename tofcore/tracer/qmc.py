"""Randomized quasi-Monte Carlo samples: Owen-scrambled Sobol' points, per pixel, in independent replicates.

A path's decisions (pixel position, lens position, each bounce's lobe and direction, the light vertex)
draw their uniforms from low-discrepancy point sets instead of independent random numbers. Per pixel and
per pair of dimensions the points are the first two dimensions of the Sobol' sequence — a (0, 2)-sequence:
every prefix of 2^m points puts one point in each of the 2^m elementary boxes of any shape — randomized by

* a nested uniform (Owen) scramble of each coordinate (Owen 1995), which keeps the net property and
  makes every single point uniform on [0, 1)², so the estimator stays **unbiased**;
* an Owen scramble of the sample index (Burley 2020, "Practical hash-based Owen scrambling", JCGT 9(4)),
  which shuffles the sequence so that different pairs of dimensions of one path are decorrelated
  ("padding"): the pixel position and the first bounce direction are two independent (0, 2)-sequences.

Scrambles are hash-based (Laine & Karras 2011, with Burley's constants): a function of a 32-bit seed in
which each output bit depends only on the input bits above it — exactly the structure of an Owen scramble.
Seeds are hashes of (seed key, pixel, replicate, dimension) from :mod:`tofcore.rng`, so, as with the plain
counter-based uniforms, a sample depends only on its coordinates, never on chunk size, worker count or
device (the CUDA twins of :func:`scrambled_2d` and :func:`scrambled_1d` compute the same bits).

**Replicates.** Sample i of a pixel belongs to replicate r = i mod R and is point j = ⌊i / R⌋ of that
replicate's scrambled sequence; the R replicates are independent randomizations. Their per-pixel means are
therefore independent unbiased estimates, and their spread estimates the error of the pixel mean honestly
(samples within one replicate are negatively correlated, so the usual per-sample variance would
overestimate the error of a QMC mean; Owen 1997, L'Ecuyer & Lemieux 2002). With n samples per pixel the
error is that of R scrambled nets of n/R points.

Example
-------
>>> import numpy as np
>>> from tofcore import rng
>>> u, v = sample_2d(rng.seed_key(0), np.zeros(4, np.int64), np.arange(4), dim=0)
"""

from __future__ import annotations

import numpy as np

from ..backend import device_twin
from .. import rng

REPLICATES = 4
"""Independent randomizations per pixel (sample i belongs to replicate i mod R); the error estimate of
a pixel mean has R − 1 degrees of freedom."""

SEED_DIM_OFFSET = 0x5EED
"""The second hash of a dimension (the y scramble seed) is taken at dimension ``dim + SEED_DIM_OFFSET``."""

_U32 = np.uint32
_LK = (_U32(0x6C50B47C), _U32(0xB82F1E52), _U32(0xC7AFE638), _U32(0x8D22F6E6))
_TO_UNIT = 1.0 / 4294967296.0


def _sobol_dim1_tables() -> np.ndarray:
    """(4, 256) uint32: byte tables of Sobol' dimension 2 (primitive polynomial x + 1).

    Direction numbers m_1 = 1, m_k = m_{k−1} ⊕ 2 m_{k−1} (1, 3, 5, 15, 17, 51, …), v_b = m_{b+1} · 2^{31−b}:
    bit b of the index toggles v_b (the generator matrix is Pascal's triangle mod 2). Table k holds, for
    each value of index byte k, the XOR of the v_b of its bits, so a point costs four lookups.
    """
    m, v = 1, []
    for b in range(32):
        v.append((m << (31 - b)) & 0xFFFFFFFF)
        m ^= m << 1
    tables = np.zeros((4, 256), dtype=np.uint32)
    for k in range(4):
        for value in range(256):
            for i in range(8):
                if value >> i & 1:
                    tables[k, value] ^= v[8 * k + i]
    return tables


_SOBOL_DIM1_TABLES = _sobol_dim1_tables()


def reverse_bits(x):
    """Reverse the 32 bits of each uint32."""
    x = ((x >> _U32(1)) & _U32(0x55555555)) | ((x & _U32(0x55555555)) << _U32(1))
    x = ((x >> _U32(2)) & _U32(0x33333333)) | ((x & _U32(0x33333333)) << _U32(2))
    x = ((x >> _U32(4)) & _U32(0x0F0F0F0F)) | ((x & _U32(0x0F0F0F0F)) << _U32(4))
    x = ((x >> _U32(8)) & _U32(0x00FF00FF)) | ((x & _U32(0x00FF00FF)) << _U32(8))
    return (x >> _U32(16)) | (x << _U32(16))


def owen_scramble(x, seed):
    """Hash-based nested uniform scramble of uint32 values in base 2 (Burley 2020, listing 4).

    In bit-reversed order the Laine–Karras hash changes each bit as a function of the bits below it only;
    reversed back, bit b of the result depends on the bits above it: a random flip of every node of the
    binary tree of intervals, which is Owen's scramble (up to the quality of the hash).
    """
    with np.errstate(over="ignore"):
        x = reverse_bits(x)
        x = x + seed
        for c in _LK:
            x = x ^ (x * c)
    return reverse_bits(x)


def sobol_2d(index):
    """The first two Sobol' dimensions of uint32 indices, as uint32 fixed point (value · 2³²)."""
    t = _SOBOL_DIM1_TABLES
    y = t[0][index & _U32(0xFF)] ^ t[1][(index >> _U32(8)) & _U32(0xFF)] \
        ^ t[2][(index >> _U32(16)) & _U32(0xFF)] ^ t[3][index >> _U32(24)]
    return reverse_bits(index), y


def _seeds(key, pixel, sample, dim: int):
    """(index, x, y scramble seeds as uint32, point index j) of samples i: replicate i mod R, point ⌊i/R⌋."""
    replicate = sample % REPLICATES
    bits = rng.bits(key, pixel, replicate, dim)
    more = rng.bits(key, pixel, replicate, dim + SEED_DIM_OFFSET)
    low = np.uint64(0xFFFFFFFF)
    s_index = (bits & low).astype(np.uint32)
    s_x = (bits >> np.uint64(32)).astype(np.uint32)
    s_y = (more & low).astype(np.uint32)
    return s_index, s_x, s_y, (sample // REPLICATES).astype(np.uint32)


SAMPLERS = ("sobol", "independent")
"""``"sobol"``: the scrambled nets of this module; ``"independent"``: plain counter-based uniforms
(:func:`tofcore.rng.uniform`), kept for comparisons (the ablation in docs/benchmarks.md)."""


def sample_2d(key, pixel, sample, dim: int, sampler: str = "sobol"):
    """Uniforms (u, v) in [0, 1)², float64, for samples ``sample`` of pixels ``pixel`` in dimension pair ``dim``.

    Parameters
    ----------
    key : the stream key (:func:`tofcore.rng.seed_key`).
    pixel, sample : integer arrays of equal shape: flat pixel index, sample index of that pixel.
    dim : which decision of the path (each pair of coordinates owns one number).
    sampler : one of :data:`SAMPLERS`.

    Notes
    -----
    Point j of replicate r: :math:`(u, v) = 2^{-32}\\,(\\mathcal O_x(s_0(\\mathcal O_i(j))),
    \\mathcal O_y(s_1(\\mathcal O_i(j))))` with s_0, s_1 the Sobol' dimensions and
    :math:`\\mathcal O` Owen scrambles seeded per (pixel, r, dim).
    """
    if sampler == "independent":
        return rng.uniform(key, pixel, sample, 2 * dim), rng.uniform(key, pixel, sample, 2 * dim + 1)
    return scrambled_2d(key, pixel, sample, dim)


def sample_1d(key, pixel, sample, dim: int, sampler: str = "sobol"):
    """Uniforms in [0, 1), float64: a scrambled van der Corput sequence per (pixel, replicate, ``dim``)."""
    if sampler == "independent":
        return rng.uniform(key, pixel, sample, 2 * dim)
    return scrambled_1d(key, pixel, sample, dim)


@device_twin(on="pixel")
def scrambled_2d(key, pixel, sample, dim: int):
    """The ``"sobol"`` sampler's (u, v) of :func:`sample_2d`: Owen-scrambled Sobol' points."""
    s_index, s_x, s_y, j = _seeds(key, pixel, sample, dim)
    x, y = sobol_2d(owen_scramble(j, s_index))
    return owen_scramble(x, s_x) * _TO_UNIT, owen_scramble(y, s_y) * _TO_UNIT


@device_twin(on="pixel")
def scrambled_1d(key, pixel, sample, dim: int):
    """The ``"sobol"`` sampler's u of :func:`sample_1d`: a scrambled van der Corput sequence."""
    s_index, s_x, _, j = _seeds(key, pixel, sample, dim)
    return owen_scramble(reverse_bits(owen_scramble(j, s_index)), s_x) * _TO_UNIT
