"""Depth from raw ToF images: N-step phase estimation, multi-frequency phase unwrapping, pulsed ratio.

Inputs are raw images (R, *shape) in electrons, ordered as :meth:`Modulation.raw_labels`; maths is float64,
image outputs of :func:`decode` are float32. Invalid pixels are NaN in ``distance`` and carry a
:class:`Reason`; amplitude, offset and intensity stay finite everywhere (they are
measurements, not depths). The settings of :func:`decode` are one :class:`DecodeSettings`:

==========================  ====  =========  ==================================================================
name                        unit  default    meaning
==========================  ====  =========  ==================================================================
``min_amplitude_e``         e⁻    0          LOW_AMPLITUDE below this amplitude (A of the highest frequency;
                                             pulsed: Q1 + Q2)
``min_amplitude_snr``       1     0          LOW_AMPLITUDE also below this many σ_A, the amplitude noise of the
                                             pixel's own offset (:func:`amplitude_noise_e`); pulsed: Q1 + Q2
                                             below this many σ of a dark pixel's, √2 σ_read (the ambient charge
                                             in Q1 + Q2 cannot be told from signal with two buckets)
``read_noise_e``            e⁻    0          σ_read of :func:`amplitude_noise_e`
``gain_noise``              1     0          Keller's β of :func:`amplitude_noise_e`
``saturation_e``            e⁻    None       SATURATED where any raw image reaches it (None: never)
``range_m``                 m     (0, inf)   OUT_OF_RANGE outside [min, max]
``range_scale``             1     None       the range test applies to distance × this (per pixel; e.g. the
                                             ray's z component: a z-depth camera limits z); None: 1
``unwrap_tolerance_m``      m     d_min/16   UNWRAPPING_FAILED above this weighted RMS disagreement
``unwrap_weights``          –     "inverse_  how the frequencies are averaged (:mod:`tofcore.sensor.processing`)
                                  variance"
``phasor_filter``           –     "none"     the camera's filter of each frequency's phasors before unwrapping
                                             (:mod:`tofcore.sensor.processing`)
``amplitude_test``          –     "highest"  which amplitudes the two LOW_AMPLITUDE tests read: ``"highest"``
                                             (the highest frequency's) or ``"every"`` (every frequency's, each
                                             against its own noise floor; libfreenect2's
                                             ``individual_ab_threshold`` on the minimum over the frequencies);
                                             with the phasor filter on, the filtered amplitudes (libfreenect2)
``dealias_tolerance_rad``   rad   None       UNWRAPPING_FAILED also where the unwrapped phases lie farther than
                                             this from the line on which the frequencies agree (libfreenect2's
                                             dealiasing confidence, :func:`dealias_distance_rad`); None: off
``edge_filter``             –     False      EDGE_FILTERED where the camera's edge-aware filter removes the
                                             pixel (:func:`tofcore.sensor.processing.edge_filter`; only with the
                                             bilateral phasor filter, whose edge test it uses)
``edge_delta_scale``        1     1          the edge filter's depth thresholds times this (the native over the
                                             rendered focal length: :attr:`InvalidRules.edge_filter_fx_px`)
==========================  ====  =========  ==================================================================

Reason precedence (the first that applies wins): SATURATED, NO_RETURN, LOW_AMPLITUDE, UNWRAPPING_FAILED,
OUT_OF_RANGE, EDGE_FILTERED (fields of :class:`DecodeSettings`) — from "data clipped" (saturation flattens every
bucket to full well, which would otherwise read as no modulation, i.e. no return), through "no data" and "too
weak to trust", to "a trusted distance that the sensor does not report" and "a distance its neighbours do not
support" (libfreenect2 tests the range before its edge filter).
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass

import numpy as np

from ..backend import asarray, namespace
from ..constants import SPEED_OF_LIGHT_M_S
from ..errors import ConfigError
from .modulation import Modulation, ideal_raw
from .processing import (BILATERAL_MAX_EDGE, PHASOR_FILTERS, UNWRAP_WEIGHTS, bilateral_weights, check_choice,
                         frequency_weights, neighbour_mean)
from .processing import edge_filter as processing_edge_filter

AMPLITUDE_TESTS = ("highest", "every")
NO_RETURN_RELATIVE_AMPLITUDE = 1e-9
"""A ≤ this · B counts as A = 0 (atan2(0, 0)): far above float64 round-off of the DFT sums (~1e-16 N B),
far below any physical modulation contrast."""
MAX_UNWRAP_CANDIDATES = 10_000
UNWRAP_BLOCK_VALUES = {"numpy": 1 << 18, "device": 1 << 24}
"""Most values (N candidates × F frequencies × pixels) of one unwrapping temporary; larger images are
unwrapped in blocks of pixels. NumPy: 2 MiB of float64, temporaries that stay in the caches (a 512 × 424
Kinect v2 frame is 38 blocks); a device: 128 MiB, few launches and a bounded footprint (the frame is one
block, its five ground-truth images together three)."""


class Reason(enum.IntEnum):
    """Why a pixel is invalid (the ``reason`` image)."""

    VALID = 0
    NO_RETURN = 1          # no LED light came back (nothing hit, or zero signal: atan2(0, 0))
    LOW_AMPLITUDE = 2      # amplitude below the sensor's threshold
    SATURATED = 3          # a raw image reached full well
    OUT_OF_RANGE = 4       # decoded distance outside the sensor's range
    UNWRAPPING_FAILED = 5  # the frequencies disagree on the distance
    EDGE_FILTERED = 6      # the camera's edge-aware filter removed it (flying pixel, incoherent neighbourhood)


@dataclass(frozen=True)
class CwDecoding:
    """Per-frequency results of :func:`decode_cw`, each (F, *shape) float64, frequencies in acquisition order."""

    phase: np.ndarray             # φ in [0, 2π), rad
    amplitude: np.ndarray         # A, e⁻ (eq. 2.40)
    offset: np.ndarray            # B, e⁻ (eq. 2.41)
    wrapped_distance: np.ndarray  # d_f = c φ / (4 π f) in [0, d_amb), m (eq. 2.34, 2.39)


@dataclass(frozen=True)
class Unwrapped:
    """Result of :func:`unwrap`, each (*shape) float64."""

    distance: np.ndarray    # m, in [0, unambiguous range)
    residual: np.ndarray    # m, weighted RMS disagreement of the frequencies at the chosen wraps
    confidence: np.ndarray  # 1, clip(1 − residual / tolerance, 0, 1)
    failed: np.ndarray      # bool, residual > tolerance
    dealias_rad: np.ndarray | None = None  # rad, :func:`dealias_distance_rad` at the chosen wraps
    wrap: np.ndarray | None = None         # int, the chosen wrap n of the highest frequency (D = d_h + n d_amb,h)


@dataclass(frozen=True)
class Decoded:
    """Output of :func:`decode`; images (*shape), float32 unless noted."""

    distance: np.ndarray    # m, radial, NaN where invalid
    amplitude: np.ndarray   # e⁻, A of the highest frequency (pulsed: Q1 + Q2)
    offset: np.ndarray      # e⁻, B of the highest frequency (pulsed: (Q1 + Q2) / 2)
    intensity: np.ndarray   # e⁻, mean of all raw images
    confidence: np.ndarray  # 1, in [0, 1], 0 where invalid
    valid: np.ndarray       # bool
    reason: np.ndarray      # uint8, Reason


# ------------------------------------------------------------------ continuous wave
def phase_amplitude_offset(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """N-step phase estimation of one frequency from samples (N, *shape) taken at gate offsets k/N.

    Returns
    -------
    phase φ in [0, 2π) (rad), amplitude A and offset B (units of ``samples``), float64.

    Notes
    -----
    For samples :math:`Q_k = B + A \\cos(\\varphi - \\theta_k)`, :math:`\\theta_k = 2\\pi k/N` (the sine
    correlation of :mod:`tofcore.sensor.modulation` scaled by the signal), the first DFT bin is
    :math:`Z = \\sum_k Q_k e^{i\\theta_k} = \\tfrac N2 A e^{i\\varphi}`, so

    .. math:: \\varphi = \\operatorname{atan2}\\Big(\\sum_k Q_k \\sin\\theta_k, \\sum_k Q_k \\cos\\theta_k\\Big),
              \\quad A = \\frac2N |Z|, \\quad B = \\frac1N \\sum_k Q_k.

    For N = 4 (steps = buckets C1, C3, C2, C4) these are eq. 2.38/2.49 φ = atan2(Q3 − Q4, Q1 − Q2),
    eq. 2.40 and eq. 2.41 exactly (the DFT weights are rounded to exact 0, ±1 where they are).
    """
    q = asarray(samples, dtype=np.float64)
    n = q.shape[0]
    theta = 2.0 * np.pi * np.arange(n) / n
    cos_k = np.round(np.cos(theta), 15)
    sin_k = np.round(np.sin(theta), 15)
    xp = namespace(q)
    real = np.tensordot(xp.asarray(cos_k), q, axes=1)
    imag = np.tensordot(xp.asarray(sin_k), q, axes=1)
    phase = np.mod(np.arctan2(imag, real), 2.0 * np.pi)
    phase = np.where(phase < 2.0 * np.pi, phase, 0.0)  # np.mod(-tiny, 2π) rounds up to 2π
    return phase, 2.0 / n * np.hypot(real, imag), q.mean(axis=0)


def decode_cw(raw: np.ndarray, modulation: Modulation, *, check: bool = True) -> CwDecoding:
    """Phase, amplitude, offset and wrapped distance of every frequency of a CW sensor.

    Parameters
    ----------
    raw : (R, *shape) raw images in electrons, R = Σ phase steps, frequency-major.
    modulation : a ``cw_square`` or ``cw_sine`` :class:`Modulation`.

    Notes
    -----
    Per frequency :func:`phase_amplitude_offset`, then eq. 2.39 and 2.34:
    :math:`d_f = c \\varphi / (4 \\pi f) \\in [0, c/(2f))`. A square source gives the same formulas with
    the systematic error of a triangle correlation sampled at N points (see :func:`systematic_error_curve`).
    ``check``: that ``raw`` is finite, as in :func:`decode`.
    """
    raw = check_raw(raw, modulation, finite=check)
    if not modulation.is_cw:
        raise ConfigError(f"decode_cw: modulation.kind must be 'cw_square' or 'cw_sine', got {modulation.kind!r}")
    results = []
    start = 0
    for n in modulation.phase_steps:
        results.append(phase_amplitude_offset(raw[start:start + n]))
        start += n
    phase, amplitude, offset = (np.stack(parts) for parts in zip(*results))
    f_hz = namespace(raw).asarray(modulation.frequencies_hz).reshape((-1,) + (1,) * (raw.ndim - 1))
    return CwDecoding(phase=phase, amplitude=amplitude, offset=offset,
                      wrapped_distance=SPEED_OF_LIGHT_M_S * phase / (4.0 * np.pi * f_hz))


def default_unwrap_tolerance_m(modulation: Modulation) -> float:
    """Default tolerance of :func:`unwrap`: 1/16 of the smallest ambiguity distance, in metres.

    That is a phase error of π/8 at the highest frequency. Noise-free systematic residuals stay well below
    it (square source: per-frequency errors of 0.0113 d_amb with 4 steps, 0.0031 d_amb with 3; Kinect v2
    residual ≤ 0.02 m against 0.078 m). The next-best wrap combination of consistent Kinect v2 data lies at
    ≥ 0.205 m, while data that no distance explains (mixed pixels, multipath) reach at most ≈ 0.166 m, the
    covering radius of the Kinect v2 wrap lattice: with 1/8 (0.156 m) only 2 % of random inconsistent pixels
    would be flagged, with 1/16 about two thirds.
    """
    return float(np.min(modulation.ambiguity_distances_m())) / 16.0


def unwrap(cw: CwDecoding, modulation: Modulation, *, tolerance_m: float | None = None,
           weights: str = "inverse_variance") -> Unwrapped:
    """Multi-frequency phase unwrapping: the distance on which all frequencies agree.

    Parameters
    ----------
    cw : per-frequency wrapped distances and amplitudes from :func:`decode_cw`.
    modulation : the CW modulation that produced them.
    tolerance_m : residual above which a pixel is UNWRAPPING_FAILED (default
        :func:`default_unwrap_tolerance_m`).
    weights : how the unwrapped distances of the frequencies are averaged into the output distance:
        ``"inverse_variance"`` or ``"frequency"`` (:func:`unwrap_weights`). The wrap is always chosen, and the
        residual always measured, with the inverse-variance weights: they are the test of whether the
        frequencies agree within their noise, while a camera's fixed combination (libfreenect2's
        ``"frequency"``) is only how it averages once the wraps are known. (Testing with the fixed weights
        gave the 16 MHz distance, whose multipath error is the largest, six times its weight in the residual:
        61 % of the Kinect v2 room's pixels failed the d_min/16 tolerance, against 5.5 %.)

    Notes
    -----
    Candidates are the wraps :math:`D = d_h + n \\, d_{amb,h}` of the highest frequency h within the
    unambiguous range (:meth:`Modulation.unambiguous_range_m`); for each, every other frequency takes its nearest wrap
    :math:`D_i = d_i + \\operatorname{round}((D - d_i)/d_{amb,i}) \\, d_{amb,i}`. With the inverse-variance
    weights of eq. 2.43, :math:`w_i = (f_i A_i)^2 / (A_i + B_i)`, the candidate minimising

    .. math:: r^2 = \\frac{\\sum_i w_i (D_i - \\bar D)^2}{\\sum_i w_i}, \\qquad
              \\bar D = \\frac{\\sum_i w_i D_i}{\\sum_i w_i}

    wins; the distance is :math:`\\bar D \\bmod R_{unamb}` and the confidence
    :math:`\\operatorname{clip}(1 - r/\\mathrm{tol}, 0, 1)`. One frequency: D = d_h, r = 0.
    """
    tolerance_m = default_unwrap_tolerance_m(modulation) if tolerance_m is None else float(tolerance_m)
    if not tolerance_m > 0:
        raise ConfigError(f"unwrap: tolerance_m must be > 0 (metres), got {tolerance_m!r}")
    d_amb = modulation.ambiguity_distances_m()
    unambiguous = modulation.unambiguous_range_m()
    h = int(np.argmax(modulation.frequencies_hz))
    n_candidates = max(1, math.ceil(unambiguous / d_amb[h] - 1e-9))
    if n_candidates > MAX_UNWRAP_CANDIDATES:
        raise ConfigError(f"unwrap: modulation.frequencies_hz must have at most {MAX_UNWRAP_CANDIDATES} wraps of "
                          f"the highest frequency in the unambiguous range (a larger common divisor), "
                          f"got {n_candidates} for {modulation.frequencies_hz!r}")
    wrapped = cw.wrapped_distance
    xp = namespace(wrapped)
    weight = unwrap_weights(cw, modulation, "inverse_variance")
    output = None if weights == "inverse_variance" else unwrap_weights(cw, modulation, weights)
    n_freq, shape = wrapped.shape[0], wrapped.shape[1:]
    wrapped, weight = wrapped.reshape(n_freq, -1), weight.reshape(n_freq, -1)
    output = weight if output is None else output.reshape(n_freq, -1)
    offsets = xp.asarray(np.arange(n_candidates) * d_amb[h])[:, None]      # (N, 1): n d_amb,h
    d_amb_i = xp.asarray(d_amb)[None, :, None]                             # (1, F, 1)
    pixels = wrapped.shape[1]
    block = max(1, UNWRAP_BLOCK_VALUES["numpy" if xp is np else "device"] // (n_candidates * n_freq))
    unit = _agreement_direction(modulation, xp)
    if pixels <= block:
        best_r2, best_d, dealias, wrap = _best_wrap(wrapped, weight, output, offsets, d_amb_i, h, unit)
    else:
        best_r2, best_d, dealias = xp.empty(pixels), xp.empty(pixels), xp.empty(pixels)
        wrap = xp.empty(pixels, dtype=np.int64)
        for first in range(0, pixels, block):
            part = slice(first, first + block)
            best_r2[part], best_d[part], dealias[part], wrap[part] = _best_wrap(
                wrapped[:, part], weight[:, part], output[:, part], offsets, d_amb_i, h, unit)
    best_r2, best_d = best_r2.reshape(shape), best_d.reshape(shape)
    residual = np.sqrt(best_r2)
    return Unwrapped(distance=np.mod(best_d, unambiguous), residual=residual,
                     confidence=np.clip(1.0 - residual / tolerance_m, 0.0, 1.0), failed=residual > tolerance_m,
                     dealias_rad=dealias.reshape(shape), wrap=wrap.reshape(shape))


def _agreement_direction(modulation: Modulation, xp):
    """(F, 1) unit vector f / |f|: the direction in the space of unwrapped phases (4π f_i D / c) along which
    the frequencies agree on one distance."""
    f = np.asarray(modulation.frequencies_hz, dtype=np.float64)
    return xp.asarray((f / np.linalg.norm(f))[:, None])


def dealias_distance_rad(unwrapped_m, modulation: Modulation):
    r"""How far (rad) the frequencies' unwrapped distances D_i (F, ...) are from agreeing on one distance.

    Notes
    -----
    libfreenect2 (``processPixelStage2``) turns the unwrapped distances into phases
    :math:`\Phi_i = 4\pi f_i D_i / c` and takes the cross product of :math:`\Phi` with the unit vector
    :math:`u = f/|f|` (its constants 0.551318, 0.110264, 0.826977 are 80, 16, 120 / 145.1): the distance of
    :math:`\Phi` from the line of consistent phases, :math:`\sqrt{|\Phi|^2 - (\Phi\cdot u)^2}`. It accepts
    a pixel where this is at most its dealiasing confidence, 0.349–0.611 rad (``min_dealias_confidence`` …
    ``max_dealias_confidence``, the looser bound for weaker pixels). One frequency: 0.
    """
    xp = namespace(unwrapped_m)
    f = xp.asarray(np.asarray(modulation.frequencies_hz, dtype=np.float64)).reshape(
        (-1,) + (1,) * (unwrapped_m.ndim - 1))
    phi = 4.0 * np.pi * f * unwrapped_m / SPEED_OF_LIGHT_M_S
    u = f / float(np.linalg.norm(np.asarray(modulation.frequencies_hz, dtype=np.float64)))
    along = (phi * u).sum(axis=0)
    return np.sqrt(np.maximum((phi * phi).sum(axis=0) - along * along, 0.0))


def _best_wrap(wrapped, weight, output, offsets, d_amb_i, h: int, unit):
    """(r², D̄, dealias, n) of the best candidate of :func:`unwrap` for pixels (F, P), all N candidates at once:
    the candidate with the least r² under ``weight``, its distances averaged with ``output`` (F, P), the
    distance of its unwrapped phases from agreement (:func:`dealias_distance_rad`, ``unit`` = f/|f| (F, 1))
    and its index n.

    Arrays (N, F, P): every candidate's nearest wrap of every frequency; the candidate axis is
    reduced by ``argmin``, whose first minimum is the first candidate with the smallest r² (as a
    scan over the candidates with a strict ``<`` would pick). Inputs are finite (from raw images that
    :func:`decode` checked), so no r² is NaN.
    """
    xp = namespace(wrapped)
    candidate = wrapped[h][None] + offsets                                   # (N, P)
    unwrapped = wrapped[None] + np.round((candidate[:, None] - wrapped[None]) / d_amb_i) * d_amb_i
    mean = (weight[None] * unwrapped).sum(axis=1)                            # (N, P)
    r2 = (weight[None] * (unwrapped - mean[:, None]) ** 2).sum(axis=1)
    best = xp.argmin(r2, axis=0)[None]
    if output is not weight:
        mean = (output[None] * unwrapped).sum(axis=1)
    chosen = xp.take_along_axis(unwrapped, best[:, None], axis=0)[0]           # (F, P)
    phi = chosen * (4.0 * np.pi / SPEED_OF_LIGHT_M_S) / (2.0 * d_amb_i[0]) * SPEED_OF_LIGHT_M_S
    along = (phi * unit).sum(axis=0)
    dealias = np.sqrt(np.maximum((phi * phi).sum(axis=0) - along * along, 0.0))
    return (xp.take_along_axis(r2, best, axis=0)[0], xp.take_along_axis(mean, best, axis=0)[0], dealias,
            best[0])


def unwrap_weights(cw: CwDecoding, modulation: Modulation, scheme: str = "inverse_variance") -> np.ndarray:
    r"""(F, *shape) normalised weights of the frequencies in :func:`unwrap`.

    ``"inverse_variance"``: :math:`w_i \propto (f_i A_i)^2 / (A_i + B_i)` (eq. 2.43: σ_d ∝ √(A+B) / (f A)),
    summing to one; equal weights where no frequency has signal. ``"frequency"``: :math:`w_i = f_i/\sum f`,
    the camera's fixed combination (:func:`tofcore.sensor.processing.frequency_weights`).
    """
    xp = namespace(cw.amplitude)
    if check_choice(scheme, UNWRAP_WEIGHTS, "unwrap", "weights") == "frequency":
        return frequency_weights(modulation.frequencies_hz, cw.amplitude.shape[1:], xp)
    f_hz = xp.asarray(modulation.frequencies_hz).reshape((-1,) + (1,) * (cw.amplitude.ndim - 1))
    total = cw.amplitude + cw.offset
    weight = np.where(total > 0, (f_hz * cw.amplitude) ** 2 / np.where(total > 0, total, 1.0), 0.0)
    weight_sum = weight.sum(axis=0)
    weight = np.where(weight_sum > 0, weight, 1.0)  # no signal anywhere: equal weights (pixel is NO_RETURN)
    return weight / weight.sum(axis=0)


def distance_gradient(raw: np.ndarray, modulation: Modulation, weights: str = "inverse_variance", *,
                      check: bool = True) -> np.ndarray:
    r"""(R, *shape) derivative of the decoded distance with respect to each raw image, metres per electron.

    The linearisation of :func:`decode` at ``raw`` — what a small error in the raw images (Monte Carlo
    noise of a render, sensor noise) does to the distance the camera outputs, for error propagation
    (``tofcore.render``'s error estimate). It holds where the unwrapping stays on the same wraps.

    Notes
    -----
    CW: with :math:`Z_i = \sum_k Q_k e^{i\theta_k}` per frequency (:func:`phase_amplitude_offset`),
    :math:`\partial\varphi_i/\partial Q_k = (\mathrm{Re}Z_i \sin\theta_k - \mathrm{Im}Z_i \cos\theta_k)
    / |Z_i|^2`, and the unwrapped distance :math:`\bar D = \sum_i w_i D_i` (:func:`unwrap`, weights held
    fixed, ``weights`` as in :func:`unwrap_weights`) gives :math:`\partial\bar D/\partial Q_{i,k} = w_i \frac{c}{4\pi f_i}
    \partial\varphi_i/\partial Q_{i,k}`. Pulsed (eq. 2.36): :math:`d = s\,Q_2/(Q_1+Q_2)`, s = c t0/2:
    :math:`\partial d/\partial Q_1 = -s Q_2/(Q_1+Q_2)^2`, :math:`\partial d/\partial Q_2 = s Q_1/(Q_1+Q_2)^2`.
    Zero where a frequency has no modulated signal (A ≤ 10⁻⁹ B, as decode's NO_RETURN test).
    ``check``: that ``raw`` is finite, as in :func:`decode`.
    """
    raw = check_raw(raw, modulation, finite=check)
    xp = namespace(raw)
    grad = xp.zeros(raw.shape)
    if not modulation.is_cw:
        total = raw[0] + raw[1]
        scale = modulation.ambiguity_distances_m()[0] / np.where(total > 0, total, 1.0) ** 2
        grad[0] = np.where(total > 0, -scale * raw[1], 0.0)
        grad[1] = np.where(total > 0, scale * raw[0], 0.0)
        return grad
    weight = unwrap_weights(decode_cw(raw, modulation, check=False), modulation, weights)
    start = 0
    for i, (f_hz, n) in enumerate(zip(modulation.frequencies_hz, modulation.phase_steps)):
        theta = 2.0 * np.pi * np.arange(n) / n
        cos_k, sin_k = np.round(np.cos(theta), 15), np.round(np.sin(theta), 15)
        q = raw[start:start + n]
        real = np.tensordot(xp.asarray(cos_k), q, axes=1)
        imag = np.tensordot(xp.asarray(sin_k), q, axes=1)
        norm2 = real * real + imag * imag
        # No modulation (decode's NO_RETURN test, A ≤ 1e-9 B): the rounded DFT weights leave |Z| ~ 1e-14 B.
        signal = 2.0 / n * np.sqrt(norm2) > NO_RETURN_RELATIVE_AMPLITUDE * q.mean(axis=0)
        scale = weight[i] * SPEED_OF_LIGHT_M_S / (4.0 * np.pi * f_hz) / np.where(signal, norm2, 1.0)
        for k in range(n):
            grad[start + k] = np.where(signal, scale * (real * sin_k[k] - imag * cos_k[k]), 0.0)
        start += n
    return grad


# ------------------------------------------------------------------ pulsed
def decode_pulsed(raw: np.ndarray, modulation: Modulation, *, check: bool = True) -> np.ndarray:
    """Distance of a two-bucket pulsed sensor, eq. 2.36: d = (c t0 / 2) · Q2 / (Q1 + Q2).

    Parameters
    ----------
    raw : (2, *shape) bucket charges Q1, Q2 in electrons.
    modulation : a ``pulsed`` :class:`Modulation`.

    Returns
    -------
    float64 distance in [0, c t0 / 2] metres, NaN where Q1 + Q2 = 0 (no return).

    Notes
    -----
    Ambient light adds the same charge a to both buckets and biases the ratio:
    :math:`d = \\tfrac{c t_0}{2} (S\\tau/t_0 + a)/(S + 2a)` (SPEC §3, thesis §6.4). ``check``: as in :func:`decode`.
    """
    raw = check_raw(raw, modulation, finite=check)
    if modulation.is_cw:
        raise ConfigError(f"decode_pulsed: modulation.kind must be 'pulsed', got {modulation.kind!r}")
    total = raw[0] + raw[1]
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(total > 0, raw[1] / total, np.nan)
    return modulation.ambiguity_distances_m()[0] * ratio


# ------------------------------------------------------------------ full decoding
def amplitude_noise_e(offset: np.ndarray, steps: int, read_noise_e: float = 0.0,
                      gain_noise: float = 0.0) -> np.ndarray:
    r"""σ_A, e⁻: the standard deviation of each Cartesian component of the amplitude A of a pixel whose
    ``steps`` raw images have mean ``offset`` B and no modulation (only unmodulated light: ambient, dark).

    Notes
    -----
    Each raw image has variance :math:`v = B + \sigma_{read}^2 + (\beta B)^2` (Poisson shot noise, read
    noise, Keller's gain noise, thesis eq. 3.1; :mod:`tofcore.sensor.noise`). The DFT of
    :func:`phase_amplitude_offset`, :math:`A e^{i\varphi} = \frac2N \sum_k Q_k e^{i\theta_k}`, gives each
    component the variance :math:`\frac{4}{N^2} \cdot \frac N2 v`, so :math:`\sigma_A = \sqrt{2v/N}`.
    Without a signal A is then Rayleigh-distributed: :math:`P(A \ge k\sigma_A) = e^{-k^2/2}` — the share
    of empty pixels that pass an amplitude threshold of k σ_A (``min_amplitude_snr`` of :func:`decode`).
    """
    b = np.maximum(offset, 0.0)
    return np.sqrt(2.0 / steps * (b + read_noise_e ** 2 + (gain_noise * b) ** 2))


@dataclass(frozen=True, eq=False)
class DecodeSettings:
    """What :func:`decode` does besides the maths: thresholds, range, unwrapping, the camera's filter.

    Fields as in the module docstring's table; checked once, here (``ConfigError`` naming the field).
    """

    min_amplitude_e: float = 0.0
    min_amplitude_snr: float = 0.0
    read_noise_e: float = 0.0
    gain_noise: float = 0.0
    saturation_e: float | None = None
    range_m: tuple[float, float] = (0.0, math.inf)
    range_scale: np.ndarray | None = None
    unwrap_tolerance_m: float | None = None
    unwrap_weights: str = "inverse_variance"
    phasor_filter: str = "none"
    amplitude_test: str = "highest"
    dealias_tolerance_rad: float | None = None
    edge_filter: bool = False
    edge_delta_scale: float = 1.0

    def __post_init__(self) -> None:
        for name in ("min_amplitude_e", "min_amplitude_snr", "read_noise_e", "gain_noise"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float, np.number)) and not isinstance(value, bool)
                    and 0.0 <= value < math.inf):
                raise ConfigError(f"DecodeSettings: {name} must be a finite number >= 0, got {value!r}")
        if self.saturation_e is not None and not (isinstance(self.saturation_e, (int, float, np.number))
                                                  and self.saturation_e > 0):
            raise ConfigError(f"DecodeSettings: saturation_e must be > 0 (electrons) or None, "
                              f"got {self.saturation_e!r}")
        object.__setattr__(self, "range_m", _check_range(self.range_m))
        tolerance = self.unwrap_tolerance_m
        if tolerance is not None and not (isinstance(tolerance, (int, float, np.number)) and tolerance > 0):
            raise ConfigError(f"DecodeSettings: unwrap_tolerance_m must be > 0 (metres) or None, got {tolerance!r}")
        check_choice(self.unwrap_weights, UNWRAP_WEIGHTS, "DecodeSettings", "unwrap_weights")
        check_choice(self.phasor_filter, PHASOR_FILTERS, "DecodeSettings", "phasor_filter")
        check_choice(self.amplitude_test, AMPLITUDE_TESTS, "DecodeSettings", "amplitude_test")
        tol = self.dealias_tolerance_rad
        if tol is not None and not (isinstance(tol, (int, float, np.number)) and 0 < tol < math.inf):
            raise ConfigError(f"DecodeSettings: dealias_tolerance_rad must be > 0 (radians) or None, got {tol!r}")
        if not (isinstance(self.edge_delta_scale, (int, float, np.number)) and 0 < self.edge_delta_scale < math.inf):
            raise ConfigError(f"DecodeSettings: edge_delta_scale must be a finite number > 0, "
                              f"got {self.edge_delta_scale!r}")
        if not isinstance(self.edge_filter, bool):
            raise ConfigError(f"DecodeSettings: edge_filter must be True or False, got {self.edge_filter!r}")

    def replace(self, **changes) -> DecodeSettings:
        """A copy with ``changes`` (checked again)."""
        return dataclasses.replace(self, **changes)


def decode(raw: np.ndarray, modulation: Modulation, settings: DecodeSettings | None = None, *,
           check: bool = True) -> Decoded:
    """Decode raw images into radial distance, amplitude, offset, intensity, confidence and validity.

    Parameters
    ----------
    raw : (R, *shape) raw images in electrons, ordered as ``modulation.raw_labels()``.
    modulation : the sensor's :class:`Modulation`.
    settings : :class:`DecodeSettings` (default: all defaults). The phasor filter works on the last two axes
        (an image) of a CW sensor; its amplitude threshold is ``min_amplitude_e``.
    check : check that ``raw`` is finite (a read-back on a GPU); a render, whose raw images are finite by
        construction, passes False.

    Returns
    -------
    :class:`Decoded`; reasons in the precedence of the module docstring.
    """
    s = DecodeSettings() if settings is None else settings
    if not isinstance(s, DecodeSettings):
        raise ConfigError(f"decode: settings must be a DecodeSettings, got {type(s).__name__}")
    raw = check_raw(raw, modulation, finite=check)
    range_min, range_max = s.range_m
    xp = namespace(raw)
    edge_ok = None
    if modulation.is_cw:
        cw = decode_cw(raw, modulation, check=False)
        tested = cw.amplitude  # the amplitudes the thresholds read: the camera's filtered ones where it filters
        if s.phasor_filter == "bilateral":
            cw, tested, edge_ok = filtered_phases(cw, modulation, s.min_amplitude_e, edge_test=True)
        result = unwrap(cw, modulation, tolerance_m=s.unwrap_tolerance_m, weights=s.unwrap_weights)
        h = int(np.argmax(modulation.frequencies_hz))
        distance, amplitude, offset = result.distance, cw.amplitude[h], cw.offset[h]
        confidence, unwrap_failed = result.confidence, result.failed
        if s.dealias_tolerance_rad is not None:
            unwrap_failed = unwrap_failed | (result.dealias_rad > s.dealias_tolerance_rad)
        no_return = np.any(cw.amplitude <= NO_RETURN_RELATIVE_AMPLITUDE * cw.offset, axis=0)
        if s.amplitude_test == "every":
            low_amplitude = xp.zeros(amplitude.shape, dtype=bool)
            for i, steps in enumerate(modulation.phase_steps):
                floor = s.min_amplitude_snr * amplitude_noise_e(cw.offset[i], steps, s.read_noise_e, s.gain_noise)
                low_amplitude = low_amplitude | (tested[i] < s.min_amplitude_e) | (tested[i] < floor)
        else:
            noise_floor = s.min_amplitude_snr * amplitude_noise_e(offset, modulation.phase_steps[h],
                                                                  s.read_noise_e, s.gain_noise)
            low_amplitude = (tested[h] < s.min_amplitude_e) | (tested[h] < noise_floor)
    else:
        distance = decode_pulsed(raw, modulation, check=False)
        amplitude = raw[0] + raw[1]
        offset = 0.5 * amplitude
        no_return = ~(amplitude > 0)
        # Q1 + Q2 holds the ambient charge too, which two buckets cannot tell from signal: the noise floor is
        # that of a dark pixel (read noise of both buckets), min_amplitude_snr of it
        low_amplitude = (amplitude < s.min_amplitude_e) | (amplitude < s.min_amplitude_snr * math.sqrt(2.0)
                                                           * s.read_noise_e)
        confidence = xp.ones(amplitude.shape)
        unwrap_failed = xp.zeros(amplitude.shape, dtype=bool)
    saturated = (np.any(raw >= s.saturation_e, axis=0) if s.saturation_e is not None
                 else xp.zeros(amplitude.shape, dtype=bool))
    ranged = distance if s.range_scale is None else distance * xp.asarray(s.range_scale)
    with np.errstate(invalid="ignore"):  # NaN distances of no-return pixels compare False
        out_of_range = ~((ranged >= range_min) & (ranged <= range_max))
    checks = [(saturated, Reason.SATURATED), (no_return, Reason.NO_RETURN), (low_amplitude, Reason.LOW_AMPLITUDE),
              (unwrap_failed, Reason.UNWRAPPING_FAILED), (out_of_range, Reason.OUT_OF_RANGE)]
    if s.edge_filter and edge_ok is not None:
        # libfreenect2 filterPixelStage2: the depth of every pixel whose phases passed (out of range or not)
        # is a neighbour's evidence; the IR sum is the frequencies' filtered amplitudes summed
        phase_ok = ~(saturated | no_return | low_amplitude | unwrap_failed)
        raw_depth = np.where(phase_ok, ranged, np.nan)
        checks.append((processing_edge_filter(raw_depth, tested.sum(axis=0), edge_ok,
                                              delta_scale=s.edge_delta_scale), Reason.EDGE_FILTERED))
    reason = _first_reason(checks)
    valid = reason == int(Reason.VALID)
    return Decoded(distance=np.where(valid, distance, np.nan).astype(np.float32),
                   amplitude=amplitude.astype(np.float32), offset=offset.astype(np.float32),
                   intensity=raw.mean(axis=0).astype(np.float32),
                   confidence=np.where(valid, confidence, 0.0).astype(np.float32), valid=valid, reason=reason)


def filtered_phases(cw: CwDecoding, modulation: Modulation, min_amplitude_e: float, *, edge_test: bool = False):
    """``cw`` with every frequency's phase from its bilateral-filtered phasor A e^{iφ}; amplitude and offset
    stay the pixel's own (the IR image and the offset the camera reports).

    ``edge_test``: return ``(cw, filtered_amplitude, edge_ok)`` instead: the filtered phasors' amplitudes
    (F, *shape), which libfreenect2's amplitude thresholds read (``transformMeasurements`` after
    ``filterPixelStage1``), and where every frequency passed the filter's edge test (the neighbours'
    phase distances summing below :data:`tofcore.sensor.processing.BILATERAL_MAX_EDGE`)."""
    re, im = cw.amplitude * np.cos(cw.phase), cw.amplitude * np.sin(cw.phase)
    weights, dist_sum = bilateral_weights(re, im, min_amplitude=min_amplitude_e, edge_sum=True)
    real, imag = neighbour_mean(re, weights), neighbour_mean(im, weights)
    phase = np.mod(np.arctan2(imag, real), 2.0 * np.pi)
    phase = np.where(phase < 2.0 * np.pi, phase, 0.0)
    f_hz = namespace(phase).asarray(modulation.frequencies_hz).reshape((-1,) + (1,) * (phase.ndim - 1))
    out = CwDecoding(phase=phase, amplitude=cw.amplitude, offset=cw.offset,
                     wrapped_distance=SPEED_OF_LIGHT_M_S * phase / (4.0 * np.pi * f_hz))
    if not edge_test:
        return out
    return out, np.hypot(real, imag), np.all(dist_sum < BILATERAL_MAX_EDGE, axis=0)


def _first_reason(checks: list) -> np.ndarray:
    """uint8 reason per pixel: the first (mask, reason) pair that holds, else VALID (``np.select``, any backend)."""
    reason = namespace(checks[0][0]).full(checks[0][0].shape, int(Reason.VALID), np.uint8)
    for mask, code in reversed(checks):
        reason = np.where(mask, np.uint8(code), reason)
    return reason.astype(np.uint8)


def radial_to_z(distance: np.ndarray, ray_directions: np.ndarray) -> np.ndarray:
    """z-depth (float32) from radial distance: distance × the z-component of the unit pixel ray (sensor frame).

    Parameters
    ----------
    distance : (*shape) radial distance lens → surface in metres (NaN where invalid, stays NaN).
    ray_directions : (*shape, 3) unit ray directions in the sensor frame (x right, y down, z forward).
    """
    distance = asarray(distance, dtype=np.float64)
    directions = asarray(ray_directions)
    if directions.shape != distance.shape + (3,):
        raise ConfigError(f"radial_to_z: ray_directions must have shape {distance.shape + (3,)}, "
                          f"got {directions.shape}")
    return (distance * directions[..., 2].astype(np.float64)).astype(np.float32)  # only z made float64


def systematic_error_curve(modulation: Modulation, distances_m: np.ndarray) -> np.ndarray:
    """Noise- and ambient-free decoding error of each frequency against distance, in metres.

    Parameters
    ----------
    modulation : the sensor's modulation.
    distances_m : (n,) true radial distances in metres.

    Returns
    -------
    (F, n) float64: CW — wrapped distance of each frequency minus the truth, wrapped into
    [−d_amb/2, d_amb/2) (the square wave's "wiggling" error, §6.4); pulsed — (1, n) eq. 2.36 minus the truth.
    """
    distances_m = asarray(distances_m, dtype=np.float64)
    raw = ideal_raw(modulation, distances_m, 1.0)
    if not modulation.is_cw:
        return (decode_pulsed(raw, modulation) - distances_m)[None]
    d_amb = modulation.ambiguity_distances_m()[:, None]
    error = decode_cw(raw, modulation).wrapped_distance - distances_m
    return np.mod(error + d_amb / 2.0, d_amb) - d_amb / 2.0


# ------------------------------------------------------------------ checks
def check_raw(raw: np.ndarray, modulation: Modulation, *, finite: bool = True) -> np.ndarray:
    """``raw`` as float64 with its shape checked; and that it is finite (a read-back on a GPU) if ``finite``."""
    raw = asarray(raw, dtype=np.float64)
    if raw.ndim < 1 or raw.shape[0] != modulation.raw_count:
        raise ConfigError(f"decode: raw must have {modulation.raw_count} raw images on axis 0 "
                          f"({', '.join(modulation.raw_labels())}), got shape {raw.shape}")
    if finite and not bool(np.isfinite(raw).all()):
        raise ConfigError("decode: raw must be finite electrons, got a NaN or inf value")
    return raw


def _check_range(range_m: tuple[float, float]) -> tuple[float, float]:
    try:
        range_min, range_max = (float(x) for x in range_m)
    except (TypeError, ValueError):
        raise ConfigError(f"DecodeSettings: range_m must be (min, max) in metres, got {range_m!r}") from None
    if not 0.0 <= range_min < range_max:
        raise ConfigError(f"DecodeSettings: range_m must satisfy 0 <= min < max (metres), got {range_m!r}")
    return range_min, range_max
