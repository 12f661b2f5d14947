r"""The render's depth-error estimate per pixel, compiled: σ and the unwrap flips of
:func:`tofcore.render.render_error` for continuous-wave sensors, one source for the CPU (numba threads over
rows) and CUDA (a thread per pixel), as :mod:`tofcore.compiled.kernels` is for the tracer; and the frame's
per-k ground truth (:func:`clean_distances`: render._decode_clean_per_k, the same decoding and unwrapping
without the camera's thresholds and filter).

The NumPy functions it mirrors, and the formulas, are those of :mod:`tofcore.render` (``_standard_error``,
``_filtered_deviation``, ``_flips``) and :mod:`tofcore.sensor.decode` (``phase_amplitude_offset``,
``unwrap_weights``, ``distance_gradient``, ``filtered_phases``, ``unwrap``); the array program makes ~400
temporaries of the image's size per pass (on a GPU as many launches), this makes two passes over the pixels:

1. :func:`pixel_phasors`: each replicate's raw images :math:`Q^{(r)}_j = s_j(\bar c^{(r)}_j + L^{(r)} \delta_j)`
   (:func:`tofcore.sensor.raw.raw_images`) and their mean :math:`\bar Q`, per frequency the first DFT bin
   :math:`Z = \sum_k Q_k e^{i\theta_k}`, its length, unit vector and the offset :math:`B = \frac1N\sum_k Q_k`;
2. :func:`pixel_error`: from those of the pixel and its 3 × 3 neighbours, the linearised standard error
   through the camera's phasor filter and unwrapping (σ, with the wrap tails), and whether the replicates,
   each decoded, filtered and unwrapped, spread by more than the flip threshold.

The compiled estimate agrees with the NumPy one to rounding, not bit for bit: NumPy's DFT sums go through
BLAS (whose order and fused multiply-adds depend on the machine), the flips' filter takes the replicate's
phasor as :math:`\frac2N Z` where NumPy rebuilds it as :math:`A\cos\varphi, A\sin\varphi`, and NumPy's
vectorised ``exp``/``atan2`` round their last bit differently from libm (tests/tofcore/test_depth_error.py
states the tolerance).

Renders on a GPU use both (:func:`tofcore.render.render_error` says when); CPU renders keep the array programs,
whose cost there is ~1 % of a frame, against 11 s more of numba's one-time compile. The CPU build is how CI,
which has no GPU, checks this source against the NumPy estimate; the CUDA simulator checks the kernels'
indexing (tests/tofcore/test_depth_error.py).
"""

from __future__ import annotations

import math

import numpy as np

from ..constants import SPEED_OF_LIGHT_M_S
from ..sensor import decode as _decode
from ..sensor import processing as _processing
from numba import prange

from ._target import cpu_parallel_function, device_function, gpu_kernel_function, gpu_module, load_cuda_build

NO_RETURN = _decode.NO_RETURN_RELATIVE_AMPLITUDE
BILATERAL_TAPS = _processing.BILATERAL_KERNEL.reshape(9).astype(np.float64)
BILATERAL_EXPONENT = float(_processing.BILATERAL_EXPONENT)
TWO_PI = 2.0 * np.pi
SPEED_OF_LIGHT = float(SPEED_OF_LIGHT_M_S)
TAIL_P, TAIL_A1, TAIL_A2, TAIL_A3, TAIL_A4, TAIL_A5 = (0.3275911, 0.254829592, -0.284496736, 1.421413741,
                                                      -1.453152027, 1.061405429)
SQRT2 = float(np.sqrt(2.0))
MAX_FREQUENCIES = 8
"""Frequencies a pixel's arrays hold (local arrays need their size when compiling)."""
MAX_REPLICATES = 16
MAX_RAW = 64
"""Raw images a pixel's arrays hold."""
# Rows of the frequency table (one row per frequency): f, steps N, first raw channel, d_amb, c / (4π f),
# the phasor filter's threshold on |Z| (min_amplitude_e · N / 2), the output weight f / Σf.
F_HZ, F_STEPS, F_FIRST, F_AMBIGUITY, F_METRES_PER_RAD, F_STRONG_Z, F_OUTPUT = range(7)
# Fields of the pixel phasor table (S = R + 1 sets of phasors per pixel: the replicates, then their mean):
Z_RE, Z_IM, Z_NORM, U_RE, U_IM, OFFSET = range(6)

