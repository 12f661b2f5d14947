r"""A time budget that is used: the next pass sized from the measured cost of the passes so far.

A trace whose :class:`~tofcore.tracer.trace.PassPolicy` has a ``time_budget_s`` (a render with one) runs
progressive passes (:func:`tofcore.tracer.trace.pass_schedule`: 1, 1, 2, 4, 8, 16, 16, … samples per pixel),
and its :class:`~tofcore.tracer.trace.PassSchedule` asks this module for each pass's size. Before each
pass, :class:`TimeBudget` models the cost of one pass cycle (tracing, the error estimate, the adaptive
allocation, an intermediate frame) as

.. math:: t(n) = a + b\,n,

n the mean samples per pixel the pass actually traced (the adaptive sampler's allocation included),
a the fixed cost of a pass and b the seconds per sample per pixel, fitted by least squares to the
passes so far but the first.
The first pass's cost is mostly warm-up (the compiled tracer loads its kernels then), so it is left out
of the fit; until a second pass is measured, the next pass (the schedule's second, 1 sample per pixel)
runs whenever any time is left. Then the next pass gets the scheduled size if it fits in what is left,
else the largest size that fits,

.. math:: n = \lfloor (T - t_\text{elapsed} - t_\text{frame} - a) / b \rfloor,

T the budget and :math:`t_\text{frame}` the cost of building the final frame: the latest frame's
measured build where the render built one after every pass, else :data:`FRAME_PER_ESTIMATE` times the
measured cost of the latest error estimate (both decode the frame's raw images). 0 ends the render. So the budget is used up to about one sample per pixel (plus the model's error), and it is
exceeded by at most one small pass (the first two, of 1 sample per pixel each, run unmeasured) or the
error of one pass's prediction.

Pass sizes only change which pass a sample belongs to, never the sample: each pixel's samples keep their
indices 0, 1, 2, … (:mod:`tofcore.tracer.qmc`), so the replicate structure of the error estimate
(sample i in replicate i mod R) and the adaptive rules (:mod:`tofcore.tracer.estimator`: a uniform pilot,
then multiples of R per pixel) hold for any sizes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

FRAME_PER_ESTIMATE = 3.0
"""A final frame's build (decode, every max path length's decode, noise) in units of one error estimate
(``tofcore.render.depth_standard_error``); measured 2.2–3.5 on the demo room at 512 × 424, max_depth 5
(2 loaded cores, 3 repeats)."""


def pass_cost_model(samples: list[float], seconds: list[float]) -> tuple[float, float]:
    """(a, b) of t(n) = a + b·n fitted to passes of ``samples`` mean samples per pixel that took ``seconds``.

    Least squares over passes of at least two different sizes; otherwise (or when the fit gives a < 0 or
    b ≤ 0, noise in small passes) a = 0 and b = Σt / Σn, which charges the fixed cost to the samples and so
    errs towards smaller passes.
    """
    n = np.asarray(samples, np.float64)
    t = np.asarray(seconds, np.float64)
    if n.size == 0 or n.sum() <= 0:
        raise ValueError("pass_cost_model: needs at least one pass with samples")
    if np.ptp(n) > 0:
        b, a = np.polyfit(n, t, 1)
        if a >= 0 and b > 0:
            return float(a), float(b)
    return 0.0, float(t.sum() / n.sum())


def budgeted_pass(scheduled: int, remaining_s: float, a: float, b: float) -> int:
    """Samples per pixel of the next pass: ``scheduled`` if a + b·scheduled fits in ``remaining_s``, else
    the largest n that fits (0: no pass fits, the render ends)."""
    fits = int(np.floor((remaining_s - a) / b)) if remaining_s > a else 0
    return max(0, min(scheduled, fits))


@dataclass
class TimeBudget:
    """The passes of one render against its budget: record each pass, ask for the next pass's size.

    ``budget_s`` counts from the render's start (scene set-up, first hits and every pass included) to the
    final frame.
    """

    budget_s: float
    samples: list[float] = field(default_factory=list)   # mean samples per pixel each pass traced
    seconds: list[float] = field(default_factory=list)   # each pass's cycle, s
    frame_s: float | None = None                          # the latest frame's build, s, if one was built
    estimate_s: float = 0.0                               # the latest error estimate's, s

    def record(self, samples_per_pixel: float, seconds: float) -> None:
        """One finished pass: its mean samples per pixel and the seconds of its whole cycle."""
        self.samples.append(float(samples_per_pixel))
        self.seconds.append(float(seconds))

    def next_pass(self, scheduled: int, elapsed_s: float) -> int:
        """Samples per pixel for the next pass (≤ ``scheduled``; 0 ends the render), ``elapsed_s`` since
        the render's start."""
        frame_s = FRAME_PER_ESTIMATE * self.estimate_s if self.frame_s is None else self.frame_s
        remaining_s = self.budget_s - elapsed_s - frame_s
        if len(self.samples) < 2:  # nothing measured yet, or only the warm-up: one more small pass if time is left
            return scheduled if remaining_s > 0 else 0
        a, b = pass_cost_model(self.samples[1:], self.seconds[1:])
        return budgeted_pass(scheduled, remaining_s, a, b)
