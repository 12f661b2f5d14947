"""Random error: noise on the raw images (shot + read), Li's distance noise (eq. 2.43), Keller's model (eq. 3.1).

Two ways to make a noisy depth image (SPEC §4, thesis §4.0.3, §5.2.2):

* ``"raw"`` — :func:`add_raw_noise` on every raw image before decoding: photon
  shot noise (Poisson in the charge) plus Gaussian read noise. Decoding turns
  it into distance noise that follows eq. 2.43 (derivation in
  :func:`li_sigma_m`), grows with distance (less light) and is higher on dark
  surfaces — the behaviour measured in §4.0.3 — and it also reaches mixed
  pixels and multi-frequency unwrapping correctly.
* ``"li"`` — :func:`li_sigma_m` from the decoded amplitude and offset, then
  :func:`add_distance_noise`: the thesis's own implementation (§5.2.2).

:func:`keller_amplitude_noise` is Keller's calibrated per-raw-image model
(eq. 3.1), for matching a real camera's measured noise instead of its physics.

=========================  ====  ==============================================================
parameter                  unit  meaning
=========================  ====  ==============================================================
``read_noise_e``           e⁻    standard deviation of the read noise per raw image and pixel
                                 (≥ 0)
``f_hz``                   Hz    modulation frequency f (> 0)
``modulation_contrast``    1     c_d ∈ (0, 1]: the demodulated fraction of the camera's light
``alpha_e``                e⁻    Keller's α ≥ 0: intensity-independent noise
``beta``                   1     Keller's β ≥ 0: noise proportional to the raw value
=========================  ====  ==============================================================

All randomness comes from a :class:`NoiseStream`: counter-based, every number
the hash of (key, element index, draw) (:mod:`tofcore.rng`), so one seed
gives the same noise on the CPU and on the GPU, and the same stream state gives
the same noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..backend import asarray, device_twin, namespace
from ..constants import SPEED_OF_LIGHT_M_S
from ..errors import ConfigError
from .. import rng as counter_rng

_DIMS_PER_DRAW = 64
"""Hash dimensions each draw of a stream owns (a Poisson draw uses 1 + 2 × 24 rounds + 2 = 51)."""


@dataclass
class NoiseStream:
    """Counter-based random numbers for sensor noise, the same on every device.

    Every draw (:meth:`uniforms`) takes the next block of hash dimensions; within it, the number of
    element i of an array is :func:`tofcore.rng.uniform` of (key, i, 0, dimension). So a
    value depends on the key, the order of the draws and the element's flat index only: not on the
    device, the chunking, or which other elements are drawn.
    """

    key: np.uint64
    draws: int = 0

    @classmethod
    def from_seed(cls, seed: int) -> NoiseStream:
        """The sensor-noise stream of a render with ``seed``, apart from the tracer's (its own key)."""
        if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
            raise ConfigError(f"NoiseStream: seed must be an integer >= 0, got {seed!r}")
        return cls(np.uint64(np.random.SeedSequence([int(seed), 0x70F]).generate_state(1, np.uint64)[0]))

    def next_draw(self) -> int:
        """The first hash dimension of the next draw (each draw owns :data:`_DIMS_PER_DRAW` of them)."""
        self.draws += 1
        return (self.draws - 1) * _DIMS_PER_DRAW


def _check_stream(where: str, rng) -> None:
    if not isinstance(rng, NoiseStream):
        raise ConfigError(f"{where}: rng must be a tofcore.sensor.noise.NoiseStream, got {rng!r}")


def _check_non_negative(where: str, name: str, value) -> None:
    if not (isinstance(value, (int, float, np.number)) and 0.0 <= value < math.inf):
        raise ConfigError(f"{where}: {name} must be a finite number >= 0, got {value!r}")


#: Elements per block of the NumPy noise code: its chains of uint64 and float64 operations run block by
#: block on arrays that stay in the CPU's cache, about twice as fast as over a whole frame (docs/benchmarks.md,
#: "Sensor noise on the CPU"). A value depends on its element's flat index only, never on the block.
BLOCK = 1 << 16


def _blocks(size: int):
    """Slices of at most :data:`BLOCK` elements that cover ``range(size)`` in order."""
    return (slice(start, min(start + BLOCK, size)) for start in range(0, size, BLOCK))


def _uniform_open(key: np.uint64, index, zeros, dim: int):
    """Uniforms in (0, 1): the hash's 53-bit [0, 1) value + 2⁻⁵⁴ (no 0 for logarithms, no 1)."""
    u = counter_rng.uniform(key, index, zeros, dim)
    u += 2.0 ** -54
    return u


