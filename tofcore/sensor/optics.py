"""Lens scattering: a point spread function convolved with every raw image before decoding.

Light focused on one pixel also reaches its neighbours (diffraction at the
aperture, reflections and scattering inside the lens; thesis §4.0.6). Because
this happens to the *charge* of every raw (bucket) image before the phase is
decoded, a bright near object mixes its phase into a dark far background: the
background's distance is pulled towards the object, most strongly at the
boundary, and the pixels on the boundary become flying (mixed) pixels
(§4.0.7, §5.2.1, §6.2). Only the scattering is simulated; mixed pixels follow.

=================  ====  ========  ============================================================
parameter          unit  default   meaning (:func:`psf_kernel`)
=================  ====  ========  ============================================================
``model``          –     –         ``"none"``, ``"airy"`` or ``"gaussians"`` (:data:`MODELS`)
``strength``       1     –         fraction s ∈ [0, 1] of a pixel's light that is scattered
``radius_px``      px    0         ``"airy"``: radius of the first dark ring (> 0)
``negative_lobe``  1     0         ``"airy"``: depth of the first ring below zero, relative
                                   to the pattern's peak (negative: a bright ring instead)
``sigmas_px``      px    ()        ``"gaussians"``: standard deviations σ_i (> 0)
``weights``        1     ()        ``"gaussians"``: weights w_i ≥ 0 (normalised; empty: equal)
``size_px``        px    None      odd kernel side; None: where the profile falls below
                                   :data:`TAIL_FRACTION` of its peak, at most :data:`MAX_SIZE_PX`
=================  ====  ========  ============================================================

Parameters of the model not chosen are ignored, so one sensor configuration
can carry both. The measured PSFs of the O3D303 and the Kinect v2 had negative
values and were not monotonic on either side of zero, so a sum of Gaussians
(Jamtsho and Lichti 2010) cannot fit them; they resembled Airy discs
(§4.0.6, Fig. 4.17). ``"airy"`` is that shape with an adjustable negative
first ring; ``"gaussians"`` is the positive-only model of the literature.

Example::

    kernel = psf_kernel("airy", strength=0.05, radius_px=2.0, negative_lobe=0.03)
    raw = apply_scattering(raw, kernel)      # raw: (R, H, W) electrons
"""

from __future__ import annotations

import math

import numpy as np

from ..backend import asarray, device_copy, namespace
from ..errors import ConfigError
from ..native import optional_module

# OpenCV is optional: a faster convolution when installed (not inside Blender), same result as the NumPy path.
cv2 = optional_module("cv2")

MODELS = ("none", "airy", "gaussians")
TAIL_FRACTION = 1e-4
"""The automatic kernel ends where the profile falls below this fraction of its peak."""
MAX_SIZE_PX = 257
"""Largest automatic kernel side (half a Kinect v2 image)."""
SUBSAMPLES_PER_RADIUS = 24
"""The ``"airy"`` taps are pixel averages of the profile by an n × n midpoint rule with
n = 24 / ``radius_px`` sub-samples per pixel side, at least 5 and at most 33: taps to ~1e-3 of the
largest one."""

J1_ZERO_1 = 3.8317059702075125
"""First positive zero of J1: the first dark ring of the Airy pattern."""
J1_ZERO_2 = 7.015586669815619
"""Second positive zero of J1: the second dark ring."""
AIRY_FIRST_RING_PEAK = 0.017497862785775
"""Peak of the Airy pattern's first bright ring relative to the centre: [2 J1(x)/x]² at x = 5.1356223
(the first zero of J2)."""
_AIRY_TAIL_X = (8.0 / (math.pi * TAIL_FRACTION)) ** (1.0 / 3.0)  # envelope 8/(π x³) of [2 J1(x)/x]² = tail


