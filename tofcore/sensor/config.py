"""The simulated ToF sensor: optics, emitters, modulation, readout, noise, scattering and validity rules.

A :class:`Sensor` bundles everything that turns transported light into a
depth frame. It is usually read from a preset TOML file
(:func:`tofcore.sensor.presets.load_preset`); every TOML key is the dataclass field
of the same name, tables are the sub-dataclasses.

``Sensor`` (top level)
======================  ======  ==========  ==================================================================
name                    unit    default     meaning
======================  ======  ==========  ==================================================================
``name``                –       –           short identifier, e.g. ``"kinect_v2"``
``camera``              –       –           ``[camera]``: :class:`~tofcore.scene.camera.Camera` fields (intrinsics,
                                            OpenCV distortion, thin lens)
``leds``                –       –           ``[[leds]]``: one or more :class:`~tofcore.scene.led.LED` (position in the
                                            sensor frame, intensity, kind)
``modulation``          –       –           ``[modulation]``: :class:`~tofcore.sensor.modulation.Modulation` fields
``readout``             –       –           ``[readout]``: :class:`Readout`
``noise``               –       Noise()     ``[noise]``: :class:`Noise`
``scattering``          –       none        ``[scattering]``: :class:`Scattering`
``range_m``             m       –           (min, max) valid output depth (z for ``depth_output`` "z", as the
                                            Kinect v2 limits z), 0 <= min < max <= the modulation's
                                            unambiguous range
``depth_output``        –       "radial"    ``"radial"`` (distance along the ray) or ``"z"`` (along the axis)
``invalid``             –       defaults    ``[invalid]``: :class:`InvalidRules`
``processing``          –       defaults    ``[processing]``: :class:`Processing`, the camera's own frequency
                                            combination and phasor filter (:mod:`tofcore.sensor.processing`)
``frame_rate_hz``       Hz      None        frames per second (metadata; None: unknown)
``ir_image``            –       true        whether the real device delivers an IR (amplitude) image
``description``         –       ""          one line for listings
``sources``             –       –           ``[sources]``: dotted key → where the number comes from
                                            (``"assumed"`` plus a reason where nothing is published)
======================  ======  ==========  ==================================================================

``[readout]`` (:class:`Readout`)
======================  ===================  =======  ====================================================
``responsivity``        e⁻ s⁻¹/(W m⁻² sr⁻¹)  –        electrons per second per unit radiance at the lens;
                                                       lumps aperture, pixel area, filter and quantum
                                                       efficiency
``full_well_e``         e⁻                   –        saturation charge of a raw image
======================  ===================  =======  ====================================================

``[noise]`` (:class:`Noise`)
=======================  ====  =======  ==========================================================================
``model``                –     "raw"    ``"none"``; ``"raw"``: shot noise (√charge) + read noise on every raw
                                        image; ``"li"``: Gaussian noise on the distance, σ of eq. 2.43
``read_noise_e``         e⁻    0.0      read noise per raw image (standard deviation), ``"raw"``
``modulation_contrast``  1     1.0      c_d of eq. 2.43, in (0, 1], ``"li"``
``gain_noise``           1     0.0      ``"raw"``: noise proportional to each raw image's charge, as a fraction
                                        of it (Keller's β, eq. 3.1): the signal-proportional fluctuations
                                        (illumination power, demodulation timing) that shot and read noise
                                        lack; it sets a depth-noise floor that does not fall with more light
=======================  ====  =======  ==========================================================================

``[processing]`` (:class:`Processing`, see :mod:`tofcore.sensor.processing`)
=====================  ====  ===================  ===========================================================
``unwrap_weights``     –     "inverse_variance"   ``"inverse_variance"`` or ``"frequency"`` (libfreenect2)
``phasor_filter``      –     "none"               ``"none"`` or ``"bilateral"`` (libfreenect2, 3 × 3)
=====================  ====  ===================  ===========================================================

``[scattering]`` (:class:`Scattering`, see :mod:`tofcore.sensor.optics`)
==================  ====  =======  ===============================================================================
``model``           –     "none"   ``"none"``, ``"airy"`` or ``"gaussians"``
``strength``        1     0.0      fraction of a pixel's light that is scattered, in [0, 1)
``radius_px``       px    0.0      ``"airy"``: radius of the first dark ring, > 0
``negative_lobe``   1     0.0      ``"airy"``: depth of the negative first ring relative to the peak, [0, 1)
                                   (the measured PSFs of O3D303 and Kinect v2 had one, thesis §4.0.6)
``sigmas_px``       px    ()       ``"gaussians"``: standard deviations, each > 0
``weights``         1     ()       ``"gaussians"``: one weight >= 0 per sigma, summing to 1
==================  ====  =======  ===============================================================================

``[invalid]`` (:class:`InvalidRules`)
=========================  ====  =======  ===================================================================
``min_amplitude_e``        e⁻    0.0      pixels with a smaller amplitude A (eq. 2.40) are invalid
``min_amplitude_snr``      1     0.0      CW: pixels with A below this many σ_A, the amplitude noise of their
                                          offset under ``[noise]`` read_noise_e and gain_noise, are invalid; a
                                          pixel with no return passes with probability exp(−k²/2)
                                          (:func:`tofcore.sensor.decode.amplitude_noise_e`); pulsed: Q1 + Q2
                                          below this many √2 σ_read (a dark pixel's noise) is invalid
``invalidate_saturated``   –     true     pixels with a raw image at full well are invalid
``unwrap_tolerance_m``     m     None     largest disagreement between frequencies; None: the decoder's default
``amplitude_test``         –     highest  CW: ``"highest"`` (the amplitude tests read the highest frequency) or
                                          ``"every"`` (every frequency must pass them, libfreenect2)
``dealias_tolerance_rad``  rad   None     CW: also invalid where the unwrapped phases are farther than this from
                                          agreeing (libfreenect2's dealiasing confidence); None: off
``edge_filter``            –     false    CW with the bilateral filter: the camera's edge-aware filter removes
                                          flying pixels and incoherent neighbourhoods (libfreenect2)
``edge_filter_fx_px``      px    None     the focal length at which the edge filter's depth thresholds hold
                                          (the native camera's); a resized camera scales them by this / fx
=========================  ====  =======  ===================================================================

Every class checks its fields in ``__post_init__`` and parses a plain dict in
``from_dict(data, where)``: unknown keys, missing required keys, wrong types and
out-of-range values raise :class:`~tofcore.errors.ConfigError` naming
``where`` (the file and table), the key, the rule and the value.

Example
-------
>>> sensor = load_preset("kinect_v2")                                  # doctest: +SKIP
>>> quiet = sensor.replace(**{"noise.model": "none", "scattering.model": "none"})  # doctest: +SKIP
>>> Sensor.from_dict(quiet.to_dict(), "copy") == quiet                 # doctest: +SKIP
True
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import MISSING, dataclass, fields, is_dataclass
from typing import Any

import numpy as np

from .. import limits
from ..errors import ConfigError, is_number
from ..scene.camera import Camera
from ..scene.led import LED
from . import optics, processing
from .modulation import Modulation

NOISE_MODELS = ("none", "raw", "li")
SCATTERING_MODELS = optics.MODELS
DEPTH_OUTPUTS = ("radial", "z")
_WEIGHT_SUM_TOL = 1e-6


# ------------------------------------------------------------------ value checks
def _fail(where: str, key: str, rule: str, value: object) -> ConfigError:
    return ConfigError(f"{where}: {key} must be {rule}, got {value!r}")


def _number(value: object, where: str, key: str, rule: str, ok: Callable[[float], bool]) -> float:
    """``value`` as a float if it is a number (TOML ints accepted) and ``ok``; else ConfigError naming ``rule``."""
    if not is_number(value) or not ok(float(value)):
        raise _fail(where, key, rule, value)
    return float(value)


def _numbers(value: object, where: str, key: str, rule: str, ok: Callable[[float], bool]) -> tuple[float, ...]:
    """A list/tuple of numbers each satisfying ``ok``, as a tuple of floats."""
    if not isinstance(value, (list, tuple, np.ndarray)) or not all(is_number(v) and ok(float(v)) for v in value):
        raise _fail(where, key, rule, value)
    return tuple(float(v) for v in value)


def _choice(value: object, where: str, key: str, choices: Sequence[str]) -> str:
    if value not in choices:
        raise _fail(where, key, f"one of {list(choices)}", value)
    return value


def _typed(value: object, where: str, key: str, kind: type, rule: str) -> Any:
    if not isinstance(value, kind):
        raise _fail(where, key, rule, value)
    return value


def _finite_positive(x: float) -> bool:
    return math.isfinite(x) and x > 0


def _finite_non_negative(x: float) -> bool:
    return math.isfinite(x) and x >= 0


def _scale(value: object, where: str, key: str, rule: str, ok: Callable[[float], bool], unit: str) -> float:
    """A physical scale factor: :func:`_number`, and at most :data:`tofcore.limits.MAX_MAGNITUDE` so that the
    radiometric chain (LED intensity x responsivity x exposure x geometry) stays finite in float64."""
    x = _number(value, where, key, rule, ok)
    if x > limits.MAX_MAGNITUDE:
        raise _fail(where, key, f"at most {limits.MAX_MAGNITUDE:g} ({unit})", value)
    return x


def _fraction(x: float) -> bool:
    return 0.0 <= x < 1.0


# ------------------------------------------------------------------ tables
def _required(cls: type) -> list[str]:
    return [f.name for f in fields(cls) if f.default is MISSING and f.default_factory is MISSING]


def _defaults(cls: type) -> dict[str, Any]:
    return {f.name: f.default for f in fields(cls) if f.default is not MISSING}


def _table(data: object, where: str, cls: type, top_level: bool = False) -> dict[str, Any]:
    """``data`` as a dict after checking it is a table with only ``cls``'s fields and all required ones."""
    valid = sorted(f.name for f in fields(cls))
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: must be a table with keys {valid}, got {data!r}")
    scope = "top-level key" if top_level else "key"
    for key in data:
        if key not in valid:
            raise ConfigError(f"{where}: unknown {scope} {key!r}; valid keys are {valid}")
    for key in _required(cls):
        if key not in data:
            raise ConfigError(f"{where}: missing required {scope} {key!r}; required keys are {_required(cls)}")
    return dict(data)