def _normal(key: np.uint64, index, zeros, dim: int):
    """Standard normals by Box–Muller, :math:`z = \\sqrt{-2 \\ln u_1} \\cos 2\\pi u_2` (exact in
    distribution), from dimensions ``dim`` and ``dim + 1``."""
    u1, u2 = _uniform_open(key, index, zeros, dim), _uniform_open(key, index, zeros, dim + 1)
    return np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * np.pi * u2)


def standard_normal(shape, stream: NoiseStream, xp=np):
    """(shape) standard normals of the next draw of ``stream``, on the array module ``xp``.

    On a device one fused kernel per uniform (:func:`tofcore.fused.uniform`) over all elements; on the
    host block by block (:data:`BLOCK`), the same numbers.
    """
    shape = tuple(shape)
    dim = stream.next_draw()
    size = int(np.prod(shape, dtype=np.int64))
    if xp is not np:
        index = xp.arange(size, dtype=np.int64).reshape(shape)
        return _normal(stream.key, index, xp.zeros(shape, np.int64), dim)
    out = np.empty(size)
    for block in _blocks(size):
        out[block] = _normal(stream.key, np.arange(block.start, block.stop, dtype=np.int64), np.int64(0), dim)
    return out.reshape(shape)


#: Below this mean, Poisson counts by inversion of the cumulative pmf; from it, PTRS.
PTRS_MIN_MEAN = 10.0
#: Terms of the inversion: P(X ≥ 45) < 4.9e-16 for every mean below :data:`PTRS_MIN_MEAN` (X is capped there).
INVERSION_TERMS = 45
#: Rejection rounds of PTRS; each accepts with probability 1/α ≥ 0.75 for means ≥ 10 (0.75 at 10, rising to
#: 0.89; Hörmann 1993, measured in tests/tofcore/test_noise.py), so a count is still open after them with
#: probability < 0.25²⁴ ≈ 3.6e-15.
PTRS_ROUNDS = 24
#: From this mean on, N(λ, λ) rounded (its total-variation distance to the Poisson is ~ λ^-1/2 < 1e-5);
#: PTRS's log-pmf loses precision to cancellation far above any full well.
GAUSSIAN_MIN_MEAN = 1e10

HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)
#: ln k! for k = 0..15; Stirling's series from 16 on (:func:`_log_factorial`).
_LOG_FACTORIAL = np.array([math.lgamma(k + 1.0) for k in range(16)])


def _log_factorial(k: np.ndarray) -> np.ndarray:
    """ln k! of integer-valued floats k ≥ 0: a table below 16, Stirling's series for ln Γ(k + 1) from
    there (4 terms: truncation error < 1/(1188 x⁹) < 1e-13 at x = k + 1 ≥ 17)."""
    x = np.maximum(k, 15.0) + 1.0
    inv = 1.0 / x
    inv2 = inv * inv
    series = (x - 0.5) * np.log(x) - x + HALF_LOG_2PI \
        + inv * (1.0 / 12.0 - inv2 * (1.0 / 360.0 - inv2 * (1.0 / 1260.0 - inv2 / 1680.0)))
    return np.where(k < 16.0, _LOG_FACTORIAL[np.minimum(k, 15.0).astype(np.int64)], series)


@device_twin(on="mean")
def poisson(mean, key: np.uint64, dim: int, *, check: bool = True):
    """Poisson counts (float64) of means ``mean`` ≥ 0, one per element, from hash dimensions ``dim`` … ``dim``
    + 50 of ``key`` (a draw of a :class:`NoiseStream`: ``poisson(q, stream.key, stream.next_draw())``).

    Notes
    -----
    Exact in distribution up to the stated tails, the same numbers on every backend:

    * mean < :data:`PTRS_MIN_MEAN`: inversion, :math:`X = \\#\\{k < 45 : F(k) < u\\}` with
      :math:`F(k) = \\sum_{j \\le k} e^{-\\lambda} \\lambda^j / j!` (X capped at 45: P < 4.9e-16);
    * otherwise PTRS, Hörmann's transformed rejection with squeeze (W. Hörmann, "The transformed
      rejection method for generating Poisson random variables", Insurance: Mathematics and Economics
      12, 1993; the method of NumPy's own sampler for these means), in up to :data:`PTRS_ROUNDS`
      rounds of two uniforms each; a count still open after them (P < 3.6e-15) and means from
      :data:`GAUSSIAN_MIN_MEAN` on take :math:`\\lfloor \\lambda + \\sqrt\\lambda\\, z + \\tfrac12 \\rfloor`.

    The numbers of element i are uniforms of (key, i, dimension): the draw's first dimension for the
    inversion, the next two per PTRS round, the two after the last round for the Gaussian. So NumPy
    draws, block by block (:data:`BLOCK`), round by round only the elements still open, and the device twin
    (:func:`tofcore.fused.poisson`) runs the same loop per element in one kernel: both give the
    same counts.
    """
    lam = asarray(mean, dtype=np.float64)
    if check and not bool(np.all(lam >= 0.0) & np.all(np.isfinite(lam))):
        raise ConfigError("poisson: mean must be finite and >= 0")
    counts = np.empty(lam.size)
    flat = lam.ravel()
    for block in _blocks(lam.size):
        counts[block] = _poisson_block(flat[block], key, dim, block.start)
    return counts.reshape(lam.shape)


