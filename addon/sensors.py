"""``camera.tof`` → :class:`tofcore.Sensor`: the preset choices, and the preset with every enabled override.

The property groups (:mod:`.properties`), the operators and the update callbacks
(:mod:`.updates`) all read the settings through this module, which imports no
other module of the add-on, so none of them has to import another in a circle.

:func:`sensor_from_settings` turns the settings into a :class:`tofcore.Sensor` and
names the override at fault when one is invalid; :func:`render_settings` gives the
quality settings as :func:`tofcore.render_progressive` keywords.
"""

from __future__ import annotations

import bpy

import tofcore

#: UI names of the shipped presets; other preset files show their file stem.
PRESET_LABELS = {"kinect_v2": "Kinect v2", "o3d303": "O3D303", "xtion2": "Xtion 2"}
CUSTOM = "CUSTOM"
FORMATS = ("exr", "png", "ply", "json")
#: Smallest preview image side, pixels.
_PREVIEW_MIN_PX = 8


def _preset_items() -> list[tuple[str, str, str]]:
    """Enum items: every shipped preset (with its one-line description), then CUSTOM."""
    items = []
    for name in tofcore.list_presets():
        try:
            description = tofcore.load_preset(name).description
        except tofcore.ConfigError as err:  # a broken preset file must not break registration
            description = f"invalid preset: {err}"
        items.append((name, PRESET_LABELS.get(name, name), description or name))
    items.append((CUSTOM, "Custom", "A preset .toml file of your own (Preset File)"))
    return items


PRESET_ITEMS = _preset_items()
DEFAULT_PRESET = "kinect_v2" if any(item[0] == "kinect_v2" for item in PRESET_ITEMS) else PRESET_ITEMS[0][0]


def preset_source(settings) -> str:
    """What :func:`tofcore.load_preset` reads: the preset name, or the absolute custom file path."""
    if settings.preset != CUSTOM:
        return settings.preset
    if not settings.preset_path.strip():
        raise tofcore.ConfigError("Preset File (preset_path) must name a .toml file when Preset is Custom, got ''")
    return bpy.path.abspath(settings.preset_path)


def preset_sensor(settings):
    """The unmodified preset, or None when it cannot be read (the render reports why)."""
    try:
        return tofcore.load_preset(preset_source(settings))
    except tofcore.ConfigError:
        return None


def resolution_overrides(camera, width: int, height: int) -> dict:
    """``Sensor.replace`` overrides that resample ``camera`` to ``width`` × ``height`` pixels, same field of view.

    Pixel centres sit at integer coordinates, so the image spans
    [−½, W − ½): the principal point maps as c' = (c + ½)·s − ½ with s = W'/W,
    and the focal lengths as f' = f·s. Distortion acts on normalised
    coordinates and is unchanged.
    """
    sx, sy = width / camera.width, height / camera.height
    return {"camera.width": int(width), "camera.height": int(height),
            "camera.fx": camera.fx * sx, "camera.fy": camera.fy * sy,
            "camera.cx": (camera.cx + 0.5) * sx - 0.5, "camera.cy": (camera.cy + 0.5) * sy - 0.5}


def _clean(value: float) -> float:
    """A Blender float (stored as float32) as the decimal the user typed: 0.30000001192 → 0.3."""
    return float(f"{value:.7g}")


def sensor_from_settings(settings, *, scale: float = 1.0):
    """The :class:`tofcore.Sensor` of ``camera.tof``: the preset with every enabled override applied.

    Parameters
    ----------
    settings : a :class:`TofCameraSettings`.
    scale : resolution factor on top of the overrides (live preview), at least 8 px a side.

    Raises
    ------
    tofcore.ConfigError
        The preset cannot be read, or an override is invalid; the message starts with the setting's
        UI label and property, e.g. ``"Preset File (preset_path): …"``, ``"ToF override Range (range_m): …"``.
    """
    try:
        sensor = tofcore.load_preset(preset_source(settings))
    except tofcore.ConfigError as err:
        if settings.preset != CUSTOM or str(err).startswith("Preset File"):
            raise
        raise tofcore.ConfigError(f"Preset File (preset_path): {err}") from None
    steps: list[tuple[str, dict]] = []
    if settings.use_resolution:
        steps.append(("Resolution (width, height)",
                      resolution_overrides(sensor.camera, settings.width, settings.height)))
    if settings.use_led_override:
        offset = [_clean(o) for o in settings.led_offset_m]
        spread = _clean(settings.led_spread)
        leds = [{"position_m": [spread * p + o for p, o in zip(led.position_m, offset)],
                 "intensity_w_sr": led.intensity_w_sr, "kind": led.kind} for led in sensor.leds]
        steps.append(("LED Offset (led_offset_m, led_spread)", {"leds": leds}))
    if settings.noise_model != 'PRESET':
        steps.append(("Noise (noise_model)", {"noise.model": settings.noise_model}))
    if not settings.use_scattering:
        steps.append(("Lens Scattering (use_scattering)", {"scattering.model": "none"}))
    if settings.depth_output != 'PRESET':
        steps.append(("Depth (depth_output)", {"depth_output": settings.depth_output}))
    if settings.use_range_m:
        steps.append(("Range (range_m)", {"range_m": [_clean(x) for x in settings.range_m]}))
    for label, overrides in steps:
        try:
            sensor = sensor.replace(**overrides)
        except tofcore.ConfigError as err:
            raise tofcore.ConfigError(f"ToF override {label}: {err}") from None
    if scale != 1.0:
        cam = sensor.camera
        width = max(_PREVIEW_MIN_PX, round(cam.width * scale))
        height = max(_PREVIEW_MIN_PX, round(cam.height * scale))
        sensor = sensor.replace(**resolution_overrides(cam, width, height))
    return sensor


def render_settings(settings) -> dict:
    """Keyword arguments of :func:`tofcore.render_progressive` from the quality settings (0 → None)."""
    return {"spp": int(settings.spp), "max_depth": int(settings.max_depth), "seed": int(settings.seed),
            "time_budget_s": float(settings.time_budget_s) or None,
            "target_error_m": float(settings.target_error_mm) / 1000.0 or None}