fn = device_function(__name__)
cpu_parallel = cpu_parallel_function(__name__)
gpu_kernel = gpu_kernel_function(__name__)
cuda = gpu_module(__name__)


@fn
def finite_or_zero(x):
    """x, or 0 where x is NaN or infinite (np.nan_to_num's zero for NaN; an infinite raw image cannot occur:
    a replicate's mean is a finite sum over a count ≥ 1, or 0/0)."""
    if math.isnan(x) or math.isinf(x):
        return 0.0
    return x


@fn
def round_half_even(x):
    """np.round of a float: the nearest integer, ties to even."""
    r = math.floor(x)
    d = x - r
    if d > 0.5 or (d == 0.5 and r % 2.0 != 0.0):
        return r + 1.0
    return r


@fn
def normal_tail(x):
    """P(Z > x) for a standard normal Z (render._normal_tail: Abramowitz & Stegun 7.1.26)."""
    z = abs(x) / SQRT2
    t = 1.0 / (1.0 + TAIL_P * z)
    poly = t * (TAIL_A1 + t * (TAIL_A2 + t * (TAIL_A3 + t * (TAIL_A4 + t * TAIL_A5))))
    upper = 0.5 * poly * math.exp(-z * z)
    return upper if x >= 0 else 1.0 - upper


@fn
def store_phasor(table, s, i, p, re, im, offset):
    """Phasor set s, frequency i of pixel p: Z, |Z|, Z/|Z| (0 for |Z| = 0) and the offset B."""
    norm = math.hypot(re, im)
    safe = norm if norm > 0 else 1.0
    table[s, i, Z_RE, p] = re
    table[s, i, Z_IM, p] = im
    table[s, i, Z_NORM, p] = norm
    table[s, i, U_RE, p] = re / safe
    table[s, i, U_IM, p] = im / safe
    table[s, i, OFFSET, p] = offset


@fn
def pixel_phasors(replicate_sum, counts, channels, freqs, p, table, t):
    """Stage 1 for pixel p, into column t of ``table``: the phasors of each replicate (NaN where it has no
    sample; its unit vector and length as np.nan_to_num's zero image would give them) and of their mean
    (nan_to_num'd, as render does).

    ``replicate_sum`` (R, J + 2, P) and ``counts`` (R, P) as :meth:`Transport.replicate_means` reads them,
    ``channels`` (J, 4): scale s_j = responsivity × exposure, gate duty δ_j, cos θ_k, sin θ_k (rounded to
    15 digits as the decoder rounds them); ``freqs`` the frequency table (F_* columns); ``table``
    (R + 1, F, 6, P)."""
    n_rep = counts.shape[0]
    ambient_row = replicate_sum.shape[1] - 1
    for i in range(freqs.shape[0]):
        first, steps = np.int64(freqs[i, F_FIRST]), np.int64(freqs[i, F_STEPS])
        c_re, c_im, c_sum = 0.0, 0.0, 0.0
        for k in range(steps):
            j = first + k
            scale, duty, cos_k, sin_k = channels[j, 0], channels[j, 1], channels[j, 2], channels[j, 3]
            mean_q = 0.0
            for r in range(n_rep):
                n = counts[r, p]
                q = scale * (replicate_sum[r, 1 + j, p] / n + replicate_sum[r, ambient_row, p] / n * duty)
                mean_q += q
            mean_q = finite_or_zero(mean_q / n_rep)
            c_re += cos_k * mean_q
            c_im += sin_k * mean_q
            c_sum += mean_q
        store_phasor(table, n_rep, i, t, c_re, c_im, c_sum / steps)
        for r in range(n_rep):
            n = counts[r, p]
            re, im, total = 0.0, 0.0, 0.0
            for k in range(steps):
                j = first + k
                q = channels[j, 0] * (replicate_sum[r, 1 + j, p] / n + replicate_sum[r, ambient_row, p] / n
                                      * channels[j, 1])
                re += channels[j, 2] * q
                im += channels[j, 3] * q
                total += q
            # the DFT of the replicate itself (NaN without samples): σ's deviations δZ = Z − Z̄
            table[r, i, Z_RE, t] = re
            table[r, i, Z_IM, t] = im
            table[r, i, OFFSET, t] = total / steps
            fixed_re, fixed_im = finite_or_zero(re), finite_or_zero(im)
            norm = math.hypot(fixed_re, fixed_im)
            safe = norm if norm > 0 else 1.0
            table[r, i, Z_NORM, t] = norm
            table[r, i, U_RE, t] = fixed_re / safe
            table[r, i, U_IM, t] = fixed_im / safe