def _poisson_block(lam, key: np.uint64, dim: int, first: int):
    """:func:`poisson` of the flat means ``lam`` of elements ``first``, ``first + 1``, … (NumPy)."""
    index = np.arange(first, first + lam.size, dtype=np.int64)
    zero = np.int64(0)
    counts = np.zeros(lam.shape)
    small = np.flatnonzero(lam < PTRS_MIN_MEAN)
    counts[small] = _inversion(lam[small], _uniform_open(key, index[small], zero, dim))
    open_ = np.flatnonzero((lam >= PTRS_MIN_MEAN) & (lam < GAUSSIAN_MIN_MEAN))
    hat = _ptrs_hat(lam[open_])
    for r in range(PTRS_ROUNDS):
        if not open_.size:
            break
        u = _uniform_open(key, index[open_], zero, dim + 1 + 2 * r)
        v = _uniform_open(key, index[open_], zero, dim + 2 + 2 * r)
        k, accepted = _ptrs(lam[open_], *hat, u, v)
        counts[open_[accepted]] = k[accepted]
        open_ = open_[~accepted]
        hat = tuple(h[~accepted] for h in hat)
    rest = np.union1d(open_, np.flatnonzero(lam >= GAUSSIAN_MIN_MEAN))
    z = _normal(key, index[rest], zero, dim + 1 + 2 * PTRS_ROUNDS)
    counts[rest] = np.maximum(np.floor(lam[rest] + np.sqrt(lam[rest]) * z + 0.5), 0.0)
    return counts


def _inversion(lam, u):
    """Poisson(λ) by inversion of the cumulative pmf, λ < :data:`PTRS_MIN_MEAN`: #{k < 45 : F(k) < u}."""
    p = np.exp(-lam)
    cdf = p
    count = np.zeros_like(lam)
    for k in range(1, INVERSION_TERMS + 1):
        count = count + (u > cdf)
        p = p * lam / k
        cdf = cdf + p
    return count


def _ptrs_hat(lam):
    """The per-mean constants of PTRS's hat function that every round needs (Hörmann 1993, Table 1): b, a, v_r.

    ln(1/α) and ln λ are needed only where the squeeze does not decide: :func:`_ptrs` takes them there.
    """
    b = 0.931 + 2.53 * np.sqrt(lam)
    return b, -0.059 + 0.02483 * b, 0.9277 - 3.6224 / (b - 2.0)


def _ptrs(lam, b, a, v_r, u, v):
    """One round of PTRS (λ ≥ 10): (candidate count k, accepted), from uniforms u, v in (0, 1).

    .. math:: u_s = \\tfrac12 - |u - \\tfrac12|, \\quad k = \\lfloor (2a/u_s + b)(u - \\tfrac12) + \\lambda
              + 0.43 \\rfloor; \\quad \\text{accept if } u_s \\ge 0.07,\\ v \\le v_r \\text{ (squeeze), else if }
              \\ln v - \\ln\\alpha - \\ln(a/u_s^2 + b) \\le -\\lambda + k \\ln\\lambda - \\ln k!

    with :math:`\\ln(1/\\alpha) = \\ln(1.1239 + 1.1328 / (b - 3.4))` (and k ≥ 0, not (u_s < 0.013 and v > u_s)).
    The log test, with its logarithms, runs only where the squeeze does not decide.
    """
    u = u - 0.5
    us = 0.5 - np.abs(u)
    k = np.maximum(np.floor((2.0 * a / us + b) * u + lam + 0.43), -1.0)
    squeeze = (us >= 0.07) & (v <= v_r)
    test = np.flatnonzero(~squeeze & (k >= 0.0) & ~((us < 0.013) & (v > us)))  # the squeeze does not decide
    ks, lam_t, b_t = k[test], lam[test], b[test]
    log_inv_alpha = np.log(1.1239 + 1.1328 / (b_t - 3.4))
    hat = np.log(v[test]) + log_inv_alpha - np.log(a[test] / (us[test] * us[test]) + b_t)
    accepted = squeeze.copy()
    accepted[test] = hat <= -lam_t + ks * np.log(lam_t) - _log_factorial(ks)
    return np.maximum(k, 0.0), accepted