def _build(cls: type, kwargs: dict[str, Any], where: str) -> Any:
    """``cls(**kwargs)``, its ConfigError re-addressed from ``"Cls: …"`` to ``where``."""
    try:
        return cls(**kwargs)
    except ConfigError as err:
        raise type(err)(f"{where}: {str(err).removeprefix(cls.__name__ + ': ')}") from None


def _plain(value: object) -> Any:
    """JSON/TOML-ready form: dataclasses → dicts (None and default-infinite fields left out), tuples → lists."""
    if is_dataclass(value) and not isinstance(value, type):
        if hasattr(value, "to_dict"):
            return value.to_dict()
        out = {}
        for f in fields(value):
            v = getattr(value, f.name)
            if v is None or (isinstance(v, float) and math.isinf(v) and v == f.default):  # JSON has no inf
                continue
            out[f.name] = _plain(v)
        return out
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in value]
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, np.generic):
        return value.item()
    return value


class _Table:
    """Shared machinery of the flat sub-tables: validation in ``__post_init__``, ``from_dict``, ``to_dict``.

    Subclasses implement ``_normalised(values, where) -> dict``: every field checked and converted.
    """

    def __post_init__(self) -> None:
        for key, value in self._normalised(vars(self), type(self).__name__).items():
            object.__setattr__(self, key, value)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str | None = None) -> Any:
        """Build from a plain dict (a TOML table); ``where`` names the file and table in errors."""
        where = where or cls.__name__
        values = _defaults(cls) | _table(data, where, cls)
        return cls(**cls._normalised(values, where))

    def to_dict(self) -> dict[str, Any]:
        """Plain dict that :meth:`from_dict` turns back into an equal object (None fields left out)."""
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self) if getattr(self, f.name) is not None}

    @staticmethod
    def _normalised(values: dict[str, Any], where: str) -> dict[str, Any]:
        raise NotImplementedError


