"""The camera's own processing of its decoded phases: how frequencies are combined, how phasors are filtered.

A real ToF camera does not output the per-pixel maximum-likelihood distance of its raw images: its
firmware or driver combines the frequencies with fixed weights and filters the per-frequency phasors
over a neighbourhood before unwrapping. Both change the depth noise a camera delivers (the Kinect v2's
3 × 3 filter alone divides it by almost 3), so a preset that should behave like its camera names them
in its ``[processing]`` table (:class:`tofcore.sensor.Processing`):

=====================  ====  ===================  ===============================================================
name                   unit  default              meaning
=====================  ====  ===================  ===============================================================
``unwrap_weights``     –     "inverse_variance"   how :func:`tofcore.decode.unwrap` averages the unwrapped
                                                  frequencies: ``"inverse_variance"`` (w_i ∝ (f_i A_i)²/(A_i+B_i),
                                                  eq. 2.43, the least noisy) or ``"frequency"`` (w_i = f_i / Σf:
                                                  the phases summed in cycles, as libfreenect2 does)
``phasor_filter``      –     "none"               ``"none"`` or ``"bilateral"``: libfreenect2's joint bilateral
                                                  filter of each frequency's phasor (:func:`bilateral_phasor_filter`)
=====================  ====  ===================  ===============================================================

The Kinect v2's pipeline is public through libfreenect2 (``src/cpu_depth_packet_processor.cpp``,
``filterPixelStage1`` and ``processPixelStage2``; parameters in ``src/depth_packet_processor.cpp``),
which reproduces the depth of Microsoft's SDK. Edge and outlier filters that only invalidate pixels
(libfreenect2's ``filterPixelStage2``) are not modelled.
"""

from __future__ import annotations

import math

import numpy as np

from ..backend import namespace
from ..errors import ConfigError

UNWRAP_WEIGHTS = ("inverse_variance", "frequency")
PHASOR_FILTERS = ("none", "bilateral")

#: libfreenect2 ``gaussian_kernel``: the 3 × 3 spatial weights, row-major (centre 0.1195716).
BILATERAL_KERNEL = np.array([[0.1069973, 0.1131098, 0.1069973],
                             [0.1131098, 0.1195716, 0.1131098],
                             [0.1069973, 0.1131098, 0.1069973]])
#: libfreenect2 ``joint_bilateral_exp`` = 5, applied as exp(−log₂(e) · 5 · dist) (its shader's exp2 form).
BILATERAL_EXPONENT = 5.0 * math.log2(math.e)


def frequency_weights(frequencies_hz, shape: tuple[int, ...], xp=np) -> np.ndarray:
    r"""(F, *shape) weights :math:`w_i = f_i / \sum_j f_j` of the ``"frequency"`` combination.

    Notes
    -----
    libfreenect2 (``processPixelStage2``) unwraps the 80, 16 and 120 MHz phases of the Kinect v2 to
    cycles of each frequency, :math:`n_i = f_i \tau`, and outputs :math:`\hat\tau = \sum_i n_i / \sum_i f_i`
    (its ``t10``: the three cycle counts summed, scaled by the 72 MHz of ``unambigious_dist``). That is
    the weighted mean of the per-frequency delays :math:`\tau_i = n_i / f_i` with weights
    :math:`f_i/\sum f`, so a frequency's phase noise σ_φ,i enters as
    :math:`\sigma_\tau^2 = \sum_i \sigma_{\varphi,i}^2 / (2\pi \sum_j f_j)^2`; for the Kinect v2
    (16 MHz with half the exposure) that is 1.34 × the σ of inverse-variance weights.
    """
    f_hz = xp.asarray(frequencies_hz, dtype=np.float64).reshape((-1,) + (1,) * len(shape))
    return xp.broadcast_to(f_hz / f_hz.sum(), (f_hz.shape[0],) + tuple(shape))


def bilateral_phasor_filter(real: np.ndarray, imag: np.ndarray, *, min_amplitude=0.0) -> tuple:
    r"""libfreenect2's joint bilateral filter of one frequency's phasors over each pixel's 3 × 3 neighbours.

    Parameters
    ----------
    real, imag : (..., H, W) the phasor :math:`Z = A e^{i\varphi}` of every pixel (any scale, e.g. e⁻).
    min_amplitude : a pixel with :math:`|Z|` at least this takes the range term and ignores neighbours
        below it; a weaker pixel is the plain Gaussian mean of all nine (libfreenect2's
        ``joint_bilateral_ab_threshold``), same unit as the phasors.

    Returns
    -------
    (real, imag) filtered, float64, same shape. Pixels on the image border pass through unchanged, as
    in libfreenect2.

    Notes
    -----
    .. math:: Z'_p = \frac{\sum_{q \in N_3(p)} k_q\, e^{-b\, d_{pq}}\, Z_q}{\sum_q k_q\, e^{-b\, d_{pq}}},
              \qquad d_{pq} = \tfrac12 \left(1 - \cos(\varphi_p - \varphi_q)\right)

    with the nearly flat Gaussian :data:`BILATERAL_KERNEL` k and :data:`BILATERAL_EXPONENT` b; the
    centre has weight k_0 and no range term. On a flat surface :math:`d \approx 0` and the filter is a
    weighted mean of 9 independent phasors: the phase variance falls to
    :math:`\sum k^2 / (\sum k)^2 = 0.1115` (σ × 0.334). Across an edge (φ differing by π) a
    neighbour's weight falls by :math:`e^{-b} = 1/32`.
    """
    re, im = _phasor_pair(real, imag)
    weights = bilateral_weights(re, im, min_amplitude=min_amplitude)
    return neighbour_mean(re, weights), neighbour_mean(im, weights)


