"""How the sensor modulates its LEDs and gates its pixels: the correlation functions g_j(τ).

======================  ====  ========  ===================================================================
name                    unit  default   meaning
======================  ====  ========  ===================================================================
``kind``                –     –         ``"pulsed"`` (eq. 2.35–2.37), ``"cw_square"`` (eq. 2.38, 2.44) or
                                        ``"cw_sine"`` (eq. 2.45–2.49, 5.3)
``frequencies_hz``      Hz    ()        CW: modulation frequencies in acquisition order, e.g. (80e6, 16e6, 120e6);
                                        pulsed: must be empty
``phase_steps``         –     4 each    CW: phase steps N per frequency (each >= 3); pulsed: must be empty
``exposure_s``          s     1 ms      CW: total integration time per frequency, split evenly over its steps;
                                        pulsed: one value, shared by both buckets (they integrate together)
``duty_cycle``          1     0.5       cw_square: fraction of the period the LED is on, in (0, 1);
                                        pulsed: t0 / pulse repetition period, in (0, 0.5]; cw_sine: unused (0.5)
``pulse_width_s``       s     None      pulsed: pulse width t0 (d_max = c t0 / 2, eq. 2.37); CW: must be None
======================  ====  ========  ===================================================================

Normalisation (the contract with :mod:`tofcore.tracer.transport` and the sensor)
---------------------------------------------------------------------------
The emitted optical power is :math:`P(t) = \\bar P \\, m(t)` with :math:`m(t) \\ge 0` of mean 1 over a
period. Raw image j integrates the received light through a 0/1 gate :math:`G_j(t)`, and

.. math:: g_j(\\tau) = \\frac{1}{T} \\int_0^T m(t - \\tau) \\, G_j(t) \\, \\mathrm{d}t

so the charge per unit time of raw image j is (received mean signal) · g_j(τ), and unmodulated ambient light
adds (ambient) · :meth:`Modulation.gate_duty`. Raw images are ordered frequency-major, then phase step.

CW gates and sign convention (thesis eq. 2.47–2.49): step k of N opens the gate for half a period starting at
k/N of the period, :math:`G_k(t) = 1` for :math:`(f t - k/N) \\bmod 1 < 1/2`. The sine source is
:math:`m(t) = 1 + \\sin(2 \\pi f t)` (eq. 2.45 with I = c_o = 1); the square source is the 0/1 wave of the
same phase (on while :math:`\\sin(2\\pi f t) > 0` for duty 0.5), scaled to mean 1, its pulse centred on a
quarter period for any duty. Then :math:`g_k(\\tau) = \\tfrac12 + \\tfrac1\\pi \\cos(\\varphi - 2\\pi k/N)`
for the sine, :math:`\\varphi = 2 \\pi f \\tau`, and for N = 4 the steps k = 0, 1, 2, 3 are the thesis's
buckets C1, C3, C2, C4 (offsets 0, t0/2, t0, 3t0/2 with t0 = 1/(2f), eq. 2.44), so eq. 2.38
:math:`\\varphi = \\operatorname{atan2}(Q_3 - Q_4, Q_1 - Q_2)` is the DFT phase of the steps.

Example
-------
>>> kinect = Modulation(kind="cw_square", frequencies_hz=(80e6, 16e6, 120e6), phase_steps=(3, 3, 3),
...                     exposure_s=(8e-3, 4e-3, 8e-3))
>>> round(kinect.unambiguous_range_m(), 3)
18.737
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .. import limits
from ..backend import asarray, is_device_array, namespace
from ..backend import device_twin
from ..constants import SPEED_OF_LIGHT_M_S
from ..errors import ConfigError, is_number

KINDS = ("pulsed", "cw_square", "cw_sine")
DEFAULT_PHASE_STEPS = 4
DEFAULT_EXPOSURE_S = 1e-3

Correlation = Callable[[np.ndarray], np.ndarray]


# ------------------------------------------------------------------ correlation functions
def phasor_component(tau_s: np.ndarray, f_hz: float, quarter: int) -> np.ndarray:
    """cos(2πfτ) (``quarter`` = 0) or sin(2πfτ) (``quarter`` = 1): one component of the phasor e^{i2πfτ}.

    For transient/phasor work outside a sensor model (the cross-check against mitransient's phasor film):
    :func:`phasor_correlations` gives them as picklable correlation functions.
    """
    return np.cos(2.0 * np.pi * f_hz * asarray(tau_s, dtype=np.float64) - 0.5 * np.pi * quarter)


def phasor_correlations(frequencies_hz) -> list:
    """[cos, sin] correlation functions per frequency, τ in seconds: Σ w e^{i2πfL/c} from two channels.

    ``functools.partial`` objects of :func:`phasor_component`, so they pickle (the tracer's worker
    processes need that; lambdas make it fall back to threads).
    """
    return [functools.partial(phasor_component, f_hz=float(f), quarter=q) for f in frequencies_hz for q in (0, 1)]


def sine_correlation(tau_s: np.ndarray, f_hz: float, offset_fraction: float) -> np.ndarray:
    """Correlation of the sine source with a half-period gate opening at ``offset_fraction`` of the period.

    Parameters
    ----------
    tau_s : delays τ in seconds (float64 array).
    f_hz : modulation frequency f in Hz.
    offset_fraction : gate opening k/N as a fraction of the period.

    Returns
    -------
    g(τ), same shape as ``tau_s``, in [0, 1]; its mean over τ is the gate duty 1/2.

    Notes
    -----
    Thesis eq. 2.47–2.48 (and eq. 5.3) with :math:`m(t) = 1 + \\sin(2\\pi f t)` and the gate
    :math:`[k/(Nf), k/(Nf) + 1/(2f))`, divided by the period:

    .. math:: g(\\tau) = \\frac12 + \\frac1\\pi \\cos\\big(2\\pi (f\\tau - k/N)\\big)
    """
    return 0.5 + np.cos(2.0 * np.pi * (f_hz * asarray(tau_s, dtype=np.float64) - offset_fraction)) / np.pi


@device_twin(on="tau_s")
def square_correlation(tau_s: np.ndarray, f_hz: float, offset_fraction: float, duty: float) -> np.ndarray:
    """Correlation of the square source (duty ``duty``) with a half-period gate opening at ``offset_fraction``.

    Parameters
    ----------
    tau_s : delays τ in seconds (float64 array).
    f_hz : modulation frequency f in Hz.
    offset_fraction : gate opening k/N as a fraction of the period.
    duty : fraction D of the period the LED is on, in (0, 1); the pulse has height 1/D (mean 1).

    Returns
    -------
    g(τ), same shape as ``tau_s``: periodic in τ with period 1/f (the gate integrates all previous
    periods, SPEC §3), a triangle for D = 1/2 and a trapezoid otherwise; its mean over τ is 1/2.

    Notes
    -----
    The circular overlap of the light pulse (length D, centred on a quarter period) with the gate
    (length 1/2, centred on k/N + 1/4), both in cycles, depends only on the circular distance
    :math:`u = |((f\\tau - k/N + 1/2) \\bmod 1) - 1/2|` between their centres:

    .. math:: g(\\tau) = \\frac1D \\operatorname{clip}\\!\\big(\\tfrac14 + \\tfrac D2 - u,\\;
              \\max(0, D - \\tfrac12),\\; \\min(D, \\tfrac12)\\big)

    This is the closed form of the thesis's loop over previous pulses (§5.1.2, listing after eq. 5.2).
    """
    shifted = f_hz * asarray(tau_s, dtype=np.float64) - offset_fraction + 0.5
    u = np.abs(shifted - np.floor(shifted) - 0.5)  # x − ⌊x⌋ is np.mod(x, 1.0) bit for bit, and faster
    return np.clip(0.25 + 0.5 * duty - u, max(0.0, duty - 0.5), min(duty, 0.5)) / duty


def pulsed_correlation(tau_s: np.ndarray, pulse_width_s: float, bucket: int) -> np.ndarray:
    """Correlation of one pulse of width t0 with bucket C_{bucket+1}, open during [bucket·t0, (bucket+1)·t0).

    Parameters
    ----------
    tau_s : delays τ in seconds (float64 array).
    pulse_width_s : pulse width t0 in seconds.
    bucket : 0 for C1 (gate [0, t0)), 1 for C2 (gate [t0, 2 t0)).

    Returns
    -------
    g(τ), same shape as ``tau_s``: the overlap of [τ, τ + t0) with the gate divided by t0. Not periodic:
    light delayed by more than (bucket + 1)·t0 falls in no bucket (the repetition period is assumed long
    enough that the next pulse does not reach back).

    Notes
    -----
    Thesis eq. 2.35–2.37. The pulse has height 1/D over a repetition period t0/D (mean 1), so the D cancels:

    .. math:: g_b(\\tau) = \\operatorname{clip}(1 - |\\tau / t_0 - b|, 0, 1), \\qquad
              g_0 + g_1 = 1 \\text{ for } 0 \\le \\tau \\le t_0,

    and :math:`Q_2/(Q_1 + Q_2) = \\tau / t_0` (eq. 2.35) without ambient light.
    """
    return np.clip(1.0 - np.abs(asarray(tau_s, dtype=np.float64) / pulse_width_s - bucket), 0.0, 1.0)


def harmonic_correlation(tau_s: np.ndarray, f_hz: float, cos_terms: tuple, sin_terms: tuple) -> np.ndarray:
    """A custom periodic correlation given by its Fourier series (a measured waveform's harmonics).

    Parameters
    ----------
    tau_s : delays τ in seconds (float64 array).
    f_hz : fundamental frequency f in Hz.
    cos_terms : (a₀, a₁, …, a_N): the mean a₀ and the cosine amplitude of each harmonic n = 1 … N.
    sin_terms : (b₁, …, b_N): the sine amplitude of each harmonic (as many as ``cos_terms`` has harmonics).

    Returns
    -------
    g(τ), same shape as ``tau_s``.

    Notes
    -----
    .. math:: g(\\tau) = a_0 + \\sum_{n=1}^{N} a_n \\cos(n \\varphi) + b_n \\sin(n \\varphi),
              \\qquad \\varphi = 2 \\pi f \\tau

    summed in n order. Real ToF correlations are sums of a few harmonics (Keller 2015, Giancola et al. 2018:
    the square wave's odd harmonics make the "wiggling" error); :func:`sine_correlation` is
    a₀ = ½, a₁ = cos(2πk/N)/π, b₁ = sin(2πk/N)/π. Data, not code: the compiled tracer evaluates the same
    series (:mod:`tofcore.compiled.setup`).
    """
    phase = 2.0 * np.pi * f_hz * asarray(tau_s, dtype=np.float64)
    out = namespace(phase).full(phase.shape, float(cos_terms[0]))
    for n, (a, b) in enumerate(zip(cos_terms[1:], sin_terms), start=1):
        out = out + (a * np.cos(n * phase) + b * np.sin(n * phase))
    return out


def tabulated_correlation(tau_s: np.ndarray, period_s: float, values: tuple) -> np.ndarray:
    """A custom periodic correlation given as M samples over one period, linearly interpolated.

    Parameters
    ----------
    tau_s : delays τ in seconds (float64 array).
    period_s : the period T in seconds (1/f of a CW camera).
    values : (g(0), g(T/M), …, g((M − 1)T/M)): the samples, M ≥ 2.

    Returns
    -------
    g(τ), same shape as ``tau_s``.

    Notes
    -----
    With :math:`x = M \\,\\mathrm{frac}(\\tau / T)`, :math:`i = \\lfloor x \\rfloor`, :math:`t = x - i`:

    .. math:: g(\\tau) = g_i (1 - t) + g_{(i + 1) \\bmod M} \\, t

    The interpolation error is at most :math:`h^2 \\max|g''| / 8` with :math:`h = T / M`
    (:func:`tabulate` makes such a table from any function). Data, not code: the compiled tracer evaluates
    the same table (:mod:`tofcore.compiled.setup`).
    """
    m = len(values)
    cycles = asarray(tau_s, dtype=np.float64) / period_s
    x = (cycles - np.floor(cycles)) * m
    i = np.floor(x)
    t = x - i
    i0 = i.astype(np.int64) % m
    table = namespace(t).asarray(np.asarray(values, dtype=np.float64))
    return table[i0] * (1.0 - t) + table[(i0 + 1) % m] * t


def tabulate(g: Correlation, period_s: float, samples: int = 4096) -> Correlation:
    """A periodic correlation function ``g`` as :func:`tabulated_correlation` data (``samples`` per period),
    which the compiled tracer runs: the samples are ``g`` at τ = i T / M.

    Interpolation error ≤ (T/M)² max|g''| / 8: for a sine of period T and M = 4096, 2.9e-7 of its amplitude.
    """
    if not (is_number(period_s) and period_s > 0) or not isinstance(samples, int) or samples < 2:
        raise ConfigError(f"tabulate: period_s must be > 0 and samples an integer >= 2, got {period_s!r}, "
                          f"{samples!r}")
    values = np.asarray(g(np.arange(samples) * (period_s / samples)), dtype=np.float64)
    if values.shape != (samples,) or not np.isfinite(values).all():
        raise ConfigError(f"tabulate: g must return {samples} finite values for {samples} delays, "
                          f"got shape {values.shape}")
    return functools.partial(tabulated_correlation, period_s=float(period_s), values=tuple(values.tolist()))


def harmonic(f_hz: float, cos_terms, sin_terms) -> Correlation:
    """:func:`harmonic_correlation` with its coefficients checked, as a correlation function the compiled
    tracer runs."""
    a = tuple(float(x) for x in cos_terms)
    b = tuple(float(x) for x in sin_terms)
    if not (is_number(f_hz) and f_hz > 0) or len(a) < 1 or len(b) != len(a) - 1 \
            or not np.isfinite(a + b).all():
        raise ConfigError(f"harmonic: f_hz must be > 0, cos_terms (a0, a1 … aN) and sin_terms (b1 … bN) finite, "
                          f"got f_hz={f_hz!r}, {len(a)} cos and {len(b)} sin terms")
    return functools.partial(harmonic_correlation, f_hz=float(f_hz), cos_terms=a, sin_terms=b)


@dataclass(frozen=True, kw_only=True)
class CorrelationBank:
    """The correlation functions of all raw images, evaluated together: ``bank(tau_s)`` → (R, N).

    Raw images are frequency-major, then step, as in :meth:`Modulation.correlations`, whose values it
    reproduces bit for bit. On the CPU each frequency's steps are one (N_steps, N) block computed in
    place from :math:`f\tau` formed once (the Kinect's 9 channels: 3.98 → 1.11 ms per 65 k delays,
    ``bench/bench_kernels.py``);
    device arrays go through the per-channel fused kernels. A frozen dataclass of numbers, so it
    pickles for the tracer's worker processes.
    """

    kind: str
    frequencies_hz: tuple[float, ...]
    offsets: tuple[tuple[float, ...], ...]  # CW: per frequency, the gate openings k/N
    duty_cycle: float
    pulse_width_s: float | None

    def __len__(self) -> int:
        return 2 if self.kind == "pulsed" else sum(len(o) for o in self.offsets)

    def functions(self) -> list[Correlation]:
        """The same channels as a list of g_j(τ) (:meth:`Modulation.correlations`)."""
        if self.kind == "pulsed":
            return [functools.partial(pulsed_correlation, pulse_width_s=self.pulse_width_s, bucket=b)
                    for b in (0, 1)]
        if self.kind == "cw_sine":
            return [functools.partial(sine_correlation, f_hz=f, offset_fraction=o)
                    for f, offsets in zip(self.frequencies_hz, self.offsets) for o in offsets]
        return [functools.partial(square_correlation, f_hz=f, offset_fraction=o, duty=self.duty_cycle)
                for f, offsets in zip(self.frequencies_hz, self.offsets) for o in offsets]

    def __call__(self, tau_s) -> np.ndarray:
        if is_device_array(tau_s):
            xp = namespace(tau_s)
            return xp.stack([g(tau_s) for g in self.functions()])
        tau_s = np.asarray(tau_s, dtype=np.float64)
        out = np.empty((len(self),) + tau_s.shape)
        if self.kind == "pulsed":
            scaled = tau_s / self.pulse_width_s
            for bucket in (0, 1):  # clip(1 − |τ/t0 − b|, 0, 1), eq. 2.35–2.37
                np.clip(1.0 - np.abs(scaled - bucket), 0.0, 1.0, out=out[bucket])
            return out
        j = 0
        for f_hz, offsets in zip(self.frequencies_hz, self.offsets):
            block = out[j:j + len(offsets)]
            j += len(offsets)
            cycles = f_hz * tau_s
            steps = np.array(offsets).reshape((-1,) + (1,) * tau_s.ndim)  # broadcast against τ of any shape
            if self.kind == "cw_sine":  # ½ + cos(2π(fτ − k/N))/π, eq. 2.47–2.48
                np.subtract(cycles, steps, out=block)
                block *= 2.0 * np.pi
                np.cos(block, out=block)
                block /= np.pi
                block += 0.5
                continue
            # clip(¼ + D/2 − |frac(fτ − k/N + ½) − ½|, max(0, D − ½), min(D, ½)) / D: square_correlation
            shifted = np.subtract(cycles, steps)
            shifted += 0.5
            np.floor(shifted, out=block)
            np.subtract(shifted, block, out=block)
            block -= 0.5
            np.abs(block, out=block)
            np.subtract(0.25 + 0.5 * self.duty_cycle, block, out=block)
            np.clip(block, max(0.0, self.duty_cycle - 0.5), min(self.duty_cycle, 0.5), out=block)
            block /= self.duty_cycle
        return out


# ------------------------------------------------------------------ configuration
def _positive_tuple(name: str, values: object) -> tuple[float, ...]:
    try:
        items = tuple(values)  # type: ignore[arg-type]
    except TypeError:
        raise ConfigError(f"Modulation: {name} must be a sequence of numbers, got {values!r}") from None
    for value in items:
        if not is_number(value) or not math.isfinite(value) or value <= 0:
            raise ConfigError(f"Modulation: {name} must be finite numbers > 0, got {values!r}")
        if value > limits.MAX_MAGNITUDE:
            raise ConfigError(f"Modulation: {name} must be numbers <= {limits.MAX_MAGNITUDE:g}, got {values!r}")
    return tuple(float(value) for value in items)


def _steps_tuple(values: object) -> tuple[int, ...]:
    items = tuple(values) if isinstance(values, (tuple, list, np.ndarray)) else None
    if items is None or not all(isinstance(n, (int, np.integer)) and not isinstance(n, bool) and n >= 3
                                for n in items):
        raise ConfigError(f"Modulation: phase_steps must be a sequence of integers >= 3, got {values!r}")
    return tuple(int(n) for n in items)


@dataclass(frozen=True, kw_only=True)
class Modulation:
    """A sensor's modulation and gating; see the module docstring for the parameters and normalisation."""

    kind: str
    frequencies_hz: tuple[float, ...] = ()
    phase_steps: tuple[int, ...] = ()
    exposure_s: tuple[float, ...] = ()
    duty_cycle: float = 0.5
    pulse_width_s: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ConfigError(f"Modulation: kind must be one of {list(KINDS)}, got {self.kind!r}")
        frequencies = _positive_tuple("frequencies_hz", self.frequencies_hz)
        exposures = _positive_tuple("exposure_s", self.exposure_s)
        steps = _steps_tuple(self.phase_steps)
        if not is_number(self.duty_cycle) or not math.isfinite(self.duty_cycle):
            raise ConfigError(f"Modulation: duty_cycle must be a finite number, got {self.duty_cycle!r}")
        if self.kind == "pulsed":
            self._check_pulsed(frequencies, steps, exposures)
            exposures = exposures or (DEFAULT_EXPOSURE_S,)
        else:
            self._check_cw(frequencies, steps, exposures)
            steps = steps or (DEFAULT_PHASE_STEPS,) * len(frequencies)
            exposures = exposures or (DEFAULT_EXPOSURE_S,) * len(frequencies)
        raw_images = sum(steps) if self.kind != "pulsed" else 2
        limits.MAX_RAW_IMAGES.check(raw_images, "Modulation", "phase_steps (raw images per frame)", list(steps))
        object.__setattr__(self, "frequencies_hz", frequencies)
        object.__setattr__(self, "phase_steps", steps)
        object.__setattr__(self, "exposure_s", exposures)
        object.__setattr__(self, "duty_cycle", float(self.duty_cycle))

    def _check_pulsed(self, frequencies: tuple, steps: tuple, exposures: tuple) -> None:
        width = self.pulse_width_s
        if width is None or not is_number(width) or not math.isfinite(width) or width <= 0:
            raise ConfigError(f"Modulation: pulse_width_s must be a finite number > 0 (seconds) for kind 'pulsed', "
                              f"got {width!r}")
        object.__setattr__(self, "pulse_width_s", float(width))
        if frequencies or steps:
            raise ConfigError(f"Modulation: frequencies_hz and phase_steps must be empty for kind 'pulsed', "
                              f"got {frequencies!r} and {steps!r}")
        if len(exposures) > 1:
            raise ConfigError(f"Modulation: exposure_s must be one value for kind 'pulsed', got {exposures!r}")
        if not 0.0 < self.duty_cycle <= 0.5:
            raise ConfigError(f"Modulation: duty_cycle must be in (0, 0.5] (t0 / repetition period) for kind "
                              f"'pulsed', got {self.duty_cycle!r}")

    def _check_cw(self, frequencies: tuple, steps: tuple, exposures: tuple) -> None:
        if not frequencies:
            raise ConfigError(f"Modulation: frequencies_hz must be at least one frequency > 0 (Hz) for kind "
                              f"{self.kind!r}, got {self.frequencies_hz!r}")
        for name, values in (("phase_steps", steps), ("exposure_s", exposures)):
            if values and len(values) != len(frequencies):
                raise ConfigError(f"Modulation: {name} must have one value per frequency ({len(frequencies)}) "
                                  f"or be empty, got {values!r}")
        if self.pulse_width_s is not None:
            raise ConfigError(f"Modulation: pulse_width_s must be None for kind {self.kind!r} (the pulse is "
                              f"set by frequency and duty_cycle), got {self.pulse_width_s!r}")
        if self.kind == "cw_square" and not 0.0 < self.duty_cycle < 1.0:
            raise ConfigError(f"Modulation: duty_cycle must be in (0, 1) for kind 'cw_square', got {self.duty_cycle!r}")
        if self.kind == "cw_sine" and self.duty_cycle != 0.5:
            raise ConfigError(f"Modulation: duty_cycle must be 0.5 (unused) for kind 'cw_sine', got {self.duty_cycle!r}")

    # -------------------------------------------------------------- raw images
    @property
    def is_cw(self) -> bool:
        """True for the continuous-wave kinds."""
        return self.kind != "pulsed"

    @property
    def raw_count(self) -> int:
        """Number R of raw images per frame (Σ phase steps for CW, 2 for pulsed)."""
        return sum(self.phase_steps) if self.is_cw else 2

    def step_offsets(self) -> tuple[np.ndarray, ...]:
        """CW: per frequency, the gate openings k/N (fractions of the period) of its N steps."""
        return tuple(np.arange(n) / n for n in self.phase_steps)

    def correlations(self) -> list[Correlation]:
        """The correlation functions g_j(τ), one per raw image, frequency-major then step.

        Each maps delays τ in seconds (float64 array) to g_j(τ) of the same shape; the normalisation is
        in the module docstring (charge per unit time = received mean signal · g_j). The callables are
        :func:`functools.partial` objects of :func:`sine_correlation`, :func:`square_correlation` and
        :func:`pulsed_correlation`, so they pickle.
        """
        return self.correlation_bank().functions()

    def correlation_bank(self) -> CorrelationBank:
        """All raw images' g_j(τ) as one callable τ → (R, N): what the tracer evaluates per contribution.

        The same values bit for bit as :meth:`correlations`, evaluated per frequency as one block.
        """
        return CorrelationBank(kind=self.kind, frequencies_hz=self.frequencies_hz, offsets=tuple(
            tuple(float(o) for o in offsets) for offsets in self.step_offsets()) if self.is_cw else (),
            duty_cycle=self.duty_cycle, pulse_width_s=self.pulse_width_s)

    def gate_duty(self) -> np.ndarray:
        """(R,) fraction of time each raw image's gate is open: 1/2 for CW, the duty cycle t0/T for pulsed.

        Ambient (unmodulated) charge per unit time of raw image j = ambient · gate_duty[j].
        """
        return np.full(self.raw_count, 0.5 if self.is_cw else self.duty_cycle)

    def raw_labels(self) -> tuple[str, ...]:
        """R names of the raw images, e.g. ``"f80MHz_s0"`` (CW) or ``"pulsed_C1"``."""
        if not self.is_cw:
            return ("pulsed_C1", "pulsed_C2")
        return tuple(f"f{f_hz / 1e6:g}MHz_s{k}" for f_hz, n in zip(self.frequencies_hz, self.phase_steps)
                     for k in range(n))

    def raw_exposure_s(self) -> np.ndarray:
        """(R,) integration time of each raw image in seconds (CW: the frequency's exposure / its steps)."""
        if not self.is_cw:
            return np.full(2, self.exposure_s[0])
        return np.concatenate([np.full(n, t / n) for t, n in zip(self.exposure_s, self.phase_steps)])

    # -------------------------------------------------------------- ranges
    def ambiguity_distances_m(self) -> np.ndarray:
        """Per frequency d_amb = c / (2 f) in metres (eq. 2.42); pulsed: (d_max,) = (c t0 / 2,) (eq. 2.37)."""
        if not self.is_cw:
            return np.array([SPEED_OF_LIGHT_M_S * self.pulse_width_s / 2.0])
        return SPEED_OF_LIGHT_M_S / (2.0 * asarray(self.frequencies_hz))

    def unambiguous_range_m(self) -> float:
        """Distance up to which the depth is unique, in metres.

        CW: c / (2 f_beat) with the beat frequency f_beat = gcd of the frequencies rounded to whole hertz
        (§2.2.2; Kinect v2: gcd(80, 16, 120) MHz = 8 MHz → 18.737 m). Pulsed: c t0 / 2 (eq. 2.37).
        """
        if not self.is_cw:
            return SPEED_OF_LIGHT_M_S * self.pulse_width_s / 2.0
        beat_hz = math.gcd(*(max(1, round(f)) for f in self.frequencies_hz))
        return SPEED_OF_LIGHT_M_S / (2.0 * beat_hz)


def ideal_raw(modulation: Modulation, distance_m: np.ndarray, signal_e: np.ndarray | float,
              ambient_e: np.ndarray | float = 0.0) -> np.ndarray:
    """Noise-free raw images (R, *shape) of a single return at radial distance ``distance_m``.

    Parameters
    ----------
    modulation : the sensor's modulation.
    distance_m : radial distance(s) d in metres; the delay is τ = 2 d / c (eq. 2.34).
    signal_e : received mean signal S in electrons (charge of the raw image per unit g_j).
    ambient_e : ambient charge A_amb in electrons per unit gate duty.

    Returns
    -------
    float64 array with :math:`Q_j = S \\, g_j(2 d / c) + A_{amb} \\, \\mathrm{gate\\_duty}_j`.
    """
    tau_s = 2.0 * asarray(distance_m, dtype=np.float64) / SPEED_OF_LIGHT_M_S
    duty = modulation.gate_duty()
    return np.stack([asarray(signal_e, dtype=np.float64) * g(tau_s) + ambient_e * duty[j]
                     for j, g in enumerate(modulation.correlations())])