@dataclass(frozen=True, kw_only=True)
class Readout(_Table):
    """Conversion of radiance at the lens to electrons; see the module docstring."""

    responsivity: float
    full_well_e: float

    @staticmethod
    def _normalised(values: dict[str, Any], where: str) -> dict[str, Any]:
        return {
            "responsivity": _scale(values["responsivity"], where, "responsivity",
                                   "a finite number > 0 (e-/s per W m^-2 sr^-1)", _finite_positive,
                                   "e-/s per W m^-2 sr^-1"),
            "full_well_e": _scale(values["full_well_e"], where, "full_well_e",
                                  "a finite number > 0 (electrons)", _finite_positive, "electrons"),
        }


@dataclass(frozen=True, kw_only=True)
class Noise(_Table):
    """Random error model; see the module docstring."""

    model: str = "raw"
    read_noise_e: float = 0.0
    modulation_contrast: float = 1.0
    gain_noise: float = 0.0

    @staticmethod
    def _normalised(values: dict[str, Any], where: str) -> dict[str, Any]:
        return {
            "model": _choice(values["model"], where, "model", NOISE_MODELS),
            "read_noise_e": _scale(values["read_noise_e"], where, "read_noise_e",
                                   "a finite number >= 0 (electrons)", _finite_non_negative, "electrons"),
            "modulation_contrast": _number(values["modulation_contrast"], where, "modulation_contrast",
                                           "a number in (0, 1]", lambda x: 0.0 < x <= 1.0),
            "gain_noise": _number(values["gain_noise"], where, "gain_noise", "a number in [0, 1)", _fraction),
        }


