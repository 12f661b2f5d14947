r"""The camera's decode of a continuous-wave frame, compiled: :func:`tofcore.sensor.decode.decode` of one raw
image stack (R, H, W) as three passes over the pixels, one source for the CPU (numba threads over rows) and
CUDA (a thread per pixel), as :mod:`tofcore.compiled.depth_error` is for the render's error estimate.

The decoder it mirrors is the array program of :mod:`tofcore.sensor.decode` (``decode``, ``decode_cw``,
``filtered_phases``, ``unwrap``, ``_best_wrap``, ``amplitude_noise_e``) and :mod:`tofcore.sensor.processing`
(``bilateral_weights``, ``neighbour_mean``, ``edge_filter``); on a GPU that program is ~270 array operations of
the image's size, here it is three launches:

1. :func:`pixel_phasors`: per frequency i the first DFT bin of the pixel's N_i raw images,
   :math:`Z_i = \sum_k Q_k e^{i\theta_k}`, its phase :math:`\varphi_i = \operatorname{atan2}(\operatorname{Im}Z_i,
   \operatorname{Re}Z_i) \bmod 2\pi`, amplitude :math:`A_i = \frac2{N_i}|Z_i|` (eq. 2.40), offset
   :math:`B_i = \frac1{N_i}\sum_k Q_k` (eq. 2.41) and, for the phasor filter, :math:`A_i e^{i\varphi_i}` with its
   length and unit vector;
2. :func:`pixel_decode`: from those of the pixel and its 3 × 3 neighbours the bilateral phasor filter
   (libfreenect2's, with its edge measure :math:`\sum_q d_{pq}`), the wrapped distances
   :math:`d_i = c\varphi_i / (4\pi f_i)` (eq. 2.34), the amplitude tests, the best wrap under the
   inverse-variance weights :math:`w_i \propto (f_i A_i)^2/(A_i + B_i)` (eq. 2.43) with the unwrap tolerance and
   libfreenect2's dealiasing distance, the range test on distance × range scale, saturation, and the first
   failing reason in :func:`tofcore.sensor.decode.decode`'s order (SATURATED, NO_RETURN, LOW_AMPLITUDE,
   UNWRAPPING_FAILED, OUT_OF_RANGE);
3. :func:`pixel_edge`, where the settings turn the edge-aware filter on: libfreenect2's ``filterPixelStage2``
   over the depths, IR sums and edge tests that pass 2 left for every pixel, EDGE_FILTERED last.

The outputs are :class:`tofcore.sensor.decode.Decoded`'s. They agree with the decoder's to rounding, not bit for
bit: NumPy's DFT sums go through BLAS (whose order and fused multiply-adds depend on the machine) and its
vectorised ``cos``/``sin``/``exp``/``atan2`` may round their last bit differently from the C library's that numba
calls; every other sum runs in the decoder's order. A float32 output can then differ by one ulp where the
float64 value lies on a rounding boundary, and a pixel's reason where a tested value lies within rounding of its
threshold (tests/tofcore/test_camera_decode.py states and tests the tolerance).

What it covers (:func:`unsupported`): continuous-wave modulation (one or more frequencies, any phase steps), the
phasor filters "none" and "bilateral", both unwrap weights and amplitude tests, the dealiasing and edge checks,
saturation, range with range scale; one image (R, H, W). Anything else (a pulsed sensor, a batch of images) is
the decoder's. Renders on a GPU use it (:func:`tofcore.render._camera_decoder` says when); CPU renders keep the
decoder (docs/benchmarks.md, "The camera's decode compiled", says why). The CPU build is how CI, which has no
GPU, checks this source against the decoder; the CUDA simulator checks the kernels' indexing.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from ..constants import SPEED_OF_LIGHT_M_S
from ..errors import ConfigError
from ..sensor import decode as _decode
from ..sensor import processing as _processing
from ._target import cpu_parallel_function, device_function, gpu_kernel_function, gpu_module, load_cuda_build

NO_RETURN = _decode.NO_RETURN_RELATIVE_AMPLITUDE
BILATERAL_TAPS = _processing.BILATERAL_KERNEL.reshape(9).astype(np.float64)
BILATERAL_EXPONENT = float(_processing.BILATERAL_EXPONENT)
BILATERAL_MAX_EDGE = float(_processing.BILATERAL_MAX_EDGE)
EDGE_AB_STD_DEV = float(_processing.EDGE_AB_STD_DEV_THRESHOLD)
EDGE_CLOSE_M, EDGE_FAR_M = float(_processing.EDGE_CLOSE_DELTA_M), float(_processing.EDGE_FAR_DELTA_M)
EDGE_MAX_M, EDGE_AVG_M = float(_processing.EDGE_MAX_DELTA_M), float(_processing.EDGE_AVG_DELTA_M)
TWO_PI = 2.0 * np.pi
SPEED_OF_LIGHT = float(SPEED_OF_LIGHT_M_S)
FOUR_PI_OVER_C = 4.0 * np.pi / SPEED_OF_LIGHT_M_S
VALID, NO_RETURN_CODE, LOW_AMPLITUDE, SATURATED, OUT_OF_RANGE, UNWRAPPING_FAILED, EDGE_FILTERED = (
    int(r) for r in (_decode.Reason.VALID, _decode.Reason.NO_RETURN, _decode.Reason.LOW_AMPLITUDE,
                     _decode.Reason.SATURATED, _decode.Reason.OUT_OF_RANGE, _decode.Reason.UNWRAPPING_FAILED,
                     _decode.Reason.EDGE_FILTERED))
MAX_FREQUENCIES = 8
"""Frequencies a pixel's local arrays hold (their size is needed when compiling)."""
MAX_RAW = 64
"""Raw images per pixel the kernels take."""
# Rows of the frequency table, one per frequency: f (Hz), steps N, first raw image, d_amb = c/(2f) (m), 4π f,
# the output weight f/Σf, the agreement direction f/|f| (decode._agreement_direction).
F_HZ, F_STEPS, F_FIRST, F_AMBIGUITY, F_FOUR_PI_F, F_OUTPUT, F_UNIT = range(7)
# Fields of the phasor table (F, 8, P): A, B, φ, and for the filter A e^{iφ}, its length and unit vector.
T_A, T_B, T_PHASE, T_RE, T_IM, T_NORM, T_URE, T_UIM = range(8)
# The settings vector (float64); NaN switches a comparison off (every comparison with NaN is False).
(S_UNAMBIGUOUS, S_CANDIDATES, S_HIGHEST, S_TOLERANCE, S_BILATERAL, S_FREQUENCY_OUT, S_EVERY, S_DEALIAS,
 S_MIN_AMPLITUDE, S_MIN_SNR, S_READ_NOISE, S_GAIN_NOISE, S_SATURATION, S_RANGE_MIN, S_RANGE_MAX, S_EDGE_FILTER,
 S_EDGE_SCALE) = range(17)
