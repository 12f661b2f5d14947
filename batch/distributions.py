"""Distributions of a set file's randomized values: parsing with set-file errors, sampling, and their moments.

A randomized value (a material's reflectance, an object's size, the camera's distance …) is written
in the set file as a number (a constant) or a table naming its distribution:

===============  ======================================  ==================================================
``dist``         keys                                    density on its support
===============  ======================================  ==================================================
``"uniform"``    ``low``, ``high``                       :math:`1/(b-a)` on :math:`[a, b]`
``"normal"``     ``mean``, ``std`` [, ``low``, ``high``]  :math:`\\mathcal N(\\mu, \\sigma^2)`, truncated to
                                                         [low, high] (and to the value's valid range) by
                                                         rejection
``"loguniform"`` ``low``, ``high`` (both > 0)            :math:`1/(x \\ln(b/a))` on :math:`[a, b]`
``"choice"``     ``values`` [, ``weights``]              :math:`P(v_i) = w_i / \\sum w` (equal weights by default)
===============  ======================================  ==================================================

Every value has a valid range (a material's ``roughness`` is in [0, π/2]): a uniform, log-uniform or
choice support outside it is refused when the file is read, naming the key; a normal is truncated to it.

Sampling takes a ``numpy.random.Generator`` (the frame's stream): the same stream gives the same value.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from tofcore.errors import is_number

KINDS = ("uniform", "normal", "loguniform", "choice")
_KEYS = {"uniform": ("dist", "low", "high"), "normal": ("dist", "mean", "std", "low", "high"),
         "loguniform": ("dist", "low", "high"), "choice": ("dist", "values", "weights")}
#: Draws a truncated normal may take before the file is refused (its mass inside the bounds is too small).
MAX_REJECTIONS = 1000


@dataclass(frozen=True)
class Distribution:
    """One randomized value: ``kind`` (a constant is a choice of one value) and its parameters."""

    kind: str
    low: float = -math.inf
    high: float = math.inf
    mean: float = 0.0
    std: float = 0.0
    values: tuple[float, ...] = ()
    weights: tuple[float, ...] = ()

    def sample(self, rng: np.random.Generator) -> float:
        """One value drawn from ``rng`` (see the module docstring); RuntimeError when a truncated normal
        finds no value within :data:`MAX_REJECTIONS` draws (refused at parse time when its mass is tiny)."""
        if self.kind == "uniform":
            return float(self.low + (self.high - self.low) * rng.random())
        if self.kind == "loguniform":
            return float(math.exp(math.log(self.low) + (math.log(self.high) - math.log(self.low)) * rng.random()))
        if self.kind == "choice":
            if len(self.values) == 1:
                return float(self.values[0])
            p = np.asarray(self.weights, dtype=np.float64)
            return float(self.values[int(rng.choice(len(self.values), p=p / p.sum()))])
        for _ in range(MAX_REJECTIONS):
            value = self.mean + self.std * rng.standard_normal()
            if self.low <= value <= self.high:
                return float(value)
        raise RuntimeError(f"a normal ({self.mean}, {self.std}) truncated to [{self.low}, {self.high}] gave no "
                           f"value in {MAX_REJECTIONS} draws")

    def as_dict(self) -> dict:
        """The plain description (for job identities and the dataset card)."""
        if self.kind == "choice":
            return {"dist": "choice", "values": list(self.values), "weights": list(self.weights)}
        if self.kind == "normal":
            return {"dist": "normal", "mean": self.mean, "std": self.std,
                    "low": None if math.isinf(self.low) else self.low,
                    "high": None if math.isinf(self.high) else self.high}
        return {"dist": self.kind, "low": self.low, "high": self.high}

    def cdf(self, x: np.ndarray) -> np.ndarray:
        """P(X ≤ x) (uniform, log-uniform and truncated normal; for tests of the sampler)."""
        x = np.asarray(x, dtype=np.float64)
        if self.kind == "uniform":
            return np.clip((x - self.low) / (self.high - self.low), 0.0, 1.0)
        if self.kind == "loguniform":
            return np.clip(np.log(np.maximum(x, self.low) / self.low) / math.log(self.high / self.low), 0.0, 1.0)
        if self.kind == "normal":
            phi = np.vectorize(lambda v: 0.5 * math.erfc(-(v - self.mean) / (self.std * math.sqrt(2.0))))
            lo, hi = phi(self.low), phi(self.high)
            return np.clip((phi(np.clip(x, self.low, self.high)) - lo) / (hi - lo), 0.0, 1.0)
        raise ValueError("cdf: a choice has probabilities, not a continuous cdf")


def from_dict(data: dict) -> Distribution:
    """The inverse of :meth:`Distribution.as_dict` (a parsed, checked description)."""
    kind = data["dist"]
    if kind == "choice":
        return Distribution(kind="choice", values=tuple(data["values"]), weights=tuple(data["weights"]))
    if kind == "normal":
        return Distribution(kind="normal", mean=data["mean"], std=data["std"],
                            low=-math.inf if data.get("low") is None else data["low"],
                            high=math.inf if data.get("high") is None else data["high"])
    return Distribution(kind=kind, low=data["low"], high=data["high"])


def constant(value: float) -> Distribution:
    return Distribution(kind="choice", values=(float(value),), weights=(1.0,))


def parse(value: object, where: str, fail: Callable[[str, str, object], Exception],
          valid: tuple[float, float] = (-math.inf, math.inf), unit: str = "") -> Distribution:
    """A :class:`Distribution` from a set file's value, checked against the value's ``valid`` range.

    ``fail(key, rule, value)`` makes the error for a key below ``where`` (``""`` the value itself): a
    :class:`batch.setfile.SetFileError` naming the file, line and dotted key.
    """
    lo_ok, hi_ok = valid
    span = f"[{lo_ok:g}, {hi_ok:g}]" + (f" ({unit})" if unit else "")
    if is_number(value):
        if not (math.isfinite(value) and lo_ok <= value <= hi_ok):
            raise fail("", f"a number in {span}", value)
        return constant(value)
    if not isinstance(value, dict):
        raise fail("", f"a number in {span} or a table {{ dist = one of {list(KINDS)}, … }}", value)
    kind = value.get("dist")
    if kind not in KINDS:
        raise fail("dist", f"one of {list(KINDS)}", kind)
    unknown = [k for k in value if k not in _KEYS[kind]]
    if unknown:
        raise fail(unknown[0], f"a key of a {kind} distribution, one of {list(_KEYS[kind])}", value[unknown[0]])
    for key in _KEYS[kind][1:]:
        if key not in value and not (kind == "normal" and key in ("low", "high")) and key != "weights":
            raise fail(key, f"given (a {kind} distribution needs {list(_KEYS[kind][1:])})", None)
    if kind == "choice":
        values = value["values"]
        if not isinstance(values, list) or not values or not all(is_number(v) and math.isfinite(v) for v in values):
            raise fail("values", "a non-empty list of finite numbers", values)
        if not all(lo_ok <= v <= hi_ok for v in values):
            raise fail("values", f"numbers in {span}", values)
        weights = value.get("weights", [1.0] * len(values))
        if (not isinstance(weights, list) or len(weights) != len(values)
                or not all(is_number(w) and math.isfinite(w) and w >= 0 for w in weights) or sum(weights) <= 0):
            raise fail("weights", f"{len(values)} finite numbers >= 0, not all 0", weights)
        return Distribution(kind="choice", values=tuple(float(v) for v in values),
                            weights=tuple(float(w) for w in weights))
    numbers = {}
    for key in _KEYS[kind][1:]:
        if key in value:
            if not (is_number(value[key]) and math.isfinite(value[key])):
                raise fail(key, "a finite number" + (f" ({unit})" if unit else ""), value[key])
            numbers[key] = float(value[key])
    if kind == "normal":
        if numbers["std"] <= 0:
            raise fail("std", "a finite number > 0", value["std"])
        low, high = max(numbers.get("low", -math.inf), lo_ok), min(numbers.get("high", math.inf), hi_ok)
        if not low < high:
            raise fail("high", f"above low and within the valid range {span}", value.get("high"))
        dist = Distribution(kind="normal", mean=numbers["mean"], std=numbers["std"], low=low, high=high)
        mass = float(np.diff(np.vectorize(lambda v: 0.5 * math.erfc(-(v - dist.mean) / (dist.std * math.sqrt(2))))(
            [low, high]))[0])
        if mass < 0.01:
            raise fail("mean", f"a mean whose normal keeps at least 1 % of its mass in [{low:g}, {high:g}] "
                               f"(it keeps {mass:.2g})", value["mean"])
        return dist
    if not numbers["low"] <= numbers["high"]:
        raise fail("high", f">= low ({numbers['low']:g})", value["high"])
    if kind == "loguniform" and numbers["low"] <= 0:
        raise fail("low", "a number > 0 (a log-uniform distribution)", value["low"])
    if numbers["low"] < lo_ok or numbers["high"] > hi_ok:
        raise fail("low" if numbers["low"] < lo_ok else "high", f"within the valid range {span}",
                   value["low"] if numbers["low"] < lo_ok else value["high"])
    return Distribution(kind=kind, low=numbers["low"], high=numbers["high"])