@fn
def filter_weight(table, s, i, p, q, tap, strong_threshold):
    """The bilateral phasor filter's weight of neighbour q (tap index 0–8, 4 the pixel) of pixel p for
    phasor set s, frequency i, before normalisation (processing.bilateral_weights):
    k_q exp(−b ½(1 − u_p·u_q)); no range term for a weak centre, 0 for a weak neighbour of a strong one."""
    weak_centre = not table[s, i, Z_NORM, p] >= strong_threshold
    d = 0.0 if weak_centre else 0.5 * (1.0 - (table[s, i, U_RE, p] * table[s, i, U_RE, q]
                                              + table[s, i, U_IM, p] * table[s, i, U_IM, q]))
    w = math.exp(d * -BILATERAL_EXPONENT) * BILATERAL_TAPS[tap]
    if tap != 4 and not (table[s, i, Z_NORM, q] >= strong_threshold or weak_centre):
        return 0.0
    return w


@fn
def unwrap_weight_sum(table, s, i_count, freqs, p, scheme_frequency, out_w):
    """The unwrapping weights of phasor set s at pixel p into ``out_w`` (decode.unwrap_weights): inverse
    variance (f A)² / (A + B), equal where no frequency has signal, or (``scheme_frequency``) f / Σf."""
    total = 0.0
    for i in range(i_count):
        if scheme_frequency:
            out_w[i] = freqs[i, F_OUTPUT]
            continue
        steps = freqs[i, F_STEPS]
        a = 2.0 / steps * finite_or_zero(table[s, i, Z_NORM, p])
        b = finite_or_zero(table[s, i, OFFSET, p])
        w = (freqs[i, F_HZ] * a) ** 2 / (a + b) if a + b > 0 else 0.0
        out_w[i] = w
        total += w
    if scheme_frequency:
        return
    for i in range(i_count):
        out_w[i] = out_w[i] / total if total > 0 else 1.0 / i_count


@fn
def unwrap_best(wrapped, w_choose, w_out, freqs, n_candidates, h, frequency_out, nearest):
    """(r², D̄) of decode.unwrap's best wrap candidate for the wrapped distances ``wrapped`` (F,): the first of the
    candidates D = d_h + n d_amb,h with the least spread r² of the frequencies' nearest wraps under the
    inverse-variance weights ``w_choose``, its distance averaged with ``w_out`` where ``frequency_out`` (the
    camera's f/Σf), else with ``w_choose``; ``nearest`` (F,) scratch. Not yet reduced modulo the range."""
    best_r2, best_d = math.inf, 0.0
    d_h, amb_h = wrapped[h], freqs[h, F_AMBIGUITY]
    for n in range(n_candidates):
        candidate = d_h + n * amb_h
        mean = 0.0
        for i in range(freqs.shape[0]):  # every frequency's nearest wrap to the candidate
            amb = freqs[i, F_AMBIGUITY]
            nearest[i] = wrapped[i] + round_half_even((candidate - wrapped[i]) / amb) * amb
            mean += w_choose[i] * nearest[i]
        r2 = 0.0
        out = 0.0
        for i in range(freqs.shape[0]):
            r2 += w_choose[i] * (nearest[i] - mean) ** 2
            out += w_out[i] * nearest[i]
        if r2 < best_r2:
            best_r2, best_d = r2, (mean if not frequency_out else out)
    return best_r2, best_d