# Rows of the edge table (3, P) that pass 2 leaves for pass 3: the ranged depth where the phases passed
# (NaN where not), the IR sum Σ_i A'_i, 1 where every frequency passed the filter's edge test.
E_DEPTH, E_IR, E_OK = range(3)
# Rows of the scratch array (5, ≥ F) of pass 2.
W_CHOOSE, W_OUT, WRAPPED, NEAREST, TESTED = range(5)
# Rows of the float32 output images (5, P): Decoded's fields in this order.
OUTPUT_IMAGES = ("distance", "amplitude", "offset", "intensity", "confidence")
O_DISTANCE, O_AMPLITUDE, O_OFFSET, O_INTENSITY, O_CONFIDENCE = range(5)

fn = device_function(__name__)
cpu_parallel = cpu_parallel_function(__name__)
gpu_kernel = gpu_kernel_function(__name__)
cuda = gpu_module(__name__)


@fn
def round_half_even(x):
    """np.round of a float: the nearest integer, ties to even."""
    r = math.floor(x)
    d = x - r
    if d > 0.5 or (d == 0.5 and r % 2.0 != 0.0):
        return r + 1.0
    return r


@fn
def phase_of(re, im):
    """atan2(im, re) in [0, 2π) (decode.phase_amplitude_offset: np.mod, then 0 where it rounds up to 2π)."""
    phase = math.atan2(im, re) % TWO_PI
    return phase if phase < TWO_PI else 0.0