def bessel_j1(x: np.ndarray) -> np.ndarray:
    """The Bessel function of the first kind of order one, J1(x), to ~1e-7 absolute, without SciPy.

    Notes
    -----
    Abramowitz and Stegun (1964) 9.4.4 for :math:`|x| \\le 3` (error < 1.3e-8 in J1/x),

    .. math:: J_1(x)/x = \\tfrac12 - 0.56249985\\,t^2 + 0.21093573\\,t^4 - 0.03954289\\,t^6
              + 0.00443319\\,t^8 - 0.00031761\\,t^{10} + 0.00001109\\,t^{12},\\quad t = x/3,

    and 9.4.6 for :math:`x > 3` (errors < 4e-8 in f1, < 9e-8 in θ1), with :math:`u = 3/x`,

    .. math:: J_1(x) = x^{-1/2} f_1 \\cos\\theta_1,\\quad
              f_1 = 0.79788456 + 0.00000156\\,u + 0.01659667\\,u^2 + 0.00017105\\,u^3
              - 0.00249511\\,u^4 + 0.00113653\\,u^5 - 0.00020033\\,u^6,

    .. math:: \\theta_1 = x - 2.35619449 + 0.12499612\\,u + 0.00005650\\,u^2 - 0.00637879\\,u^3
              + 0.00074348\\,u^4 + 0.00079824\\,u^5 - 0.00029166\\,u^6.

    J1 is odd; the tests check it against the integral :math:`\\frac1\\pi\\int_0^\\pi
    \\cos(\\tau - x\\sin\\tau)\\,d\\tau`.
    """
    x = asarray(x, dtype=np.float64)
    ax = np.abs(x)
    t2 = (np.minimum(ax, 3.0) / 3.0) ** 2
    small = x * (0.5 + t2 * (-0.56249985 + t2 * (0.21093573 + t2 * (-0.03954289 + t2 * (
        0.00443319 + t2 * (-0.00031761 + t2 * 0.00001109))))))
    u = 3.0 / np.maximum(ax, 3.0)
    f1 = 0.79788456 + u * (0.00000156 + u * (0.01659667 + u * (0.00017105 + u * (
        -0.00249511 + u * (0.00113653 + u * -0.00020033)))))
    theta1 = ax - 2.35619449 + u * (0.12499612 + u * (0.00005650 + u * (-0.00637879 + u * (
        0.00074348 + u * (0.00079824 + u * -0.00029166)))))
    large = np.sign(x) * f1 * np.cos(theta1) / np.sqrt(np.maximum(ax, 3.0))
    return np.where(ax <= 3.0, small, large)


def airy_profile(r_px: np.ndarray, *, radius_px: float, negative_lobe: float) -> np.ndarray:
    """The ``"airy"`` ring pattern p(r) (peak 1 at r = 0) at distances ``r_px`` (px) from the centre.

    Notes
    -----
    With :math:`x = j_{1,1} r / r_0` (:math:`j_{1,1}` = 3.8317, the first zero of J1,
    :math:`r_0` = ``radius_px``) and the Airy pattern :math:`I(x) = [2 J_1(x)/x]^2`,

    .. math:: p(r) = \\begin{cases} -\\dfrac{\\ell}{a_1} I(x) & j_{1,1} < x < j_{1,2} \\\\
              I(x) & \\text{otherwise,} \\end{cases}

    :math:`\\ell` = ``negative_lobe``, :math:`a_1` = :data:`AIRY_FIRST_RING_PEAK`,
    :math:`j_{1,2}` = 7.0156. The first bright ring of the Airy pattern, between
    the first and second dark rings, is turned into a ring whose extreme is
    :math:`-\\ell` (at r = 1.340 r0), so ℓ reads directly off a measured PSF
    plot (Fig. 4.17). ``negative_lobe = 0`` leaves that ring dark;
    ``negative_lobe = -AIRY_FIRST_RING_PEAK`` gives the diffraction-limited
    Airy pattern. I has double zeros at the dark rings, so p stays continuously
    differentiable; the outer rings are the Airy ones (envelope 8/(π x³)).
    """
    x = J1_ZERO_1 * asarray(r_px, dtype=np.float64) / radius_px
    safe_x = np.where(x > 0.0, x, 1.0)
    intensity = np.where(x > 0.0, (2.0 * bessel_j1(safe_x) / safe_x) ** 2, 1.0)
    first_ring = (x > J1_ZERO_1) & (x < J1_ZERO_2)
    return np.where(first_ring, -negative_lobe / AIRY_FIRST_RING_PEAK * intensity, intensity)