@fn
def clean_distances(correlation_sum, ambient_sum, sample_count, channels, freqs, settings, p, scratch, raw, out):
    """The noise-free decoded distance of pixel p for every max path length k = 1..K into ``out`` (K, P): the
    raw images of the bounce buckets ≤ k (running sums of the buckets' means) decoded without thresholds,
    range limit or phasor filter (render._decode_clean_per_k: decode.decode with the clean settings); NaN
    where a frequency has no modulated signal or the frequencies disagree beyond the unwrap tolerance.
    ``settings`` as in :func:`pixel_error` with the unwrap tolerance in row 6; ``raw`` (≥ J,) scratch."""
    unambiguous, tolerance = settings[0], settings[6]
    n_candidates, h = np.int64(settings[1]), np.int64(settings[2])
    frequency_out = settings[5] != 0.0
    w_choose, w_out, wrapped, nearest, a, b = scratch[0], scratch[1], scratch[2], scratch[3], scratch[4], scratch[5]
    n = sample_count[p]
    ambient = ambient_sum[p] / n
    n_raw = channels.shape[0]
    for j in range(n_raw):
        raw[j] = 0.0
    for k in range(correlation_sum.shape[0]):
        for j in range(n_raw):
            raw[j] += correlation_sum[k, j, p] / n  # the cumulative mean of buckets ≤ k
        no_return = False
        total_w = 0.0
        for i in range(freqs.shape[0]):
            first, steps = np.int64(freqs[i, F_FIRST]), np.int64(freqs[i, F_STEPS])
            re, im, sum_q = 0.0, 0.0, 0.0
            for s_k in range(steps):
                j = first + s_k
                q = channels[j, 0] * (raw[j] + ambient * channels[j, 1])
                re += channels[j, 2] * q
                im += channels[j, 3] * q
                sum_q += q
            a[i] = 2.0 / steps * math.hypot(re, im)
            b[i] = sum_q / steps
            if a[i] <= NO_RETURN * b[i]:
                no_return = True
            phase = math.atan2(im, re) % TWO_PI
            if not phase < TWO_PI:
                phase = 0.0
            wrapped[i] = phase * freqs[i, F_METRES_PER_RAD]
            w = (freqs[i, F_HZ] * a[i]) ** 2 / (a[i] + b[i]) if a[i] + b[i] > 0 else 0.0
            w_choose[i] = w
            total_w += w
        for i in range(freqs.shape[0]):
            w_choose[i] = w_choose[i] / total_w if total_w > 0 else 1.0 / freqs.shape[0]
            w_out[i] = freqs[i, F_OUTPUT] if frequency_out else w_choose[i]
        best_r2, best_d = unwrap_best(wrapped, w_choose, w_out, freqs, n_candidates, h, frequency_out, nearest)
        failed = not math.sqrt(best_r2) <= tolerance
        out[k, p] = math.nan if no_return or failed else best_d % unambiguous