def bilateral_weights(real: np.ndarray, imag: np.ndarray, *, min_amplitude=0.0) -> np.ndarray | None:
    """(3, 3, ..., H − 2, W − 2) normalised weights of :func:`bilateral_phasor_filter` for every inner pixel
    (neighbour offset dy, dx first); None for an image smaller than 3 × 3 (nothing is filtered).

    With the weights of the noise-free phasors held fixed, :func:`neighbour_mean` is the filter's
    linearisation: what it does to small errors of the pixels (e.g. the render's Monte Carlo error).
    ``min_amplitude`` as in :func:`bilateral_phasor_filter`, a number or an array broadcast against the
    phasors (e.g. one threshold per frequency, shape (F, 1, 1)). One neighbour offset at a time, each
    weight computed in place in the output: a fixed 9 × 10 array operations whatever the image, and no
    temporary larger than one image (2.3× faster than stacking the nine neighbours first, the same bits).
    """
    re, im = _phasor_pair(real, imag)
    xp = namespace(re)
    height, width = re.shape[-2:]
    if height < 3 or width < 3:
        return None
    norm = np.hypot(re, im)
    safe = np.where(norm > 0, norm, 1.0)
    unit_re, unit_im = re / safe, im / safe
    strong = norm >= min_amplitude
    inner = (..., slice(1, height - 1), slice(1, width - 1))
    centre_re, centre_im, weak = unit_re[inner], unit_im[inner], ~strong[inner]
    weights = xp.empty((9,) + centre_re.shape)
    for q, (dy, dx) in enumerate(_OFFSETS):
        tap = (..., slice(1 + dy, height - 1 + dy), slice(1 + dx, width - 1 + dx))
        w = weights[q]
        np.multiply(centre_re, unit_re[tap], out=w)          # d = ½ (1 − cos(φ_p − φ_q))
        w += centre_im * unit_im[tap]
        np.subtract(1.0, w, out=w)
        w *= 0.5
        np.copyto(w, 0.0, where=weak)                        # a weak centre: no range term
        w *= -BILATERAL_EXPONENT
        np.exp(w, out=w)
        w *= float(_KERNEL_TAPS[q])
        if q != _CENTRE:  # a neighbour counts only if strong (or the centre is weak); the centre always
            np.copyto(w, 0.0, where=~(strong[tap] | weak))
    total = weights[0].copy()
    for q in range(1, 9):
        total += weights[q]
    weights /= total
    return weights.reshape((3, 3) + weights.shape[1:])


def neighbour_mean(image: np.ndarray, weights: np.ndarray | None) -> np.ndarray:
    """Σ_q w_q x_q over each inner pixel's 3 × 3 neighbours (``weights`` from :func:`bilateral_weights`,
    broadcast against ``image``'s leading axes); the border and images smaller than 3 × 3 unchanged."""
    xp = namespace(image)
    out = xp.asarray(image, dtype=np.float64).copy()
    if weights is None:
        return out
    height, width = out.shape[-2:]
    acc = None  # 18 operations whatever the image, summed in place; no (9, ...) stack of a large image
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            term = weights[1 + dy, 1 + dx] * out[..., 1 + dy:height - 1 + dy, 1 + dx:width - 1 + dx]
            if acc is None:
                acc = term
                acc += 0.0  # as 0.0 + term: a −0.0 term starts the sum at +0.0
            else:
                acc += term
    out[..., 1:-1, 1:-1] = acc
    return out


#: The 3 × 3 neighbourhood as offsets (dy, dx), row-major; index 4 is the pixel itself.
_OFFSETS = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1))
_CENTRE = 4
_KERNEL_TAPS = BILATERAL_KERNEL.reshape(9)


def _phasor_pair(real, imag) -> tuple[np.ndarray, np.ndarray]:
    xp = namespace(real)
    re = xp.asarray(real, dtype=np.float64)
    im = xp.asarray(imag, dtype=np.float64)
    if re.shape != im.shape or re.ndim < 2:
        raise ConfigError(f"bilateral_phasor_filter: real and imag must have one shape (..., H, W), "
                          f"got {re.shape} and {im.shape}")
    return re, im


def check_choice(value: str, choices: tuple[str, ...], where: str, key: str) -> str:
    """``value`` if it is one of ``choices``; else ConfigError naming ``where``, ``key`` and the choices."""
    if value not in choices:
        raise ConfigError(f"{where}: {key} must be one of {list(choices)}, got {value!r}")
    return value