@fn
def pixel_phasors(raw, channels, freqs, bilateral, p, table):
    """Pass 1 for pixel p: per frequency A, B and φ of its raw images (decode.decode_cw) into ``table``
    (F, 8, P), and where ``bilateral`` the phasor A e^{iφ} the filter reads (decode.filtered_phases rebuilds it
    from A and φ), its length |A e^{iφ}| and unit vector (0 for length 0; processing.bilateral_weights).

    ``raw`` (J, P) electrons; ``channels`` (J, 2): cos θ_k, sin θ_k of each raw image's step (rounded to 15
    digits, as the decoder rounds them); ``freqs`` the frequency table (F_* columns)."""
    for i in range(freqs.shape[0]):
        first, steps = np.int64(freqs[i, F_FIRST]), np.int64(freqs[i, F_STEPS])
        re, im, total = 0.0, 0.0, 0.0
        for k in range(steps):
            q = raw[first + k, p]
            re += channels[first + k, 0] * q
            im += channels[first + k, 1] * q
            total += q
        amplitude = 2.0 / steps * math.hypot(re, im)
        phase = phase_of(re, im)
        table[i, T_A, p] = amplitude
        table[i, T_B, p] = total / steps
        table[i, T_PHASE, p] = phase
        if bilateral:
            c_re, c_im = amplitude * math.cos(phase), amplitude * math.sin(phase)
            norm = math.hypot(c_re, c_im)
            safe = norm if norm > 0 else 1.0
            table[i, T_RE, p] = c_re
            table[i, T_IM, p] = c_im
            table[i, T_NORM, p] = norm
            table[i, T_URE, p] = c_re / safe
            table[i, T_UIM, p] = c_im / safe