def psf_kernel(model: str, *, strength: float, radius_px: float = 0.0, negative_lobe: float = 0.0,
               sigmas_px=(), weights=(), size_px: int | None = None) -> np.ndarray:
    """The lens-scattering kernel: odd (n, n) float64, symmetric, summing to 1.

    Parameters are described in the module docstring table.

    Returns
    -------
    kernel : (n, n) float64 array, centre tap at ``[n // 2, n // 2]``; the 1 × 1
        identity for ``"none"`` or strength 0 (unless ``size_px`` asks for more).

    Raises
    ------
    ConfigError
        Naming the parameter, for an unknown model or an invalid value.

    Notes
    -----
    .. math:: K_{total} = (1 - s)\\,\\delta + s\\,K / \\textstyle\\sum K

    ``"airy"``: K is the pixel-averaged :func:`airy_profile`; its total must be
    positive, which holds for ``negative_lobe`` < 0.22 (the total, and with it
    the normalisation, approaches zero there). ``"gaussians"``:
    :math:`K = \\sum_i \\hat w_i G_{\\sigma_i}` with :math:`\\hat w_i = w_i / \\sum w`
    and every :math:`G_\\sigma` the exact pixel integral of a normalised 2-D Gaussian,
    renormalised over the kernel window, so :math:`s \\hat w_i` is exactly the
    fraction of light scattered by component i. The automatic size holds the
    profile down to :data:`TAIL_FRACTION` of its peak: :math:`r = 29.4\\,r_0 / j_{1,1}`
    = 7.7 ``radius_px`` for ``"airy"`` (≈2 % of an Airy pattern's light lies
    beyond), :math:`\\sqrt{2 \\ln 10^4}\\,\\sigma_{max}` = 4.3 σ for ``"gaussians"``.
    """
    where = "psf_kernel"
    if model not in MODELS:
        raise ConfigError(f"{where}: model must be one of {list(MODELS)}, got {model!r}")
    if not (isinstance(strength, (int, float, np.number)) and 0.0 <= strength <= 1.0):
        raise ConfigError(f"{where}: strength must be a number in [0, 1], got {strength!r}")
    if size_px is not None and not (isinstance(size_px, (int, np.integer)) and size_px >= 1 and size_px % 2 == 1):
        raise ConfigError(f"{where}: size_px must be None or an odd integer >= 1, got {size_px!r}")
    if model == "airy":
        _check_airy(radius_px, negative_lobe)
    elif model == "gaussians":
        sigmas, fractions = _check_gaussians(sigmas_px, weights)
    if model == "none" or strength == 0.0:
        return _delta(1 if size_px is None else size_px)
    if model == "airy":
        half = _half_width(radius_px * _AIRY_TAIL_X / J1_ZERO_1, size_px)
        pattern = _airy_taps(half, radius_px=radius_px, negative_lobe=negative_lobe)
        if not pattern.sum() > 0.0:
            raise ConfigError(f"{where}: negative_lobe must leave the ring pattern a positive total "
                              f"(below about 0.22), got {negative_lobe!r}")
    else:
        half = _half_width(math.sqrt(2.0 * math.log(1.0 / TAIL_FRACTION)) * max(sigmas), size_px)
        pattern = sum(w * _gaussian_taps(half, s) for w, s in zip(fractions, sigmas))
    kernel = strength * pattern / pattern.sum()
    kernel[half, half] += 1.0 - strength
    return kernel / kernel.sum()


def _check_airy(radius_px: float, negative_lobe: float) -> None:
    if not (isinstance(radius_px, (int, float, np.number)) and 0.0 < radius_px < math.inf):
        raise ConfigError(f"psf_kernel: radius_px must be a finite number > 0 for model 'airy', got {radius_px!r}")
    if not (isinstance(negative_lobe, (int, float, np.number)) and math.isfinite(negative_lobe)):
        raise ConfigError(f"psf_kernel: negative_lobe must be a finite number, got {negative_lobe!r}")