def add_raw_noise(raw: np.ndarray, *, read_noise_e: float, rng: NoiseStream, check: bool = True) -> np.ndarray:
    """Shot noise and read noise on raw images (any shape, any backend), in electrons; float64 out.

    Parameters
    ----------
    raw : noise-free charge q, e⁻, e.g. (R, H, W) after lens scattering.
    read_noise_e : σ_read, e⁻.
    rng : the :class:`NoiseStream`; two draws: the Poisson counts (:func:`poisson`), then the read noise.
    check : validate the parameters and that ``raw`` is finite (a read-back on a GPU); a render checks
        its sensor once and passes False.

    Returns
    -------
    :math:`\\max(0,\\; \\mathrm{Poisson}(\\max(q, 0)) + \\sigma_{read}\\, n)`, n ~ N(0, 1) per
    image and pixel.

    Notes
    -----
    Poisson counts exact in distribution at every charge a sensor holds (:func:`poisson`; no switch to
    N(q, q) below 1e10 e⁻). Negative charge, which negative PSF lobes can leave in a dark pixel next
    to a bright one, has no photons: its shot noise is that of zero. The clip at 0 (a pixel cannot
    hold negative charge) biases the mean only where q ≲ 3 σ_read. Saturation (full well) is the
    sensor's business, after this.
    """
    where = "add_raw_noise"
    charge = asarray(raw, dtype=np.float64)
    if check:
        _check_non_negative(where, "read_noise_e", read_noise_e)
        _check_stream(where, rng)
        if not np.isfinite(charge).all():
            raise ConfigError(f"{where}: raw must be finite, got {int(np.count_nonzero(~np.isfinite(charge)))} "
                              f"non-finite values")
    shot = poisson(np.maximum(charge, 0.0), rng.key, rng.next_draw(), check=False)
    read = standard_normal(charge.shape, rng, namespace(charge))
    return np.maximum(shot + read_noise_e * read, 0.0)


def li_sigma_m(amplitude, offset, f_hz: float, modulation_contrast: float) -> np.ndarray:
    """Standard deviation of the distance, m, by Li's model (thesis eq. 2.43).

    .. math:: \\sigma = \\frac{c}{4\\sqrt2\\,\\pi f} \\cdot \\frac{\\sqrt{A + B}}{c_d A}

    Parameters
    ----------
    amplitude : A, e⁻ per bucket (array): the camera's own light, see Notes.
    offset : B, e⁻ per bucket (array, broadcast with ``amplitude``): everything else
        (ambient light, dark current), see Notes.
    f_hz : modulation frequency f, Hz.
    modulation_contrast : c_d ∈ (0, 1].

    Returns
    -------
    σ, m, float64 of the broadcast shape: +inf where A ≤ 0 (no signal, no
    distance information — :func:`add_distance_noise` turns it into NaN), NaN
    only where an input is NaN. A + B < 0 (negative charge from negative PSF
    lobes) counts as 0 under the root.

    Notes
    -----
    Where eq. 2.43 comes from, and so what A and B mean: four buckets θ_k = 0,
    π, π/2, 3π/2 collect :math:`Q_k = A + B + c_d A \\cos(\\varphi - \\theta_k)`
    electrons, A the mean charge of the camera's light per bucket and B the
    rest. The phase :math:`\\varphi = \\operatorname{atan2}(y, x)` with
    :math:`x = Q_1 - Q_2 = 2 c_d A \\cos\\varphi`, :math:`y = Q_3 - Q_4 = 2 c_d A \\sin\\varphi`
    changes to first order by :math:`\\delta\\varphi = (x\\,\\delta y - y\\,\\delta x)/(x^2 + y^2)`.
    With independent Poisson charges, Var δx = Q1 + Q2 = 2(A + B) = Var δy, so

    .. math:: \\operatorname{Var}\\delta\\varphi = \\frac{(x^2 + y^2)\\, 2(A + B)}{(x^2 + y^2)^2}
              = \\frac{A + B}{2 c_d^2 A^2},\\qquad
              \\sigma_d = \\frac{c}{4\\pi f}\\,\\sigma_\\varphi = \\text{eq. 2.43.}

    So eq. 2.43 is the shot-noise limit of 4-bucket decoding when A is the
    signal's *mean* charge per bucket (its demodulated amplitude, eq. 2.40, is
    c_d A) and B the charge per bucket **not** due to the camera's light. The
    offset of eq. 2.41 is A + B; the thesis (§5.2.2) put that offset in for B,
    which overestimates σ by :math:`\\sqrt{(2A + B)/(A + B)}` (up to √2 without
    ambient light). To follow the shot-noise limit from decoded images pass
    ``amplitude / c_d`` and ``offset − amplitude / c_d``. Read noise σ_read
    adds σ_read² to every bucket's variance: B → B + σ_read².
    """
    where = "li_sigma_m"
    if not (isinstance(f_hz, (int, float, np.number)) and 0.0 < f_hz < math.inf):
        raise ConfigError(f"{where}: f_hz must be a finite number > 0, got {f_hz!r}")
    if not (isinstance(modulation_contrast, (int, float, np.number)) and 0.0 < modulation_contrast <= 1.0):
        raise ConfigError(f"{where}: modulation_contrast must be a number in (0, 1], got {modulation_contrast!r}")
    a, b = np.broadcast_arrays(asarray(amplitude, dtype=np.float64), asarray(offset, dtype=np.float64))
    scale_m = SPEED_OF_LIGHT_M_S / (4.0 * math.sqrt(2.0) * math.pi * f_hz)
    safe_a = np.where(a > 0.0, a, 1.0)
    sigma = np.where(a > 0.0, scale_m * np.sqrt(np.maximum(a + b, 0.0)) / (modulation_contrast * safe_a), np.inf)
    return np.where(np.isnan(a) | np.isnan(b), np.nan, sigma)