@fn
def pixel_error(table, counts, distance, depth_scale, freqs, settings, y, x, width, height, rows, scratch, weights,
                deviations, unwrapped):
    """Stage 2 for pixel (y, x): (σ of the output depth, whether its replicates unwrap to different intervals).

    ``settings`` (float64) = (unambiguous range U, wrap candidates N, index h of the highest frequency, flip
    threshold, bilateral filter on (1/0), output weights f/Σf (1) or inverse variance (0), unwrap tolerance);
    ``distance`` the first-hit distance (NaN: none), ``depth_scale`` |ω_z| of a z-depth sensor, else 1;
    ``rows`` the table columns of x = 0 in the rows above, at and below y; scratch: ``scratch`` (5, ≥ F),
    ``weights`` (9,), ``deviations`` and ``unwrapped`` (≥ R,)."""
    unambiguous, threshold = settings[0], settings[3]
    n_candidates, h = np.int64(settings[1]), np.int64(settings[2])
    bilateral, frequency_out = settings[4] != 0.0, settings[5] != 0.0
    w_sigma, w_choose, w_out, wrapped, nearest = scratch[0], scratch[1], scratch[2], scratch[3], scratch[4]
    n_freq = freqs.shape[0]
    n_rep = counts.shape[0]
    centre = n_rep
    p = y * width + x  # the pixel in the image; t (and its neighbours') its column of the phasor table
    t = rows[1] + x
    inner = 0 < y < height - 1 and 0 < x < width - 1
    min_count = counts[0, p]
    for r in range(1, n_rep):
        min_count = min(min_count, counts[r, p])
    # ---- σ: the replicates' deviations through the decoder's linearisation (render._standard_error)
    unwrap_weight_sum(table, centre, n_freq, freqs, t, frequency_out, w_sigma)
    any_signal = False  # Σ|∂d/∂Q| > 0: some frequency has modulated signal (distance_gradient's test)
    for i in range(n_freq):
        if 2.0 / freqs[i, F_STEPS] * table[centre, i, Z_NORM, t] > NO_RETURN * table[centre, i, OFFSET, t]:
            any_signal = True
    for r in range(n_rep):
        deviations[r] = 0.0
    for i in range(n_freq):
        metres = w_sigma[i] * freqs[i, F_METRES_PER_RAD]
        if bilateral:  # render._filtered_deviation: the filter's weights at the replicates' mean, for all r
            z_re, z_im = table[centre, i, Z_RE, t], table[centre, i, Z_IM, t]
            if inner:
                total = 0.0
                for tap in range(9):
                    weights[tap] = filter_weight(table, centre, i, t, rows[tap // 3] + x + tap % 3 - 1,
                                                 tap, freqs[i, F_STRONG_Z])
                    total += weights[tap]
                z_re, z_im = 0.0, 0.0
                for tap in range(9):
                    q = rows[tap // 3] + x + tap % 3 - 1
                    weights[tap] = weights[tap] / total
                    z_re += weights[tap] * table[centre, i, Z_RE, q]
                    z_im += weights[tap] * table[centre, i, Z_IM, q]
            norm2 = z_re * z_re + z_im * z_im
            for r in range(n_rep):
                if inner:
                    d_re, d_im = 0.0, 0.0
                    for tap in range(9):
                        q = rows[tap // 3] + x + tap % 3 - 1
                        d_re += weights[tap] * (table[r, i, Z_RE, q] - table[centre, i, Z_RE, q])
                        d_im += weights[tap] * (table[r, i, Z_IM, q] - table[centre, i, Z_IM, q])
                else:
                    d_re = table[r, i, Z_RE, t] - z_re
                    d_im = table[r, i, Z_IM, t] - z_im
                d_phase = (z_re * d_im - z_im * d_re) / norm2 if norm2 > 0 else 0.0
                deviations[r] += metres * d_phase
        else:  # Σ_k ∂d/∂Q_k δQ_k = w c/(4πf) (Re Z̄ Im δZ − Im Z̄ Re δZ) / |Z̄|²
            re, im, norm = table[centre, i, Z_RE, t], table[centre, i, Z_IM, t], table[centre, i, Z_NORM, t]
            if 2.0 / freqs[i, F_STEPS] * norm > NO_RETURN * table[centre, i, OFFSET, t]:
                for r in range(n_rep):
                    d_re = table[r, i, Z_RE, t] - re
                    d_im = table[r, i, Z_IM, t] - im
                    deviations[r] += metres * (re * d_im - im * d_re) / (norm * norm)
    variance = 0.0
    for r in range(n_rep):
        variance += deviations[r] * deviations[r]
    variance = variance / (n_rep * (n_rep - 1))
    d = distance[p] if not math.isnan(distance[p]) else 0.5 * unambiguous
    sd = math.sqrt(variance)
    if sd > 0:
        variance = variance + (normal_tail(d / sd) + normal_tail((unambiguous - d) / sd)) * unambiguous ** 2
    sigma = math.sqrt(variance) * depth_scale[p] if min_count >= 1 and any_signal else math.nan
    if n_rep < 2:
        return sigma, False
    # ---- flips: each replicate decoded, filtered and unwrapped on its own (render._flips)
    signal = True
    for r in range(n_rep):
        for i in range(n_freq):
            a = 2.0 / freqs[i, F_STEPS] * table[r, i, Z_NORM, t]
            if not a > NO_RETURN * finite_or_zero(table[r, i, OFFSET, t]):
                signal = False
    if not (signal and min_count >= 1):
        return sigma, False
    for r in range(n_rep):
        unwrap_weight_sum(table, r, n_freq, freqs, t, False, w_choose)
        unwrap_weight_sum(table, r, n_freq, freqs, t, frequency_out, w_out)
        for i in range(n_freq):  # the wrapped distance of frequency i, after the camera's filter
            re, im = finite_or_zero(table[r, i, Z_RE, t]), finite_or_zero(table[r, i, Z_IM, t])
            if bilateral and inner:  # decode.filtered_phases on the phasors A e^{iφ} = (2/N) Z (atan2 of Σ w Z)
                f_re, f_im = 0.0, 0.0
                for tap in range(9):
                    q = rows[tap // 3] + x + tap % 3 - 1
                    w = filter_weight(table, r, i, t, q, tap, freqs[i, F_STRONG_Z])
                    f_re += w * finite_or_zero(table[r, i, Z_RE, q])
                    f_im += w * finite_or_zero(table[r, i, Z_IM, q])
                re, im = f_re, f_im
            phase = math.atan2(im, re) % TWO_PI
            if not phase < TWO_PI:
                phase = 0.0
            wrapped[i] = phase * freqs[i, F_METRES_PER_RAD]
        best_d = unwrap_best(wrapped, w_choose, w_out, freqs, n_candidates, h, frequency_out, nearest)[1]
        unwrapped[r] = best_d % unambiguous
    low, high = unwrapped[0], unwrapped[0]
    for r in range(1, n_rep):
        low, high = min(low, unwrapped[r]), max(high, unwrapped[r])
    return sigma, high - low > threshold


@fn
def band_error(replicate_sum, counts, channels, freqs, distance, depth_scale, settings, width, y0, y1, ring, scratch,
               weights, deviations, unwrapped, sigma, flips):
    """Both stages for rows y0 ≤ y < y1, the phasors of three rows (the row, and its neighbours above and below)
    kept in ``ring`` (R + 1, F, 6, 3 W): a megabyte that stays in the core's cache. The rows next to the band
    are computed here too."""
    height = counts.shape[1] // width
    for y in range(max(y0 - 1, 0), min(y0 + 1, height)):  # the first row and the one above it
        for x in range(width):
            pixel_phasors(replicate_sum, counts, channels, freqs, y * width + x, ring, (y % 3) * width + x)
    for y in range(y0, y1):
        if y + 1 < height:
            for x in range(width):
                pixel_phasors(replicate_sum, counts, channels, freqs, (y + 1) * width + x, ring,
                              ((y + 1) % 3) * width + x)
        rows = (((y + 2) % 3) * width, (y % 3) * width, ((y + 1) % 3) * width)
        for x in range(width):
            s, f = pixel_error(ring, counts, distance, depth_scale, freqs, settings, y, x, width, height, rows,
                               scratch, weights, deviations, unwrapped)
            sigma[y * width + x] = s
            flips[y * width + x] = f


@cpu_parallel
def depth_error_rows(replicate_sum, counts, channels, freqs, distance, depth_scale, settings, width, bands, sigma,
                     flips):
    """:func:`band_error` over ``bands`` bands of rows on numba's threads: ``sigma`` (P,) and ``flips`` (P,) bool.
    (The loop's body is one call: numba's parallel loops compile slowly when they inline large bodies.)"""
    height = counts.shape[1] // width
    for b in prange(bands):
        band_error(replicate_sum, counts, channels, freqs, distance, depth_scale, settings, width,
                   b * height // bands, (b + 1) * height // bands,
                   np.empty((counts.shape[0] + 1, freqs.shape[0], 6, 3 * width)), np.empty((5, freqs.shape[0])),
                   np.empty(9), np.empty(counts.shape[0]), np.empty(counts.shape[0]), sigma, flips)


@gpu_kernel
def phasors_kernel(replicate_sum, counts, channels, freqs, table):
    """Stage 1 on the GPU, a thread per pixel."""
    p = cuda.grid(1)
    if p < counts.shape[1]:
        pixel_phasors(replicate_sum, counts, channels, freqs, p, table, p)


@gpu_kernel
def error_kernel(table, counts, distance, depth_scale, freqs, settings, width, sigma, flips):
    """Stage 2 on the GPU, a thread per pixel."""
    p = cuda.grid(1)
    if p < counts.shape[1]:
        scratch = cuda.local.array((5, MAX_FREQUENCIES), np.float64)
        weights = cuda.local.array(9, np.float64)
        deviations = cuda.local.array(MAX_REPLICATES, np.float64)
        unwrapped = cuda.local.array(MAX_REPLICATES, np.float64)
        y = p // width
        s, f = pixel_error(table, counts, distance, depth_scale, freqs, settings, y, p % width, width,
                           counts.shape[1] // width, ((y - 1) * width, y * width, (y + 1) * width), scratch, weights,
                           deviations, unwrapped)
        sigma[p] = s
        flips[p] = f


@cpu_parallel
def clean_rows(correlation_sum, ambient_sum, sample_count, channels, freqs, settings, width, out):
    """:func:`clean_distances` for every pixel on numba's threads, a row at a time (CI's check of the kernel)."""
    for y in prange(sample_count.shape[0] // width):
        scratch = np.empty((6, freqs.shape[0]))
        raw = np.empty(channels.shape[0])
        for x in range(width):
            clean_distances(correlation_sum, ambient_sum, sample_count, channels, freqs, settings, y * width + x,
                            scratch, raw, out)


@gpu_kernel
def clean_kernel(correlation_sum, ambient_sum, sample_count, channels, freqs, settings, out):
    """:func:`clean_distances` on the GPU, a thread per pixel."""
    p = cuda.grid(1)
    if p < sample_count.shape[0]:
        scratch = cuda.local.array((6, MAX_FREQUENCIES), np.float64)
        raw = cuda.local.array(MAX_RAW, np.float64)
        clean_distances(correlation_sum, ambient_sum, sample_count, channels, freqs, settings, p, scratch, raw, out)


# ------------------------------------------------------------------ host side: the tables and the launches
def unsupported(sensor) -> str:
    """Why this estimate cannot take ``sensor`` ("" where it can): it covers continuous-wave sensors with
    the phasor filters "none" and "bilateral" and at most MAX_FREQUENCIES frequencies."""
    mod = sensor.modulation
    if not mod.is_cw:
        return "a pulsed sensor (its estimate is two buckets, no filter: the array program's is cheap)"
    if len(mod.frequencies_hz) > MAX_FREQUENCIES:
        return f"more than {MAX_FREQUENCIES} frequencies"
    if sensor.processing.phasor_filter not in ("none", "bilateral"):
        return f"phasor filter {sensor.processing.phasor_filter!r}"
    if mod.raw_count > MAX_RAW:
        return f"more than {MAX_RAW} raw images"
    return ""


def tables(sensor, n_raw: int, flip_threshold_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(channels (J, 4), frequency table (F, 7), settings (7,)) of :func:`pixel_phasors`, :func:`pixel_error` and
    :func:`clean_distances` for ``sensor`` (its first ``n_raw`` correlation channels are the raw images) and the
    spread of the replicates' distances above which they unwrapped to different intervals."""
    mod = sensor.modulation
    scale = sensor.readout.responsivity * np.asarray(mod.raw_exposure_s(), np.float64)
    duty = np.asarray(mod.gate_duty(), np.float64)
    channels = np.zeros((n_raw, 4))
    freqs = np.zeros((len(mod.frequencies_hz), 7))
    d_amb = mod.ambiguity_distances_m()
    f_total = float(np.sum(mod.frequencies_hz))
    first = 0
    for i, (f_hz, steps) in enumerate(zip(mod.frequencies_hz, mod.phase_steps)):
        theta = TWO_PI * np.arange(steps) / steps
        channels[first:first + steps] = np.stack([scale[first:first + steps], duty[first:first + steps],
                                                  np.round(np.cos(theta), 15), np.round(np.sin(theta), 15)], axis=1)
        freqs[i] = (f_hz, steps, first, d_amb[i], SPEED_OF_LIGHT / (4.0 * np.pi * f_hz),
                    sensor.invalid.min_amplitude_e * steps / 2.0, f_hz / f_total)
        first += steps
    unambiguous = mod.unambiguous_range_m()
    h = int(np.argmax(mod.frequencies_hz))
    tolerance = sensor.invalid.unwrap_tolerance_m
    settings = np.array([unambiguous, max(1, math.ceil(unambiguous / d_amb[h] - 1e-9)), h, flip_threshold_m,
                         sensor.processing.phasor_filter == "bilateral",
                         sensor.processing.unwrap_weights == "frequency",
                         _decode.default_unwrap_tolerance_m(mod) if tolerance is None else tolerance], np.float64)
    return channels, freqs, settings


def cuda_build():
    """This file compiled by numba.cuda (loaded once per process, as tofcore.compiled.cuda loads kernels.py)."""
    return load_cuda_build(__name__, __file__)


THREADS_PER_BLOCK = 128


def render_error(transport, sensor, n_raw: int, flip_threshold_m: float):
    """(σ (H, W), flips (H, W) bool) of :func:`tofcore.render.render_error` for a sensor :func:`unsupported` does not refuse,
    on the transport's device: numba's threads on the CPU, two CUDA kernels on a GPU."""
    from ..backend import device_copy, namespace
    from ..tracer.estimator import replicate_counts

    xp = namespace(transport.replicate_sum)
    h, w = transport.height, transport.width
    counts = xp.ascontiguousarray(replicate_counts(transport.sample_count).astype(np.int64))
    replicates = counts.shape[0]
    if replicates > MAX_REPLICATES:
        raise ValueError(f"depth_error: at most {MAX_REPLICATES} replicates, got {replicates}")
    channels, freqs, settings = (xp.asarray(a) for a in tables(sensor, n_raw, flip_threshold_m))
    distance = xp.ascontiguousarray(device_copy(xp, transport.first_hit.distance_m).reshape(-1), dtype=np.float64)
    if sensor.depth_output == "z":
        scale = np.abs(sensor.camera.pixel_center_directions()[..., 2]).reshape(-1).astype(np.float64)
    else:
        scale = np.ones(h * w)
    scale = device_copy(xp, scale)
    replicate_sum = xp.ascontiguousarray(transport.replicate_sum, dtype=np.float64)
    sigma = xp.empty(h * w)
    flips = xp.zeros(h * w, dtype=np.bool_)
    if xp is np:
        import numba

        from .cpu import PARALLEL_LOCK

        with PARALLEL_LOCK:
            depth_error_rows(replicate_sum, counts, channels, freqs, distance, scale, settings, w,
                             min(h, 4 * numba.get_num_threads()), sigma, flips)
    else:
        table = xp.empty((replicates + 1, freqs.shape[0], 6, h * w))  # every pixel's phasors, read by its neighbours
        build = cuda_build()
        blocks = (h * w + THREADS_PER_BLOCK - 1) // THREADS_PER_BLOCK
        build.phasors_kernel[blocks, THREADS_PER_BLOCK](replicate_sum, counts, channels, freqs, table)
        build.error_kernel[blocks, THREADS_PER_BLOCK](table, counts, distance, scale, freqs, settings, w, sigma,
                                                      flips)
    return sigma.reshape(h, w), flips.reshape(h, w)


def clean_per_k(transport, sensor, n_raw: int):
    """(K, H, W) float32 noise-free decoded distance for every max path length k (render._decode_clean_per_k) for
    a sensor :func:`unsupported` does not refuse, on the transport's device: one CUDA kernel on a GPU, numba's threads on the
    CPU."""
    from ..backend import namespace

    xp = namespace(transport.correlation_sum)
    k, h, w = transport.max_depth, transport.height, transport.width
    channels, freqs, settings = (xp.asarray(a) for a in tables(sensor, n_raw, 0.0))
    correlation_sum = xp.ascontiguousarray(transport.correlation_sum[:, :n_raw], dtype=np.float64)
    ambient_sum = xp.ascontiguousarray(transport.ambient_sum, dtype=np.float64)
    sample_count = xp.ascontiguousarray(transport.sample_count, dtype=np.int64)
    out = xp.empty((k, h * w))
    if xp is np:
        from .cpu import PARALLEL_LOCK

        with PARALLEL_LOCK:
            clean_rows(correlation_sum, ambient_sum, sample_count, channels, freqs, settings, w, out)
    else:
        blocks = (h * w + THREADS_PER_BLOCK - 1) // THREADS_PER_BLOCK
        cuda_build().clean_kernel[blocks, THREADS_PER_BLOCK](correlation_sum, ambient_sum, sample_count, channels,
                                                            freqs, settings, out)
    return out.reshape(k, h, w).astype(np.float32)
