r"""Preview denoising: a joint bilateral local-plane filter of the output depth, guided by the amplitude image.

For interactive previews only (``render(..., preview_denoise=True)``, ``tofcore render --preview-denoise``,
the add-on's live preview): it trades a small bias at depth edges for less render noise in a frame of
few samples. Datasets never get it unless asked for explicitly; a filtered frame says so in
``frame.stats["preview_denoise"]``.

Each valid pixel p becomes the value at p of the plane fitted by weighted least squares to the valid
pixels q = p + (Δx, Δy) of its (2r + 1)² window,

.. math::

    \hat d_p = c_0, \quad (c_0, c_x, c_y) = \arg\min \sum_q w_{pq}\,(d_q - c_0 - c_x Δx - c_y Δy)^2,

    w_{pq} = \exp\!\Big(-\frac{Δx^2 + Δy^2}{2 r^2}\Big)
             \exp\!\Big(-\frac{(\ln A_q - \ln A_p)^2}{2 s_A^2}\Big)
             \exp\!\Big(-\frac{(d_q - d_p)^2}{2 k^2 \sigma_p^2}\Big),

a joint (cross) bilateral filter (Petschnigg et al. 2004, Eisemann & Durand 2004) with the amplitude A
as the guide — an edge in reflectance or orientation stops the averaging — and a range term on the
depth itself scaled by the render's own estimated depth error :math:`\sigma_p` (``frame.render_error``,
:func:`tofcore.render.depth_standard_error`): neighbours within a few standard errors count, a step of
many (an occluding edge with the same amplitude on both sides) does not. The plane instead of the
weighted mean (a local-linear bilateral fit, as in Choudhury & Tumblin's trilateral filter) keeps a
sloped surface unbiased where the window is lopsided (invalid neighbours, the range term cutting one
side): on the demo room at 8 spp the weighted mean *raised* the error on smooth surfaces (4.27 → 4.25
mm at best, 9.6 mm as a plain Gaussian), the plane lowers it (studies/preview_denoise.py). Where the
fit is degenerate (neighbours on a line) the weighted mean is used; where :math:`\sigma_p` is unknown
(fewer than R = 4 samples) or zero the pixel is left as it is.

Pure NumPy (no OpenCV: it must run inside Blender, :mod:`tofcore.native`), float32, (2r + 1)² shifted
array operations; its time is measured in ``studies/preview_denoise.py``.
"""

from __future__ import annotations

import numpy as np

RADIUS_PX = 3
"""Window radius r (pixels); also the spatial Gaussian's standard deviation."""
AMPLITUDE_SIGMA = 0.3
"""s_A: standard deviation of the log-amplitude difference (≈ 30 % relative amplitude)."""
DEPTH_SIGMAS = 3.0
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
    # weighted moments of the offsets, s = Σ w (1, Δx, Δy, Δx², ΔxΔy, Δy²), and of the depth relative to p,
    # t = Σ w (d_q − d_p)(1, Δx, Δy); the loop adds into their rows (views)
    s, t = np.zeros((6, h, w), np.float32), np.zeros((3, h, w), np.float32)
    s0, sx, sy, sxx, sxy, syy = s
    t0, tx, ty = t
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            window = (slice(r + dy, r + dy + h), slice(r + dx, r + dx + w))
            rel = d_pad[window] - d
            t_amp = la_pad[window] - log_amp
            t_depth = rel * depth_scale
            exponent = t_amp * t_amp
            exponent += t_depth * t_depth
            exponent += np.float32((dy * dy + dx * dx) / (2.0 * r * r))
            w_q = np.exp(-exponent, out=exponent)
            w_q *= ok_pad[window]
            s0 += w_q
            t0 += w_q * rel
            if dx:
                sx += np.float32(dx) * w_q
                sxx += np.float32(dx * dx) * w_q
                tx += np.float32(dx) * (w_q * rel)
            if dy:
                sy += np.float32(dy) * w_q
                syy += np.float32(dy * dy) * w_q
                ty += np.float32(dy) * (w_q * rel)
            if dx and dy:
                sxy += np.float32(dx * dy) * w_q
    smooth = d + _plane_at_centre(s, t)
    return np.where(filtered, smooth, depth).astype(np.asarray(depth).dtype, copy=False)


def _plane_at_centre(s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """c_0 of the weighted least-squares plane (Cramer's rule on the 3 × 3 normal equations), or the
    weighted mean t0/s0 where the system is nearly singular (det < 10⁻³ s0³).

    ``s`` (6, H, W): the weighted moments Σ w (1, Δx, Δy, Δx², ΔxΔy, Δy²) of the offsets; ``t`` (3, H, W):
    Σ w (d_q − d_p)(1, Δx, Δy). The normal equations are

    .. math:: \\begin{pmatrix} s_0 & s_x & s_y \\\\ s_x & s_{xx} & s_{xy} \\\\ s_y & s_{xy} & s_{yy} \\end{pmatrix}
              \\begin{pmatrix} c_0 \\\\ c_x \\\\ c_y \\end{pmatrix}
              = \\begin{pmatrix} t_0 \\\\ t_x \\\\ t_y \\end{pmatrix}.
    """
    s0, sx, sy, sxx, sxy, syy = s
    t0, tx, ty = t
    minor_xx = sxx * syy - sxy * sxy
    det = s0 * minor_xx - sx * (sx * syy - sxy * sy) + sy * (sx * sxy - sxx * sy)
    numerator = t0 * minor_xx - sx * (tx * syy - sxy * ty) + sy * (tx * sxy - sxx * ty)
    with np.errstate(invalid="ignore", divide="ignore"):
        plane = numerator / det
        mean = t0 / s0
    return np.where(det > 1e-3 * s0 * s0 * s0, plane, mean)
