r"""The estimator in one place: replicates and their error, the MIS weights, adaptive sample allocation.

**Replicates.** Sample i of a pixel belongs to replicate r = i mod R (:mod:`tofcore.tracer.qmc`); the R
replicate means m_r are independent unbiased estimates, so the variance of the pixel mean is estimated by

.. math:: \widehat{\mathrm{Var}}[\bar m] = \sum_r (m_r - \bar m_R)^2 / (R (R - 1))

(:func:`variance_of_mean`). The depth the camera outputs is a function of these means through the sensor's
decoder: ``tofcore.render.depth_standard_error`` projects each replicate's raw images through the decoder's
linearisation (it needs the sensor model, which the tracer does not import).

**MIS.** A path through a light vertex can be sampled by the BSDF + next event (strategy A, area density
p_A) or by the light vertex (strategy B, p_B); both are weighted by the balance heuristic,
w_A ← w_A p_A/(p_A + p_B), w_B ← w_B p_B/(p_A + p_B) (Veach 1997; :mod:`tofcore.tracer.light_paths`):
:func:`bsdf_strategy_weight`, :func:`light_strategy_weight`.

**Adaptive sampling**: spend each pass's samples where the estimated depth error is largest.

After a uniform pilot (``PILOT_SPP`` samples per pixel) every pass distributes its budget of n·P samples
over the pixels so that the sum of the pixels' error variances falls fastest. With per-sample variance
v_p (σ_p² n_p, σ_p the standard error of pixel p's depth after n_p samples) the error of pixel p after
N_p samples is v_p / N_p, and minimising Σ_p v_p / N_p for a fixed Σ_p N_p gives

.. math:: N_p \\propto \\sqrt{v_p} = \\sigma_p \\sqrt{n_p}

(the Neyman allocation of stratified sampling). The pass gives every pixel what it lacks of that target
total, scaled to the pass's budget. Because σ_p comes from R independent replicates (R − 1 = 3 degrees
of freedom per pixel, :mod:`tofcore.tracer.qmc`), v is averaged over the 3 × 3 neighbourhood first; a floor keeps
every pixel sampled (an unlucky low estimate must not starve it) and a cap keeps a few pixels from taking
the whole pass. Counts are multiples of R, so the replicates stay balanced.

Each pixel's estimate remains the plain mean of its own samples, whose indices run 0, 1, 2, … as
without adaptivity. The number of samples depends on earlier samples of the pixel and its
neighbours; the bias this can cause is second order (O(1/N)), far below the Monte Carlo error, and
measured in ``tests/tofcore/test_adaptive.py``.
"""

from __future__ import annotations

import numpy as np

from ..backend import namespace
from .qmc import REPLICATES


# ------------------------------------------------------------------ replicates
def replicate_counts(sample_count: np.ndarray) -> np.ndarray:
    """(R, P) samples of each replicate per pixel: samples i < n with i ≡ r (mod R)."""
    xp = namespace(sample_count)
    r = xp.arange(REPLICATES)[:, None]
    return (sample_count[None, :] - r + REPLICATES - 1) // REPLICATES


def variance_of_mean(means: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(C, H, W) variance of each pixel mean from replicate means (R, C, H, W) and counts (R, H, W).

    The replicates are weighted equally (their counts differ by at most one sample); NaN until every
    replicate has a sample.
    """
    r = means.shape[0]
    with np.errstate(invalid="ignore"):
        centred = means - means.mean(axis=0)
        var = (centred**2).sum(axis=0) / (r * (r - 1))
    return np.where((counts.min(axis=0) >= 1)[None], var, np.nan)


def rms_error(error_m: np.ndarray, distance_m: np.ndarray) -> float | None:
    """RMS of a per-pixel error over the pixels that see a surface (finite first-hit ``distance_m``) and have an
    error (finite); None where none has. What a target error is held against (``tofcore.render``'s
    convergence log, :class:`tofcore.tracer.trace.PassSchedule`)."""
    values = error_m[np.isfinite(distance_m) & np.isfinite(error_m)]
    return float(np.sqrt(np.mean(np.square(values)))) if values.size else None


# ------------------------------------------------------------------ MIS
def bsdf_strategy_weight(p_bsdf_area, prev_delta, led, q_led: float, cos_axis, cos_geo, dist):
    """Balance-heuristic weight of strategy A for next-event estimates at y to one LED.

    ``p_bsdf_area`` is p_A (the previous bounce's solid-angle pdf × cos at y / segment²); paths whose
    previous bounce was a mirror (``prev_delta``) only A can sample (weight 1).
    """
    p_light = q_led * led.emission_pdf(cos_axis) * np.maximum(cos_geo, 0.0) / dist**2
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.where(p_bsdf_area + p_light > 0, p_bsdf_area / (p_bsdf_area + p_light), 1.0)
    return np.where(prev_delta, 1.0, share)


def light_strategy_weight(w, p_bsdf, p_light):
    """Strategy B's contribution w_B weighted by the balance heuristic: w_B p_B / (p_A + p_B)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return w * p_light / (p_bsdf + p_light)


# ------------------------------------------------------------------ adaptive allocation
PILOT_SPP = 16
"""Uniform samples per pixel before the first adaptive pass (4 per replicate)."""
FLOOR = 0.1
"""Every pixel's weight is at least this fraction of the mean weight."""
CAP = 16.0
"""No pixel's weight exceeds this multiple of the mean weight."""


def allocate_samples(sigma_m: np.ndarray, counts: np.ndarray, samples_per_pixel: int) -> np.ndarray | None:
    """Samples per pixel for the next pass, or None while the pilot is still being taken (uniform).

    Parameters
    ----------
    sigma_m : (H, W) estimated standard error of each pixel's depth so far (m); NaN where unknown.
    counts : (H, W) or (P,) samples each pixel has so far.
    samples_per_pixel : the pass's budget, n samples per pixel on average.

    Returns
    -------
    (P,) int64 multiples of R (:data:`tofcore.tracer.qmc.REPLICATES`) summing to about n·P.
    """
    sigma = np.asarray(sigma_m, np.float64)
    n = np.asarray(counts, np.float64).reshape(sigma.shape)
    if n.min() < PILOT_SPP:
        return None
    v = np.where(np.isfinite(sigma), sigma**2 * n, np.nan)
    weight = np.sqrt(_neighbourhood_mean(v))
    known = np.isfinite(weight)
    mean = weight[known].mean() if known.any() and weight[known].mean() > 0 else 1.0
    weight = np.clip(np.where(known, weight, mean), FLOOR * mean, CAP * mean)
    budget = samples_per_pixel * n.size
    target = (n.sum() + budget) * weight / weight.sum()
    lacking = np.maximum(target - n, 0.0)
    extra = lacking * (budget / lacking.sum())
    return (np.floor(extra / REPLICATES + 0.5).astype(np.int64) * REPLICATES).reshape(-1)


def _neighbourhood_mean(values: np.ndarray) -> np.ndarray:
    """Mean of the finite values in each pixel's 3 × 3 neighbourhood (NaN where none is finite)."""
    finite = np.isfinite(values)
    padded = np.pad(np.where(finite, values, 0.0), 1)
    weights = np.pad(finite.astype(np.float64), 1)
    h, w = values.shape
    total = sum(padded[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3))
    count = sum(weights[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan)