@dataclass(frozen=True, kw_only=True)
class Processing(_Table):
    """The camera's own processing of its phases; see the module docstring and :mod:`tofcore.sensor.processing`."""

    unwrap_weights: str = "inverse_variance"
    phasor_filter: str = "none"

    @staticmethod
    def _normalised(values: dict[str, Any], where: str) -> dict[str, Any]:
        return {
            "unwrap_weights": _choice(values["unwrap_weights"], where, "unwrap_weights", processing.UNWRAP_WEIGHTS),
            "phasor_filter": _choice(values["phasor_filter"], where, "phasor_filter", processing.PHASOR_FILTERS),
        }


@dataclass(frozen=True, kw_only=True)
class Scattering(_Table):
    """Lens-scattering PSF applied to every raw image; see the module docstring and :mod:`tofcore.sensor.optics`."""

    model: str = "none"
    strength: float = 0.0
    radius_px: float = 0.0
    negative_lobe: float = 0.0
    sigmas_px: tuple[float, ...] = ()
    weights: tuple[float, ...] = ()

    @staticmethod
    def _normalised(values: dict[str, Any], where: str) -> dict[str, Any]:
        out = {
            "model": _choice(values["model"], where, "model", SCATTERING_MODELS),
            "strength": _number(values["strength"], where, "strength", "a number in [0, 1)", _fraction),
            "radius_px": _number(values["radius_px"], where, "radius_px", "a finite number >= 0 (pixels)",
                                 _finite_non_negative),
            "negative_lobe": _number(values["negative_lobe"], where, "negative_lobe", "a number in [0, 1)",
                                     _fraction),
            "sigmas_px": _numbers(values["sigmas_px"], where, "sigmas_px", "a list of finite numbers > 0 (pixels)",
                                  _finite_positive),
            "weights": _numbers(values["weights"], where, "weights", "a list of finite numbers >= 0",
                                _finite_non_negative),
        }
        if out["model"] == "airy" and out["radius_px"] <= 0:
            raise _fail(where, "radius_px", "> 0 (pixels) for model 'airy'", out["radius_px"])
        if out["model"] == "gaussians":
            sigmas, weights = out["sigmas_px"], out["weights"]
            if not sigmas:
                raise _fail(where, "sigmas_px", "one or more numbers > 0 for model 'gaussians'", sigmas)
            if len(weights) != len(sigmas) or abs(sum(weights) - 1.0) > _WEIGHT_SUM_TOL:
                raise _fail(where, "weights", f"{len(sigmas)} numbers (one per sigmas_px entry) summing to 1",
                            weights)
        if out["model"] != "none" and out["strength"] > 0:
            _build_kernel(out, where)
        return out


def _build_kernel(values: dict[str, Any], where: str) -> None:
    """Raise ConfigError at ``where`` if :func:`tofcore.sensor.optics.psf_kernel` rejects the parameters."""
    try:
        optics.psf_kernel(**values)
    except ConfigError as err:
        raise ConfigError(f"{where}: {str(err).removeprefix('psf_kernel: ')}") from None


