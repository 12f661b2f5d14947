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

All randomness comes from the caller's ``numpy.random.Generator``: the same
generator state gives the same noise.
"""

from __future__ import annotations

import math

import numpy as np

from ..backend import asarray
from ..constants import SPEED_OF_LIGHT_M_S
from ..errors import ConfigError


def _check_rng(where: str, rng) -> None:
    if not isinstance(rng, np.random.Generator):
        raise ConfigError(f"{where}: rng must be a numpy.random.Generator, got {rng!r}")


def _check_non_negative(where: str, name: str, value) -> None:
    if not (isinstance(value, (int, float, np.number)) and 0.0 <= value < math.inf):
        raise ConfigError(f"{where}: {name} must be a finite number >= 0, got {value!r}")


def add_raw_noise(raw: np.ndarray, *, read_noise_e: float, rng: np.random.Generator) -> np.ndarray:
    """Shot noise and read noise on raw images (any shape), in electrons; float64 in, float64 out.

    Parameters
    ----------
    raw : noise-free charge q, e⁻, e.g. (R, H, W) after lens scattering.
    read_noise_e : σ_read, e⁻.
    rng : the generator; draws the Poisson counts of all pixels, then the read noise.

    Returns
    -------
    :math:`\\max(0,\\; \\mathrm{Poisson}(\\max(q, 0)) + \\sigma_{read}\\, n)`, n ~ N(0, 1) per
    image and pixel.

    Notes
    -----
    Exact Poisson counts at every charge NumPy's sampler takes (λ up to ~9.2e18
    e⁻, far beyond any full well; no switch to the Gaussian N(q, q) at high
    counts, so no threshold to tune); above that, N(q, q), drawn after the
    Poisson counts so that frames without such charges keep their noise.
    Negative charge, which negative PSF lobes can leave in a dark pixel next to
    a bright one, has no photons: its shot noise is that of zero. The clip at 0
    (a pixel cannot hold negative charge) biases the mean only where
    q ≲ 3 σ_read. Saturation (full well) is the sensor's business, after this.
    """
    where = "add_raw_noise"
    _check_non_negative(where, "read_noise_e", read_noise_e)
    _check_rng(where, rng)
    charge = asarray(raw, dtype=np.float64)
    if not np.isfinite(charge).all():
        raise ConfigError(f"{where}: raw must be finite, got {np.count_nonzero(~np.isfinite(charge))} "
                          f"non-finite values")
    mean = np.maximum(charge, 0.0)
    huge = mean > _POISSON_MAX_LAM
    if not huge.any():
        shot = rng.poisson(mean).astype(np.float64)
    else:  # far beyond any full well: NumPy's sampler refuses λ this large; N(q, q) is exact to ~1e-9 there
        shot = rng.poisson(np.where(huge, 0.0, mean)).astype(np.float64)
        shot[huge] = mean[huge] + np.sqrt(mean[huge]) * rng.standard_normal(int(np.count_nonzero(huge)))
    return np.maximum(shot + read_noise_e * rng.standard_normal(charge.shape), 0.0)


#: Largest λ ``numpy.random.Generator.poisson`` accepts (int64 max minus 10 σ); above it, a Gaussian draw.
_POISSON_MAX_LAM = float(np.iinfo(np.int64).max - 10 * np.sqrt(np.iinfo(np.int64).max))


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


def add_distance_noise(distance, sigma, rng: np.random.Generator) -> np.ndarray:
    """Gaussian distance noise: d + σ n, n ~ N(0, 1) per pixel; NaN where σ is +inf or NaN.

    Parameters
    ----------
    distance : d, m (array; NaN stays NaN).
    sigma : σ ≥ 0, m, broadcast with ``distance`` (e.g. from :func:`li_sigma_m`).
    rng : the generator; one standard normal per element of the broadcast shape.

    Returns
    -------
    float64 array of the broadcast shape.
    """
    where = "add_distance_noise"
    _check_rng(where, rng)
    d = asarray(distance, dtype=np.float64)
    s = asarray(sigma, dtype=np.float64)
    if np.any(s < 0.0):
        raise ConfigError(f"{where}: sigma must be >= 0 (m), got minimum {float(np.nanmin(s))!r}")
    shape = np.broadcast_shapes(d.shape, s.shape)
    known = np.isfinite(s)
    noise = np.where(known, s, 0.0) * rng.standard_normal(shape)
    return np.where(known, d + noise, np.nan)


def keller_amplitude_noise(raw: np.ndarray, *, alpha_e: float, beta: float,
                           rng: np.random.Generator) -> np.ndarray:
    """Keller's intensity-dependent noise on every raw image (thesis eq. 3.1), e⁻; float64 out.

    .. math:: A_{noisy,i} = A_i + \\alpha\\, n + A_i\\, \\beta\\, n, \\qquad n \\sim N(0, 1)

    per raw image i and pixel, one n for both terms, so the standard deviation
    is :math:`\\alpha + \\beta A_i`; the result is clipped at 0 like
    :func:`add_raw_noise`. The thesis writes :math:`n \\in [-1, 1]` yet calls n
    normally distributed; a standard normal is used. α and β are calibrated
    against a real camera, not derived from physics.
    """
    where = "keller_amplitude_noise"
    _check_non_negative(where, "alpha_e", alpha_e)
    _check_non_negative(where, "beta", beta)
    _check_rng(where, rng)
    value = asarray(raw, dtype=np.float64)
    n = rng.standard_normal(value.shape)
    return np.maximum(value + alpha_e * n + value * beta * n, 0.0)
