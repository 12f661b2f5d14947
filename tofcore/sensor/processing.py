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
which reproduces the depth of Microsoft's SDK. The filters that only invalidate pixels
(libfreenect2's ``filterPixelStage2``) are modelled apart, as checks of the decoder that a preset switches
on in its ``[invalid]`` table (:func:`edge_filter`, :data:`BILATERAL_MAX_EDGE`,
:data:`MAX_DEALIAS_CONFIDENCE_RAD`; :mod:`tofcore.sensor.decode`).
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
#: libfreenect2 ``joint_bilateral_max_edge`` = 2.5: a pixel whose neighbours' phase distances (of any one
#: frequency) sum to this or more fails the filter's edge test and gets no depth (``filterPixelStage2``).
BILATERAL_MAX_EDGE = 2.5
#: libfreenect2 ``filterPixelStage2`` (the edge-aware filter) parameters, ``src/depth_packet_processor.cpp``:
#: ``edge_ab_std_dev_threshold`` (relative spread of the 3 × 3 IR sums), ``edge_close_delta_threshold``,
#: ``edge_far_delta_threshold``, ``edge_max_delta_threshold`` (mm of depth, here metres) and
#: ``edge_avg_delta_threshold``.
EDGE_AB_STD_DEV_THRESHOLD = 0.05
EDGE_CLOSE_DELTA_M = 0.050
EDGE_FAR_DELTA_M = 0.030
EDGE_MAX_DELTA_M = 0.100
EDGE_AVG_DELTA_M = 0.0
#: libfreenect2 ``max_dealias_confidence`` = 0.6108653 rad: the largest distance (rad) of the three unwrapped
#: phases from the line on which they agree that ``processPixelStage2`` accepts (its weakest pixels'
#: bound; ``min_dealias_confidence`` = 0.3490659 rad for the strongest).
MAX_DEALIAS_CONFIDENCE_RAD = 0.6108653


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


def bilateral_weights(real: np.ndarray, imag: np.ndarray, *, min_amplitude=0.0, edge_sum: bool = False):
    r"""(3, 3, ..., H − 2, W − 2) normalised weights of :func:`bilateral_phasor_filter` for every inner pixel
    (neighbour offset dy, dx first); None for an image smaller than 3 × 3 (nothing is filtered).

    ``edge_sum``: also return the filter's own edge measure (a pair ``(weights, dist_sum)``):
    :math:`\sum_q d_{pq}` over the neighbours that take part (all eight for a weak centre, the strong ones
    for a strong centre), (..., H, W), 0 on the border — libfreenect2's ``dist_acc`` of
    ``filterPixelStage1``, which its edge-aware filter compares with ``joint_bilateral_max_edge``
    (:data:`BILATERAL_MAX_EDGE`). A pixel in empty space, whose neighbours' phases are random, sums to 4 on
    average (each :math:`d` has mean ½ and variance ⅛ for a random phase difference, so the eight sum to
    4 ± 1); a surface to about 0.

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
        return (None, xp.zeros(re.shape)) if edge_sum else None
    norm = np.hypot(re, im)
    safe = np.where(norm > 0, norm, 1.0)
    unit_re, unit_im = re / safe, im / safe
    strong = norm >= min_amplitude
    inner = (..., slice(1, height - 1), slice(1, width - 1))
    centre_re, centre_im, weak = unit_re[inner], unit_im[inner], ~strong[inner]
    weights = xp.empty((9,) + centre_re.shape)
    dist_sum = xp.zeros(re.shape) if edge_sum else None
    for q, (dy, dx) in enumerate(_OFFSETS):
        tap = (..., slice(1 + dy, height - 1 + dy), slice(1 + dx, width - 1 + dx))
        w = weights[q]
        np.multiply(centre_re, unit_re[tap], out=w)          # d = ½ (1 − cos(φ_p − φ_q))
        w += centre_im * unit_im[tap]
        np.subtract(1.0, w, out=w)
        w *= 0.5
        if edge_sum and q != _CENTRE:  # libfreenect2's dist_acc: the neighbours that take part
            dist_sum[inner] += np.where(strong[tap] | weak, w, 0.0)
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
    weights = weights.reshape((3, 3) + weights.shape[1:])
    return (weights, dist_sum) if edge_sum else weights


def edge_filter(depth: np.ndarray, ir_sum: np.ndarray, neighbour_ok: np.ndarray, *, ir_floor=0.0,
                delta_scale: float = 1.0) -> np.ndarray:
    r"""libfreenect2's edge-aware filter (``filterPixelStage2``): True where it removes a pixel's depth.

    Parameters
    ----------
    depth : (..., H, W) the unwrapped output depth in metres where the pixel passed the amplitude and
        phase tests, NaN (or ≤ 0) where not; the range test comes first (a pixel outside it is not filtered
        here: it is invalid anyway).
    ir_sum : (..., H, W) the sum of the frequencies' (filtered) amplitudes, any unit.
    neighbour_ok : (..., H, W) bool: the pixel passed the bilateral filter's edge test (``dist_sum`` of
        :func:`bilateral_weights` below :data:`BILATERAL_MAX_EDGE` for every frequency); only such
        neighbours' depths count, and a pixel that failed it is removed itself.
    ir_floor : the least mean IR sum the spread is divided by (libfreenect2's ``edge_ab_avg_min_value`` of
        50 ADC counts, here in the unit of ``ir_sum``; 0 where the scale is unknown).
    delta_scale : the depth thresholds times this: the camera's native focal length over the rendered one
        (a quarter-resolution render's neighbours lie 4 native pixels apart, so a slanted surface's depth
        steps between them are 4 × larger; the thresholds hold for the native pixel pitch).

    Notes
    -----
    For an inner pixel p with depth :math:`z_p > 0`, over its 3 × 3 neighbourhood N:
    :math:`s = \operatorname{std}(I_N) / \max(\operatorname{mean}(I_N), I_{floor})`, and
    :math:`z_{min}, z_{max}` over p and the neighbours that have a depth and passed the edge test. The
    pixel is a flying pixel and removed when :math:`s \ge 0.05`, :math:`|z_p - z_{min}| > 50` mm,
    :math:`|z_p - z_{max}| > 30` mm, :math:`\max(\cdot) > 100` mm and their mean > 0 (the constants of
    :data:`EDGE_AB_STD_DEV_THRESHOLD` …). Otherwise a pixel that failed the bilateral edge test is removed
    (libfreenect2: ``*depth_out = !max_edge_test_ok ? 0 : raw_depth``). The border passes unchanged.
    """
    xp = namespace(depth)
    z = xp.asarray(depth, dtype=np.float64)
    has = np.isfinite(z) & (z > 0)
    z = np.where(has, z, 0.0)
    ir = xp.asarray(ir_sum, dtype=np.float64)
    height, width = z.shape[-2:]
    removed = has & ~neighbour_ok
    if height < 3 or width < 3:
        return xp.zeros(z.shape, dtype=bool)
    inner = (..., slice(1, height - 1), slice(1, width - 1))
    zc = z[inner]
    total = xp.zeros(zc.shape)
    total2 = xp.zeros(zc.shape)
    zmin, zmax = zc.copy(), zc.copy()
    usable = has & neighbour_ok
    for dy, dx in _OFFSETS:
        tap = (..., slice(1 + dy, height - 1 + dy), slice(1 + dx, width - 1 + dx))
        total += ir[tap]
        total2 += ir[tap] * ir[tap]
        if (dy, dx) == (0, 0):
            continue
        other = usable[tap]
        zmin = np.where(other, np.minimum(zmin, z[tap]), zmin)
        zmax = np.where(other, np.maximum(zmax, z[tap]), zmax)
    spread = np.sqrt(np.maximum(total2 * 9.0 - total * total, 0.0)) / 9.0
    spread = spread / np.maximum(np.maximum(total / 9.0, ir_floor), 1e-300)
    close, far = np.abs(zc - zmin), np.abs(zc - zmax)
    k = float(delta_scale)
    flying = (has[inner] & (spread >= EDGE_AB_STD_DEV_THRESHOLD) & (close > k * EDGE_CLOSE_DELTA_M)
              & (far > k * EDGE_FAR_DELTA_M) & (np.maximum(close, far) > k * EDGE_MAX_DELTA_M)
              & (0.5 * (close + far) > k * EDGE_AVG_DELTA_M))
    out = xp.zeros(z.shape, dtype=bool)
    out[inner] = flying | removed[inner]
    return out


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