def _check_gaussians(sigmas_px, weights) -> tuple[list[float], list[float]]:
    """Validated σ_i and the normalised weights ŵ_i."""
    sigmas = _float_vector(sigmas_px)
    if sigmas is None or sigmas.size == 0 or not np.all((sigmas > 0.0) & np.isfinite(sigmas)):
        raise ConfigError(f"psf_kernel: sigmas_px must be one or more finite numbers > 0 for model 'gaussians', "
                          f"got {sigmas_px!r}")
    w = _float_vector(weights)
    if w is not None and w.size == 0:
        w = np.ones(sigmas.size)
    if w is None or w.size != sigmas.size or not np.all((w >= 0.0) & np.isfinite(w)) or not w.sum() > 0.0:
        raise ConfigError(f"psf_kernel: weights must be empty or {sigmas.size} finite numbers >= 0 "
                          f"(one per sigmas_px entry) with a positive sum, got {weights!r}")
    return sigmas.tolist(), (w / w.sum()).tolist()


def _float_vector(values) -> np.ndarray | None:
    """``values`` as a flat float64 array, or None if they are not numbers."""
    try:
        return asarray(values, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        return None


def _half_width(tail_radius_px: float, size_px: int | None) -> int:
    if size_px is not None:
        return size_px // 2
    return min(max(1, math.ceil(tail_radius_px)), MAX_SIZE_PX // 2)


def _delta(size: int) -> np.ndarray:
    kernel = np.zeros((size, size))
    kernel[size // 2, size // 2] = 1.0
    return kernel


def _mirror_quadrant(quadrant: np.ndarray) -> np.ndarray:
    """The full (2h+1)² kernel from its (h+1)² quadrant of taps at offsets (|dy|, |dx|), exactly symmetric."""
    half = quadrant.shape[0] - 1
    index = np.abs(np.arange(-half, half + 1))
    symmetric = 0.5 * (quadrant + quadrant.T)  # exactly symmetric: IEEE addition commutes
    return symmetric[index[:, None], index[None, :]]


def _airy_taps(half: int, *, radius_px: float, negative_lobe: float) -> np.ndarray:
    """Pixel averages of :func:`airy_profile` on the (2 half + 1)² grid (:data:`SUBSAMPLES_PER_RADIUS`)."""
    n = min(max(5, math.ceil(SUBSAMPLES_PER_RADIUS / radius_px)), 33)
    sub = (np.arange(n) + 0.5) / n - 0.5
    pos = (np.arange(half + 1)[:, None] + sub[None, :]).ravel()  # (half+1)·n sub-sample positions, px
    r = np.hypot(pos[:, None], pos[None, :])
    values = airy_profile(r, radius_px=radius_px, negative_lobe=negative_lobe)
    quadrant = values.reshape(half + 1, n, half + 1, n).mean(axis=(1, 3))
    return _mirror_quadrant(quadrant)


def _gaussian_taps(half: int, sigma_px: float) -> np.ndarray:
    """Exact pixel integrals of a normalised 2-D Gaussian of σ = ``sigma_px``, renormalised to sum 1."""
    edges = (np.arange(-half, half + 2) - 0.5) / (sigma_px * math.sqrt(2.0))
    cdf = np.array([math.erf(e) for e in edges])
    taps_1d = 0.5 * np.diff(cdf)
    taps_1d = 0.5 * (taps_1d + taps_1d[::-1])  # exactly symmetric
    kernel = np.outer(taps_1d, taps_1d)
    return kernel / kernel.sum()


def apply_scattering(raw: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Convolve every raw image with the PSF kernel; edges reflect, so no charge leaves the sensor.

    Parameters
    ----------
    raw : (..., H, W) charge, e⁻ — typically (R, H, W), one image per (frequency, phase step).
    kernel : (m, n) with odd sides, e.g. from :func:`psf_kernel`.

    Returns
    -------
    (..., H, W) float64: :math:`(raw * K)(y, x) = \\sum_{i,j} K(i, j)\\, raw(y - i, x - j)`,
    offsets from the kernel centre.

    Notes
    -----
    The image is extended by half-sample symmetric reflection (``d c b a | a b c d``,
    NumPy ``"symmetric"``, OpenCV ``BORDER_REFLECT``), repeated as often as the
    kernel needs. For a kernel symmetric under x → −x and y → −y this returns
    to the image exactly the light that would leave it across an edge, so the
    total charge is multiplied by ΣK (conserved for ΣK = 1) — the sensor does
    not lose light at its border, and a uniform image stays uniform. Zero
    padding would instead darken the border and bend the phase of border
    pixels towards nothing in particular; the light from outside the field of
    view, which would scatter in, is unknown either way and the mirror is its
    closest stand-in. Negative taps can make a dark pixel's charge negative
    next to a bright one; it is kept (noise clips it, :mod:`tofcore.sensor.noise`).

    OpenCV's ``filter2D`` is used when installed, else (and always on the GPU, with cuFFT) an FFT
    convolution (:func:`_convolve_fft`); both are exact to float64 round-off and tested
    against a direct sum.
    """
    raw = asarray(raw, dtype=np.float64)
    kernel = asarray(kernel, dtype=np.float64)
    # a host kernel is checked here and uploaded once per array (device_copy); a device kernel's values are
    # the caller's business (checking them would read them back)
    finite = not isinstance(kernel, np.ndarray) or bool(np.isfinite(kernel).all())
    kernel = device_copy(namespace(raw), kernel) if isinstance(kernel, np.ndarray) else kernel
    if kernel.ndim != 2 or kernel.shape[0] % 2 == 0 or kernel.shape[1] % 2 == 0 or not finite:
        raise ConfigError(f"apply_scattering: kernel must be a finite 2-D array with odd sides, "
                          f"got shape {kernel.shape!r}")
    if raw.ndim < 2 or raw.shape[-1] == 0 or raw.shape[-2] == 0:
        raise ConfigError(f"apply_scattering: raw must have shape (..., H, W) with H, W >= 1, got {raw.shape!r}")
    if kernel.shape == (1, 1):
        return raw * kernel[0, 0]
    images = raw.reshape(-1, *raw.shape[-2:])
    on_cpu = namespace(images) is np
    out = _convolve_cv2(images, kernel) if cv2 is not None and on_cpu else _convolve_fft(images, kernel)
    return out.reshape(raw.shape)


def _convolve_cv2(images: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """:func:`apply_scattering` of (N, H, W) images by OpenCV (correlation with the flipped kernel)."""
    flipped = np.ascontiguousarray(kernel[::-1, ::-1])
    return np.stack([cv2.filter2D(np.ascontiguousarray(image), cv2.CV_64F, flipped, borderType=cv2.BORDER_REFLECT)
                     for image in images])


def _convolve_fft(images: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """:func:`apply_scattering` of (N, H, W) images by ``numpy.fft.rfft2``, exact for any sizes.

    The images are padded by the kernel's half sizes (reflecting); a circular
    convolution of length L ≥ H + 2 h_y (and W + 2 h_x) has no wrap-around in
    the rows and columns kept, [2 h_y, 2 h_y + H) × [2 h_x, 2 h_x + W).
    """
    hy, hx = kernel.shape[0] // 2, kernel.shape[1] // 2
    _, height, width = images.shape
    xp = namespace(images)  # NumPy, or CuPy's cuFFT on the GPU
    padded = xp.pad(images, ((0, 0), (hy, hy), (hx, hx)), mode="symmetric")
    shape = (_fast_fft_length(height + 2 * hy), _fast_fft_length(width + 2 * hx))
    spectrum = xp.fft.rfft2(padded, s=shape) * xp.fft.rfft2(kernel, s=shape)
    full = xp.fft.irfft2(spectrum, s=shape)
    return full[:, 2 * hy:2 * hy + height, 2 * hx:2 * hx + width]


def _fast_fft_length(n: int) -> int:
    """The smallest 5-smooth integer ≥ n (FFT lengths with factors 2, 3, 5 only are fast)."""
    while True:
        m = n
        for p in (2, 3, 5):
            while m % p == 0:
                m //= p
        if m == 1:
            return n
        n += 1
