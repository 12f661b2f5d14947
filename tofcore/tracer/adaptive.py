"""Adaptive sampling: spend each pass's samples where the estimated depth error is largest.

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

from .qmc import REPLICATES

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