@fn
def filtered_phasor(table, i, p, rows, x, min_amplitude, weights):
    r"""(Re, Im, Σd) of frequency i's phasor at the inner pixel p = rows[1] + x after libfreenect2's joint
    bilateral filter (processing.bilateral_weights, neighbour_mean), and its edge measure.

    .. math:: Z'_p = \frac{\sum_q k_q e^{-b d_{pq}} Z_q}{\sum_q k_q e^{-b d_{pq}}}, \qquad
              d_{pq} = \tfrac12 (1 - u_p \cdot u_q)

    over the 3 × 3 neighbours q (taps 0–8 row-major, 4 the pixel; ``rows`` the table columns of x = 0 in the
    rows above, at and below), with no range term for a weak centre (|Z_p| < ``min_amplitude``) and no weight for
    a weak neighbour of a strong one; Σd sums d_pq over the neighbours that take part (libfreenect2's
    ``dist_acc``). ``weights`` (9,) scratch. The sums run in the decoder's order."""
    weak = not table[i, T_NORM, p] >= min_amplitude
    c_re, c_im = table[i, T_URE, p], table[i, T_UIM, p]
    dist_sum, total = 0.0, 0.0
    for tap in range(9):
        q = rows[tap // 3] + x + tap % 3 - 1
        d = c_re * table[i, T_URE, q]
        d = d + c_im * table[i, T_UIM, q]
        d = (1.0 - d) * 0.5
        takes_part = table[i, T_NORM, q] >= min_amplitude or weak
        if tap != 4 and takes_part:
            dist_sum += d
        if weak:
            d = 0.0
        w = math.exp(d * -BILATERAL_EXPONENT) * BILATERAL_TAPS[tap]
        if tap != 4 and not takes_part:
            w = 0.0
        weights[tap] = w
        total += w
    re, im = 0.0, 0.0
    for tap in range(9):
        q = rows[tap // 3] + x + tap % 3 - 1
        w = weights[tap] / total
        re += w * table[i, T_RE, q]
        im += w * table[i, T_IM, q]
    return re, im, dist_sum


@fn
def best_wrap(scratch, freqs, n_candidates, h, frequency_out):
    """(r², D̄, n) of decode._best_wrap for the wrapped distances ``scratch[WRAPPED]`` (F,): the first of the
    candidates D = d_h + n d_amb,h with the least spread r² = Σ w_i (D_i − D̄)² of the frequencies' nearest wraps
    D_i = d_i + round((D − d_i)/d_amb,i) d_amb,i under the weights ``scratch[W_CHOOSE]``; D̄ averaged with
    ``scratch[W_OUT]`` where ``frequency_out``, else with the same weights. ``scratch[NEAREST]`` is left holding
    the D_i of the last candidate."""
    wrapped, w_choose, w_out, nearest = scratch[WRAPPED], scratch[W_CHOOSE], scratch[W_OUT], scratch[NEAREST]
    best_r2, best_d, best_n = math.inf, 0.0, 0
    for n in range(n_candidates):
        candidate = wrapped[h] + n * freqs[h, F_AMBIGUITY]
        mean = 0.0
        for i in range(freqs.shape[0]):
            amb = freqs[i, F_AMBIGUITY]
            nearest[i] = wrapped[i] + round_half_even((candidate - wrapped[i]) / amb) * amb
            mean += w_choose[i] * nearest[i]
        r2, out = 0.0, 0.0
        for i in range(freqs.shape[0]):
            r2 += w_choose[i] * (nearest[i] - mean) ** 2
            out += w_out[i] * nearest[i]
        if r2 < best_r2:
            best_r2, best_d, best_n = r2, (out if frequency_out else mean), n
    return best_r2, best_d, best_n


@fn
def dealias_rad(scratch, freqs, n, h):
    r"""decode.dealias_distance_rad at wrap n of the highest frequency: the unwrapped phases
    :math:`\Phi_i = 4\pi f_i D_i / c` (as :math:`D_i \frac{4\pi}{c} / (2 d_{amb,i})\, c`, the decoder's order)
    and their distance from the line of agreement, :math:`\sqrt{|\Phi|^2 - (\Phi\cdot u)^2}`, u = f/|f|."""
    wrapped = scratch[WRAPPED]
    candidate = wrapped[h] + n * freqs[h, F_AMBIGUITY]
    along, length2 = 0.0, 0.0
    for i in range(freqs.shape[0]):
        amb = freqs[i, F_AMBIGUITY]
        unwrapped = wrapped[i] + round_half_even((candidate - wrapped[i]) / amb) * amb
        phi = unwrapped * FOUR_PI_OVER_C / (2.0 * amb) * SPEED_OF_LIGHT
        along += phi * freqs[i, F_UNIT]
        length2 += phi * phi
    return math.sqrt(max(length2 - along * along, 0.0))


@fn
def amplitude_floor(offset, steps, settings):
    """min_amplitude_snr · σ_A of a pixel with offset B (decode.amplitude_noise_e:
    σ_A = √(2/N (B + σ_read² + (β B)²)), B clipped at 0)."""
    b = max(offset, 0.0)
    read, gain = settings[S_READ_NOISE], settings[S_GAIN_NOISE]
    return settings[S_MIN_SNR] * math.sqrt(2.0 / steps * (b + read ** 2 + (gain * b) ** 2))


@fn
def pixel_decode(raw, table, freqs, settings, range_scale, y, x, width, height, rows, scratch, weights, edge,
                 images, reason_out, valid_out):
    """Pass 2 for pixel (y, x): decode.decode of its phasors and its neighbours', into column p of ``images``
    (5, P) float32 (the O_* rows: distance, amplitude, offset, intensity, confidence), ``reason_out`` (P,) uint8 and
    ``valid_out`` (P,) bool, and where the edge filter is on into the pixel's column of ``edge`` (E_* rows) for
    pass 3.

    ``settings`` the S_* vector; ``range_scale`` (P,) what multiplies the distance in the range test;
    ``rows`` the table columns of x = 0 in the rows above, at and below y; ``scratch`` (5, ≥ F) and ``weights``
    (9,) scratch."""
    n_freq = freqs.shape[0]
    p = rows[1] + x
    h = np.int64(settings[S_HIGHEST])
    bilateral = settings[S_BILATERAL] != 0.0
    inner = bilateral and 0 < y < height - 1 and 0 < x < width - 1
    min_amplitude = settings[S_MIN_AMPLITUDE]
    # the wrapped distances (after the filter) and the amplitudes the thresholds read
    wrapped, tested = scratch[WRAPPED], scratch[TESTED]
    edge_ok = True
    for i in range(n_freq):
        if not bilateral:
            phase, tested[i] = table[i, T_PHASE, p], table[i, T_A, p]
        else:
            re, im, dist_sum = table[i, T_RE, p], table[i, T_IM, p], 0.0  # the border passes unfiltered
            if inner:
                re, im, dist_sum = filtered_phasor(table, i, p, rows, x, min_amplitude, weights)
            phase, tested[i] = phase_of(re, im), math.hypot(re, im)
            edge_ok = edge_ok and dist_sum < BILATERAL_MAX_EDGE
        wrapped[i] = SPEED_OF_LIGHT * phase / freqs[i, F_FOUR_PI_F]
    # unwrapping weights (decode.unwrap_weights): inverse variance from the pixel's own A and B
    w_choose, w_out = scratch[W_CHOOSE], scratch[W_OUT]
    total = 0.0
    for i in range(n_freq):
        a, b = table[i, T_A, p], table[i, T_B, p]
        w = (freqs[i, F_HZ] * a) ** 2 / (a + b) if a + b > 0 else 0.0
        w_choose[i] = w
        total += w
    for i in range(n_freq):
        w_choose[i] = w_choose[i] / total if total > 0 else 1.0 / n_freq
        w_out[i] = freqs[i, F_OUTPUT] if settings[S_FREQUENCY_OUT] != 0.0 else w_choose[i]
    best_r2, best_d, best_n = best_wrap(scratch, freqs, np.int64(settings[S_CANDIDATES]), h,
                                        settings[S_FREQUENCY_OUT] != 0.0)
    residual = math.sqrt(best_r2)
    tolerance = settings[S_TOLERANCE]
    distance = best_d % settings[S_UNAMBIGUOUS]
    confidence = min(max(1.0 - residual / tolerance, 0.0), 1.0)
    unwrap_failed = residual > tolerance or dealias_rad(scratch, freqs, best_n, h) > settings[S_DEALIAS]
    # the tests, in decode's precedence
    no_return, low_amplitude = False, False
    for i in range(n_freq):
        a, b = table[i, T_A, p], table[i, T_B, p]
        no_return = no_return or a <= NO_RETURN * b
        if settings[S_EVERY] != 0.0 or i == h:
            floor = amplitude_floor(b, freqs[i, F_STEPS], settings)
            low_amplitude = low_amplitude or tested[i] < min_amplitude or tested[i] < floor
    saturated, raw_sum = False, 0.0
    for j in range(raw.shape[0]):
        saturated = saturated or raw[j, p] >= settings[S_SATURATION]
        raw_sum += raw[j, p]
    ranged = distance * range_scale[p]
    out_of_range = not (ranged >= settings[S_RANGE_MIN] and ranged <= settings[S_RANGE_MAX])
    reason = VALID
    if saturated:
        reason = SATURATED
    elif no_return:
        reason = NO_RETURN_CODE
    elif low_amplitude:
        reason = LOW_AMPLITUDE
    elif unwrap_failed:
        reason = UNWRAPPING_FAILED
    elif out_of_range:
        reason = OUT_OF_RANGE
    if settings[S_EDGE_FILTER] != 0.0:  # the phases passed: the pixel's depth is evidence for its neighbours
        phase_ok = not (saturated or no_return or low_amplitude or unwrap_failed)
        ir_sum = 0.0
        for i in range(n_freq):
            ir_sum += tested[i]
        edge[E_DEPTH, p] = ranged if phase_ok else math.nan
        edge[E_IR, p] = ir_sum
        edge[E_OK, p] = 1.0 if edge_ok else 0.0
    valid = reason == VALID
    images[O_DISTANCE, p] = distance if valid else math.nan
    images[O_AMPLITUDE, p] = table[h, T_A, p]
    images[O_OFFSET, p] = table[h, T_B, p]
    images[O_INTENSITY, p] = raw_sum / raw.shape[0]
    images[O_CONFIDENCE, p] = confidence if valid else 0.0
    reason_out[p] = reason
    valid_out[p] = valid


@fn
def pixel_edge(edge, settings, y, x, width, height):
    r"""Pass 3 for pixel (y, x): whether libfreenect2's edge-aware filter removes it
    (processing.edge_filter over pass 2's ``edge`` table; the border never).

    With :math:`z` the pixel's depth (0 where it has none), :math:`I` the IR sums of its 3 × 3 neighbourhood N,
    :math:`s = \sqrt{\max(9\sum I^2 - (\sum I)^2, 0)}/9 \,/\, \max(\bar I, 10^{-300})` and :math:`z_{min},
    z_{max}` over the pixel and the neighbours that have a depth and passed the edge test: removed where
    :math:`s \ge 0.05`, :math:`|z - z_{min}| > 50` mm, :math:`|z - z_{max}| > 30` mm, the larger > 100 mm and
    their mean > 0 (each threshold × the edge delta scale), or where the pixel has a depth and failed the
    bilateral filter's edge test itself."""
    if not (0 < y < height - 1 and 0 < x < width - 1):
        return False
    p = y * width + x
    z = edge[E_DEPTH, p]
    has = math.isfinite(z) and z > 0
    zc = z if has else 0.0
    total, total2 = 0.0, 0.0
    z_min, z_max = zc, zc
    for tap in range(9):
        q = (y + tap // 3 - 1) * width + x + tap % 3 - 1
        ir = edge[E_IR, q]
        total += ir
        total2 += ir * ir
        if tap == 4:
            continue
        zq = edge[E_DEPTH, q]
        if math.isfinite(zq) and zq > 0 and edge[E_OK, q] != 0.0:
            z_min, z_max = min(z_min, zq), max(z_max, zq)
    spread = math.sqrt(max(total2 * 9.0 - total * total, 0.0)) / 9.0
    spread = spread / max(max(total / 9.0, 0.0), 1e-300)
    close, far = abs(zc - z_min), abs(zc - z_max)
    k = settings[S_EDGE_SCALE]
    flying = (has and spread >= EDGE_AB_STD_DEV and close > k * EDGE_CLOSE_M and far > k * EDGE_FAR_M
              and max(close, far) > k * EDGE_MAX_M and 0.5 * (close + far) > k * EDGE_AVG_M)
    return flying or (has and edge[E_OK, p] == 0.0)


@fn
def remove_edge_pixel(edge, settings, y, x, width, height, images, reason_out, valid_out):
    """Pass 3's result for pixel (y, x): a pixel valid after pass 2 that :func:`pixel_edge` removes becomes
    EDGE_FILTERED (the last reason: any other one wins)."""
    p = y * width + x
    if reason_out[p] == VALID and pixel_edge(edge, settings, y, x, width, height):
        images[O_DISTANCE, p] = math.nan
        images[O_CONFIDENCE, p] = 0.0
        reason_out[p] = EDGE_FILTERED
        valid_out[p] = False


@fn
def decode_row(raw, table, freqs, settings, range_scale, y, width, height, scratch, weights, edge, images, reason,
               valid):
    """Pass 2 for row y (the CPU driver's unit of work)."""
    rows = ((y - 1) * width, y * width, (y + 1) * width)
    for x in range(width):
        pixel_decode(raw, table, freqs, settings, range_scale, y, x, width, height, rows, scratch, weights, edge,
                     images, reason, valid)


@cpu_parallel
def decode_rows(raw, channels, freqs, settings, range_scale, width, table, edge, images, reason, valid):
    """The three passes over every row on numba's threads (the CPU build; CI's check of the kernels' source).
    (Each loop's body is one call: numba's parallel loops compile slowly when they inline large bodies.)"""
    pixels = raw.shape[1]
    height = pixels // width
    bilateral = settings[S_BILATERAL] != 0.0
    for p in prange(pixels):
        pixel_phasors(raw, channels, freqs, bilateral, p, table)
    for y in prange(height):
        decode_row(raw, table, freqs, settings, range_scale, y, width, height, np.empty((5, freqs.shape[0])),
                   np.empty(9), edge, images, reason, valid)
    if settings[S_EDGE_FILTER] != 0.0:
        for p in prange(pixels):
            remove_edge_pixel(edge, settings, p // width, p % width, width, height, images, reason, valid)


@gpu_kernel
def phasors_kernel(raw, channels, freqs, settings, table):
    """Pass 1 on the GPU, a thread per pixel."""
    p = cuda.grid(1)
    if p < raw.shape[1]:
        pixel_phasors(raw, channels, freqs, settings[S_BILATERAL] != 0.0, p, table)


@gpu_kernel
def decode_kernel(raw, table, freqs, settings, range_scale, width, edge, images, reason, valid):
    """Pass 2 on the GPU, a thread per pixel."""
    p = cuda.grid(1)
    if p < raw.shape[1]:
        scratch = cuda.local.array((5, MAX_FREQUENCIES), np.float64)
        weights = cuda.local.array(9, np.float64)
        y = p // width
        pixel_decode(raw, table, freqs, settings, range_scale, y, p % width, width, raw.shape[1] // width,
                     ((y - 1) * width, y * width, (y + 1) * width), scratch, weights, edge, images, reason, valid)


@gpu_kernel
def edge_kernel(edge, settings, width, images, reason, valid):
    """Pass 3 on the GPU, a thread per pixel."""
    p = cuda.grid(1)
    if p < edge.shape[1]:
        remove_edge_pixel(edge, settings, p // width, p % width, width, edge.shape[1] // width, images, reason,
                          valid)


# ------------------------------------------------------------------ host side: the tables and the launches
def unsupported(modulation, settings, shape: tuple[int, ...]) -> str:
    """Why these kernels cannot decode raw images of image ``shape`` (the raw stack's shape without its first
    axis) for ``modulation`` and :class:`~tofcore.sensor.decode.DecodeSettings` ``settings`` ("" where they can).
    The decoder then does, raising its own errors where it must (e.g. too many wrap candidates)."""
    if not modulation.is_cw:
        return "a pulsed sensor (two buckets and no filter: the decoder's array program is short)"
    if len(modulation.frequencies_hz) > MAX_FREQUENCIES:
        return f"more than {MAX_FREQUENCIES} frequencies"
    if modulation.raw_count > MAX_RAW:
        return f"more than {MAX_RAW} raw images"
    if len(shape) != 2:
        return f"raw images of shape {tuple(shape)}, not one (H, W) image"
    if settings.phasor_filter not in ("none", "bilateral"):
        return f"phasor filter {settings.phasor_filter!r}"
    if wrap_candidates(modulation) > _decode.MAX_UNWRAP_CANDIDATES:
        return f"{wrap_candidates(modulation)} wrap candidates, more than {_decode.MAX_UNWRAP_CANDIDATES}"
    if settings.range_scale is not None and np.broadcast_shapes(np.shape(settings.range_scale), shape) != shape:
        return f"range_scale of shape {np.shape(settings.range_scale)} for images {tuple(shape)}"
    return ""


def wrap_candidates(modulation) -> int:
    """N, the wraps of the highest frequency in the unambiguous range (decode.unwrap's candidates)."""
    d_amb = modulation.ambiguity_distances_m()
    h = int(np.argmax(modulation.frequencies_hz))
    return max(1, math.ceil(modulation.unambiguous_range_m() / d_amb[h] - 1e-9))


def tables(modulation, settings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(channels (J, 2), frequency table (F, 7), settings vector (17,)) of the passes for ``modulation`` and
    ``settings`` (float64; NaN where a test is off)."""
    f_hz = np.asarray(modulation.frequencies_hz, dtype=np.float64)
    d_amb = modulation.ambiguity_distances_m()
    channels = np.zeros((modulation.raw_count, 2))
    freqs = np.zeros((len(f_hz), 7))
    first = 0
    for i, steps in enumerate(modulation.phase_steps):
        theta = 2.0 * np.pi * np.arange(steps) / steps
        channels[first:first + steps] = np.stack([np.round(np.cos(theta), 15), np.round(np.sin(theta), 15)], axis=1)
        freqs[i] = (f_hz[i], steps, first, d_amb[i], 4.0 * np.pi * f_hz[i], f_hz[i] / f_hz.sum(),
                    f_hz[i] / np.linalg.norm(f_hz))
        first += steps
    s = settings
    tolerance = _decode.default_unwrap_tolerance_m(modulation) if s.unwrap_tolerance_m is None \
        else float(s.unwrap_tolerance_m)
    off = math.nan
    vector = np.array([
        modulation.unambiguous_range_m(), wrap_candidates(modulation), int(np.argmax(f_hz)), tolerance,
        s.phasor_filter == "bilateral", s.unwrap_weights == "frequency", s.amplitude_test == "every",
        off if s.dealias_tolerance_rad is None else s.dealias_tolerance_rad, s.min_amplitude_e, s.min_amplitude_snr,
        s.read_noise_e, s.gain_noise, off if s.saturation_e is None else s.saturation_e, s.range_m[0], s.range_m[1],
        s.edge_filter and s.phasor_filter == "bilateral", s.edge_delta_scale], np.float64)
    return channels, freqs, vector


def cuda_build():
    """This file compiled by numba.cuda (loaded once per process)."""
    return load_cuda_build(__name__, __file__)


THREADS_PER_BLOCK = 128


def launch_cuda(build, raw, host_tables, range_scale, width: int, images, reason, valid, xp) -> None:
    """The three kernels of ``build`` over ``raw`` (J, P) into ``images``, ``reason``, ``valid`` (as
    :func:`pixel_decode` writes them):
    ``host_tables`` those of :func:`tables` (uploaded here; read on the host first, so no launch waits for a
    device value), the pixels' tables allocated with the array module ``xp`` (CuPy; NumPy under numba's CUDA
    simulator)."""
    edge_on = host_tables[2][S_EDGE_FILTER] != 0.0
    channels, freqs, vector = (xp.asarray(a) for a in host_tables)
    pixels = raw.shape[1]
    table = xp.empty((freqs.shape[0], 8, pixels))  # every pixel's phasors, read by its neighbours
    edge = xp.empty((3, pixels if edge_on else 1))
    blocks = (pixels + THREADS_PER_BLOCK - 1) // THREADS_PER_BLOCK
    build.phasors_kernel[blocks, THREADS_PER_BLOCK](raw, channels, freqs, vector, table)
    build.decode_kernel[blocks, THREADS_PER_BLOCK](raw, table, freqs, vector, range_scale, width, edge, images,
                                                   reason, valid)
    if edge_on:
        build.edge_kernel[blocks, THREADS_PER_BLOCK](edge, vector, width, images, reason, valid)


def decode(raw, modulation, settings=None, *, check: bool = True) -> _decode.Decoded:
    """:func:`tofcore.sensor.decode.decode` of one raw image stack ``raw`` (R, H, W) by the three passes, on the
    array's device: numba's threads on the CPU, three CUDA kernels on a GPU. Same arguments, checks and result
    (to rounding: the module docstring); a decode that :func:`unsupported` refuses is a ConfigError naming why."""
    from ..backend import namespace

    s = _decode.DecodeSettings() if settings is None else settings
    if not isinstance(s, _decode.DecodeSettings):
        raise ConfigError(f"decode: settings must be a DecodeSettings, got {type(s).__name__}")
    raw = _decode.check_raw(raw, modulation, finite=check)
    why = unsupported(modulation, s, raw.shape[1:])
    if why:
        raise ConfigError(f"camera_decode: cannot decode {why}; tofcore.sensor.decode.decode does")
    xp = namespace(raw)
    height, width = raw.shape[1:]
    pixels = height * width
    host_tables = tables(modulation, s)
    flat = xp.ascontiguousarray(raw.reshape(raw.shape[0], pixels))
    scale = xp.ones(pixels) if s.range_scale is None else xp.ascontiguousarray(
        xp.broadcast_to(xp.asarray(s.range_scale, dtype=np.float64), (height, width))).reshape(pixels)
    images = xp.empty((len(OUTPUT_IMAGES), pixels), dtype=np.float32)
    reason, valid = xp.empty(pixels, dtype=np.uint8), xp.empty(pixels, dtype=np.bool_)
    if xp is np:
        from .cpu import PARALLEL_LOCK

        channels, freqs, vector = host_tables
        edge = np.empty((3, pixels if vector[S_EDGE_FILTER] != 0.0 else 1))
        with PARALLEL_LOCK:
            decode_rows(flat, channels, freqs, vector, scale, width, np.empty((freqs.shape[0], 8, pixels)), edge,
                        images, reason, valid)
    else:
        launch_cuda(cuda_build(), flat, host_tables, scale, width, images, reason, valid, xp)
    images = images.reshape(len(OUTPUT_IMAGES), height, width)
    return _decode.Decoded(**dict(zip(OUTPUT_IMAGES, images)), valid=valid.reshape(height, width),
                           reason=reason.reshape(height, width))