@dataclass(frozen=True, kw_only=True)
class InvalidRules(_Table):
    """When a pixel has no depth; see the module docstring."""

    min_amplitude_e: float = 0.0
    min_amplitude_snr: float = 0.0
    invalidate_saturated: bool = True
    unwrap_tolerance_m: float | None = None
    amplitude_test: str = "highest"
    dealias_tolerance_rad: float | None = None
    edge_filter: bool = False
    edge_filter_fx_px: float | None = None

    @staticmethod
    def _normalised(values: dict[str, Any], where: str) -> dict[str, Any]:
        tolerance = values["unwrap_tolerance_m"]
        dealias = values["dealias_tolerance_rad"]
        return {
            "amplitude_test": _choice(values["amplitude_test"], where, "amplitude_test", ("highest", "every")),
            "dealias_tolerance_rad": None if dealias is None else _number(
                dealias, where, "dealias_tolerance_rad", "a finite number > 0 (radians) or absent", _finite_positive),
            "edge_filter": _typed(values["edge_filter"], where, "edge_filter", bool, "true or false"),
            "edge_filter_fx_px": None if values["edge_filter_fx_px"] is None else _number(
                values["edge_filter_fx_px"], where, "edge_filter_fx_px", "a finite number > 0 (pixels) or absent",
                _finite_positive),
            "min_amplitude_e": _scale(values["min_amplitude_e"], where, "min_amplitude_e",
                                      "a finite number >= 0 (electrons)", _finite_non_negative, "electrons"),
            "min_amplitude_snr": _number(values["min_amplitude_snr"], where, "min_amplitude_snr",
                                         "a finite number >= 0", _finite_non_negative),
            "invalidate_saturated": _typed(values["invalidate_saturated"], where, "invalidate_saturated", bool,
                                           "true or false"),
            "unwrap_tolerance_m": None if tolerance is None else _number(
                tolerance, where, "unwrap_tolerance_m", "a finite number > 0 (metres) or absent", _finite_positive),
        }


# ------------------------------------------------------------------ camera, LEDs, modulation tables
def _camera_from_dict(data: object, where: str) -> Camera:
    values = _table(data, where, Camera)
    for key in ("width", "height"):
        if key in values and (isinstance(values[key], bool) or not isinstance(values[key], int)):
            raise _fail(where, key, "a positive integer (pixels)", values[key])
    for key in values.keys() - {"width", "height"}:
        values[key] = _number(values[key], where, key, "a number", lambda x: True)
    return _build(Camera, values, where)


def _led_from_dict(data: object, where: str) -> LED:
    values = _table(data, where, LED)
    if "position_m" in values:
        values["position_m"] = _numbers(values["position_m"], where, "position_m",
                                        "three finite numbers (metres, sensor frame)", math.isfinite)
    if "intensity_w_sr" in values:
        values["intensity_w_sr"] = _scale(values["intensity_w_sr"], where, "intensity_w_sr",
                                          "a finite number >= 0 (W/sr)", _finite_non_negative, "W/sr")
    if "kind" in values:
        values["kind"] = _typed(values["kind"], where, "kind", str, "a string")
    return _build(LED, values, where)


def _modulation_from_dict(data: object, where: str) -> Modulation:
    values = _table(data, where, Modulation)
    values["kind"] = _typed(values["kind"], where, "kind", str, "a string")
    for key in ("frequencies_hz", "exposure_s"):
        if key in values:
            values[key] = _numbers(values[key], where, key, "a list of numbers", lambda x: True)
    if "phase_steps" in values:
        steps = values["phase_steps"]
        if not isinstance(steps, (list, tuple)) or not all(isinstance(n, int) and not isinstance(n, bool)
                                                            for n in steps):
            raise _fail(where, "phase_steps", "a list of integers", steps)
        values["phase_steps"] = tuple(steps)
    for key in ("duty_cycle", "pulse_width_s"):
        if key in values:
            values[key] = _number(values[key], where, key, "a number", lambda x: True)
    return _build(Modulation, values, where)


# ------------------------------------------------------------------ the sensor
_TABLE_TYPES: dict[str, type] = {"camera": Camera, "leds": LED, "modulation": Modulation, "readout": Readout,
                                 "noise": Noise, "scattering": Scattering, "invalid": InvalidRules,
                                 "processing": Processing}


