r"""Preview denoising: a joint bilateral filter of the output depth, guided by the amplitude image.

For interactive previews only (``render(..., preview_denoise=True)``, ``tofcore render --preview-denoise``,
the add-on's live preview): it trades a small bias at depth edges for less render noise in a frame of
few samples. Datasets never get it unless asked for explicitly; a filtered frame says so in
``frame.stats["preview_denoise"]``.

Each valid pixel p becomes the weighted mean of the valid pixels q in its (2r + 1)² window,

.. math::

    \hat d_p = \frac{\sum_q w_{pq}\, d_q}{\sum_q w_{pq}}, \qquad
    w_{pq} = \exp\!\Big(-\frac{|q - p|^2}{2 r^2}\Big)
             \exp\!\Big(-\frac{(\ln A_q - \ln A_p)^2}{2 s_A^2}\Big)
             \exp\!\Big(-\frac{(d_q - d_p)^2}{2 k^2 \sigma_p^2}\Big),

the joint (cross) bilateral filter (Petschnigg et al. 2004, Eisemann & Durand 2004) with the amplitude
A as the guide — an edge in reflectance or orientation stops the averaging — plus a range term on
the depth itself scaled by the render's own estimated depth error :math:`\sigma_p`
(``frame.render_error``, :func:`tofcore.render.depth_standard_error`): neighbours within a few
standard errors are averaged, a step of many (an occluding edge with the same amplitude on both
sides) is kept. Where :math:`\sigma_p` is unknown (fewer than R = 4 samples) or zero the pixel is left
as it is. A guided filter (He et al. 2013) was the other candidate: its output is linear in the
guide inside each window, so a depth edge without an amplitude edge would be blurred across.

Pure NumPy (no OpenCV: it must run inside Blender, :mod:`tofcore.native`); (2r + 1)² shifted
array operations, measured in ``studies/preview_denoise.py``.
"""

from __future__ import annotations

import numpy as np

RADIUS_PX = 2
"""Window radius r (pixels); also the spatial Gaussian's standard deviation."""
AMPLITUDE_SIGMA = 0.15
"""s_A: standard deviation of the log-amplitude difference (≈ 15 % relative amplitude)."""
DEPTH_SIGMAS = 2.5
"""k: the depth range term's width in units of the pixel's estimated depth error."""


def preview_denoise(depth: np.ndarray, amplitude: np.ndarray, sigma_m: np.ndarray, *, radius_px: int = RADIUS_PX,
                    amplitude_sigma: float = AMPLITUDE_SIGMA, depth_sigmas: float = DEPTH_SIGMAS) -> np.ndarray:
    """(H, W) depth after the joint bilateral filter (module docstring), NaN where ``depth`` is NaN.

    Parameters
    ----------
    depth : (H, W) output depth or distance (m), NaN where invalid.
    amplitude : (H, W) the decoded amplitude (electrons), the guide; pixels with A ≤ 0 are not used.
    sigma_m : (H, W) estimated depth standard error of each pixel (m); NaN or 0 leaves the pixel unfiltered.
    radius_px : window radius r ≥ 1 (pixels).
    amplitude_sigma : s_A > 0, on ln A.
    depth_sigmas : k > 0.
    """
    if not (isinstance(radius_px, (int, np.integer)) and radius_px >= 1):
        raise ValueError(f"preview_denoise: radius_px must be an integer >= 1, got {radius_px!r}")
    for name, value in (("amplitude_sigma", amplitude_sigma), ("depth_sigmas", depth_sigmas)):
        if not value > 0:
            raise ValueError(f"preview_denoise: {name} must be > 0, got {value!r}")
    d = np.asarray(depth, np.float32)
    amp = np.asarray(amplitude, np.float32)
    sigma = np.asarray(sigma_m, np.float32)
    if not d.shape == amp.shape == sigma.shape or d.ndim != 2:
        raise ValueError(f"preview_denoise: depth, amplitude and sigma_m must be one (H, W) shape, got "
                         f"{d.shape}, {amp.shape}, {sigma.shape}")
    usable = np.isfinite(d) & (amp > 0)
    log_amp = np.log(np.where(usable, amp, 1.0)) * np.float32(np.sqrt(0.5) / amplitude_sigma)  # scaled: Δ² is the term
    filtered = usable & np.isfinite(sigma) & (sigma > 0)
    depth_scale = np.where(filtered, np.float32(np.sqrt(0.5) / depth_sigmas) / np.where(filtered, sigma, 1.0), 0.0)
    d = np.where(usable, d, 0.0).astype(np.float32)
    r = int(radius_px)
    h, w = d.shape
    d_pad, la_pad = np.pad(d, r), np.pad(log_amp, r)
    ok_pad = np.pad(usable, r).astype(np.float32)
    total = np.zeros((h, w), np.float32)
    weight = np.zeros((h, w), np.float32)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            window = (slice(r + dy, r + dy + h), slice(r + dx, r + dx + w))
            d_q = d_pad[window]
            t_amp = la_pad[window] - log_amp
            t_depth = (d_q - d) * depth_scale
            exponent = t_amp * t_amp
            exponent += t_depth * t_depth
            exponent += np.float32((dy * dy + dx * dx) / (2.0 * r * r))
            w_q = np.exp(-exponent, out=exponent)
            w_q *= ok_pad[window]
            total += w_q * d_q
            weight += w_q
    with np.errstate(invalid="ignore", divide="ignore"):
        smooth = total / weight
    return np.where(filtered, smooth, depth).astype(np.asarray(depth).dtype, copy=False)