def add_distance_noise(distance, sigma, rng: NoiseStream, *, check: bool = True) -> np.ndarray:
    """Gaussian distance noise: d + σ n, n ~ N(0, 1) per pixel; NaN where σ is +inf or NaN.

    Parameters
    ----------
    distance : d, m (array, any backend; NaN stays NaN).
    sigma : σ ≥ 0, m, broadcast with ``distance`` (e.g. from :func:`li_sigma_m`).
    rng : the :class:`NoiseStream`; one draw, a standard normal per element of the broadcast shape.
    check : validate ``rng`` and σ ≥ 0 (a read-back on a GPU).

    Returns
    -------
    float64 array of the broadcast shape.
    """
    where = "add_distance_noise"
    d = asarray(distance, dtype=np.float64)
    s = asarray(sigma, dtype=np.float64)
    if check:
        _check_stream(where, rng)
        if bool(np.any(s < 0.0)):
            raise ConfigError(f"{where}: sigma must be >= 0 (m), got minimum {float(np.nanmin(s))!r}")
    shape = np.broadcast_shapes(d.shape, s.shape)
    known = np.isfinite(s)
    noise = np.where(known, s, 0.0) * standard_normal(shape, rng, namespace(d, s))
    return np.where(known, d + noise, np.nan)


def keller_amplitude_noise(raw: np.ndarray, *, alpha_e: float, beta: float, rng: NoiseStream,
                           check: bool = True) -> np.ndarray:
    """Keller's intensity-dependent noise on every raw image (thesis eq. 3.1), e⁻; float64 out.

    .. math:: A_{noisy,i} = A_i + \\alpha\\, n + A_i\\, \\beta\\, n, \\qquad n \\sim N(0, 1)

    per raw image i and pixel, one n for both terms (one draw of the :class:`NoiseStream` ``rng``), so
    the standard deviation is :math:`\\alpha + \\beta A_i`; the result is clipped at 0 like
    :func:`add_raw_noise`. The thesis writes :math:`n \\in [-1, 1]` yet calls n normally distributed;
    a standard normal is used. α and β are calibrated against a real camera, not derived from physics.
    ``check``: validate the parameters (False: the caller did, once).
    """
    where = "keller_amplitude_noise"
    if check:
        _check_non_negative(where, "alpha_e", alpha_e)
        _check_non_negative(where, "beta", beta)
        _check_stream(where, rng)
    value = asarray(raw, dtype=np.float64)
    n = standard_normal(value.shape, rng, namespace(value))
    return np.maximum(value + alpha_e * n + value * beta * n, 0.0)