@dataclass(frozen=True, kw_only=True)
class Sensor:
    """A complete ToF sensor; see the module docstring for the parameter tables."""

    name: str
    camera: Camera
    leds: tuple[LED, ...]
    modulation: Modulation
    readout: Readout
    noise: Noise = Noise()
    scattering: Scattering = Scattering()
    range_m: tuple[float, float]
    depth_output: str = "radial"
    invalid: InvalidRules = InvalidRules()
    processing: Processing = Processing()
    frame_rate_hz: float | None = None
    ir_image: bool = True
    description: str = ""
    sources: dict[str, str]

    def __post_init__(self) -> None:
        for key, value in self._normalised(vars(self), "Sensor").items():
            object.__setattr__(self, key, value)

    @staticmethod
    def _normalised(values: dict[str, Any], where: str) -> dict[str, Any]:
        out = dict(values)
        name = values["name"]
        if not isinstance(name, str) or not name:
            raise _fail(where, "name", "a non-empty string", name)
        for key in ("camera", "modulation", "readout", "noise", "scattering", "invalid", "processing"):
            _typed(values[key], where, key, _TABLE_TYPES[key], f"a {_TABLE_TYPES[key].__name__}")
        leds = values["leds"]
        if not isinstance(leds, (list, tuple)) or not leds or not all(isinstance(led, LED) for led in leds):
            raise _fail(where, "leds", "one or more LEDs ([[leds]] tables)", leds)
        out["leds"] = tuple(leds)
        out["range_m"] = _numbers(values["range_m"], where, "range_m", "[min, max] in metres, 0 <= min < max",
                                  _finite_non_negative)
        low_high = out["range_m"]
        if len(low_high) != 2 or not low_high[0] < low_high[1]:
            raise _fail(where, "range_m", "[min, max] in metres, 0 <= min < max", values["range_m"])
        unambiguous_m = values["modulation"].unambiguous_range_m()
        if low_high[1] > unambiguous_m:
            raise _fail(where, "range_m", f"within the modulation's unambiguous range (max <= {unambiguous_m:.4g} m)",
                        values["range_m"])
        out["depth_output"] = _choice(values["depth_output"], where, "depth_output", DEPTH_OUTPUTS)
        rate = values["frame_rate_hz"]
        out["frame_rate_hz"] = None if rate is None else _number(rate, where, "frame_rate_hz",
                                                                 "a finite number > 0 (Hz) or absent", _finite_positive)
        _typed(values["ir_image"], where, "ir_image", bool, "true or false")
        _typed(values["description"], where, "description", str, "a string")
        out["sources"] = _checked_sources(values["sources"], where)
        if values["noise"].model == "li" and not values["modulation"].is_cw:
            raise _fail(where, "noise.model", "'raw' or 'none' for a pulsed sensor (eq. 2.43 is for CW)", "li")
        if values["processing"] != Processing() and not values["modulation"].is_cw:
            raise _fail(where, "processing", "the defaults for a pulsed sensor (it has no phases to filter or "
                        "combine)", values["processing"].to_dict())
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "Sensor") -> Sensor:
        """Build from a plain dict (a parsed preset TOML file); ``where`` (the file path) prefixes every error."""
        values = _defaults(cls) | _table(data, where, cls, top_level=True)
        values["camera"] = _camera_from_dict(values["camera"], f"{where} [camera]")
        leds = values["leds"]
        if not isinstance(leds, list) or not leds:
            raise _fail(where, "leds", "one or more [[leds]] tables", leds)
        values["leds"] = tuple(_led_from_dict(led, f"{where} [[leds]] #{i + 1}") for i, led in enumerate(leds))
        values["modulation"] = _modulation_from_dict(values["modulation"], f"{where} [modulation]")
        for key in ("readout", "noise", "scattering", "invalid", "processing"):
            if isinstance(values[key], Mapping):  # the defaults are objects already
                values[key] = _TABLE_TYPES[key].from_dict(values[key], f"{where} [{key}]")
            elif not isinstance(values[key], _TABLE_TYPES[key]):
                raise _fail(where, key, f"a table [{key}]", values[key])
        return cls(**cls._normalised(values, where))

    def to_dict(self) -> dict[str, Any]:
        """Plain, JSON-serialisable dict (lists, no None, no inf) that :meth:`from_dict` turns back into ``self``."""
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self) if getattr(self, f.name) is not None}

    def replace(self, **overrides: Any) -> Sensor:
        """A copy with top-level or dotted fields replaced, validated like a preset.

        Parameters
        ----------
        **overrides
            ``field=value`` for top-level fields, ``**{"table.field": value}`` for
            fields of a table, e.g. ``{"modulation.frequencies_hz": [20e6], "noise.model": "none"}``.
            Values may be plain (lists, dicts) or objects (``Camera``, ``LED``, …);
            None removes a key (its default applies).
        """
        data = self.to_dict()
        for dotted, value in overrides.items():
            table, _, key = dotted.partition(".")
            if key and not isinstance(data.get(table), dict):
                raise ConfigError(f"Sensor.replace: {dotted!r} must name a field of one of the tables "
                                  f"{sorted(k for k, v in data.items() if isinstance(v, dict))}, got {dotted!r}")
            target, field = (data[table], key) if key else (data, table)
            if value is None:
                target.pop(field, None)
            else:
                target[field] = _plain(value)
        return Sensor.from_dict(data, where="Sensor.replace")

    def resized(self, width: int, height: int) -> Sensor:
        r"""A copy whose image is ``width`` × ``height`` pixels, the intrinsics scaled with it.

        Notes
        -----
        The focal lengths scale with the size ratios :math:`s_x = w'/w`, :math:`s_y = h'/h`, and the
        principal point keeps its place on the sensor, pixel centres at integer coordinates
        (:mod:`tofcore.camera`): :math:`c_x' = (c_x + 1/2)\,s_x - 1/2`. Distortion coefficients act on
        normalised coordinates and stay as they are, so the field of view is unchanged. Everything per
        pixel (responsivity, noise, scattering radius in pixels) stays as in the preset: the result is the
        same camera seen at another resolution, not a camera with larger pixels.
        """
        for name, value in (("width", width), ("height", height)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ConfigError(f"Sensor.resized: {name} must be an integer >= 1, got {value!r}")
        limits.MAX_PIXELS.check(width * height, "Sensor.resized", "width x height", f"{width} x {height}")
        cam = self.camera
        if (width, height) == (cam.width, cam.height):
            return self
        # Before the camera of that size checks its distortion over per-pixel tables (a minute and GBs at
        # 4096 x 4096): a size that even a max_depth 1 render cannot hold is refused now.
        limits.check_render_size(width, height, self.modulation.raw_count, max_depth=1, where="Sensor.resized")
        sx, sy = width / cam.width, height / cam.height
        return self.replace(**{
            "camera.width": width, "camera.height": height, "camera.fx": cam.fx * sx, "camera.fy": cam.fy * sy,
            "camera.cx": (cam.cx + 0.5) * sx - 0.5, "camera.cy": (cam.cy + 0.5) * sy - 0.5})

    def scaled(self, factor: float) -> Sensor:
        """A copy with width and height times ``factor`` (rounded half up, at least 1 px) and the intrinsics
        scaled to the actual size ratios (:meth:`resized`); ``scaled(0.25)`` is a quarter of each side."""
        return self.resized(*self.scaled_size(factor))

    def scaled_size(self, factor: float) -> tuple[int, int]:
        """(width, height) of :meth:`scaled` ``(factor)``, without making the sensor."""
        if not isinstance(factor, (int, float)) or isinstance(factor, bool) or not 0 < factor < math.inf:
            raise ConfigError(f"Sensor.scaled: factor must be a finite number > 0, got {factor!r}")
        cam = self.camera
        exact_w, exact_h = cam.width * factor, cam.height * factor
        if exact_w * exact_h > 4 * limits.MAX_PIXELS.value:  # refuse before rounding a huge product
            limits.MAX_PIXELS.check(math.inf, "Sensor.scaled", "width x height", f"{exact_w:.4g} x {exact_h:.4g}")
        return max(1, int(math.floor(exact_w + 0.5))), max(1, int(math.floor(exact_h + 0.5)))


def _source_keys() -> set[str]:
    """Every dotted key a ``[sources]`` entry may name: top-level fields and ``table.field``."""
    keys = {f.name for f in fields(Sensor)} - {"sources"}
    for table, cls in _TABLE_TYPES.items():
        keys.update(f"{table}.{f.name}" for f in fields(cls))
    return keys


def _checked_sources(sources: object, where: str) -> dict[str, str]:
    if not isinstance(sources, Mapping):
        raise _fail(where, "sources", "a table of dotted key = \"source\" strings", sources)
    valid = _source_keys()
    for key, text in sources.items():
        if key not in valid:
            raise ConfigError(f"{where} [sources]: unknown key {key!r}; keys must name a field, e.g. "
                              f"'camera.fx' or 'range_m'; valid keys are {sorted(valid)}")
        if not isinstance(text, str) or not text.strip():
            raise _fail(f"{where} [sources]", repr(key), "a non-empty string", text)
    return dict(sources)
