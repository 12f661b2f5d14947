"""ToF settings stored in the .blend file: ``camera.tof`` and ``material.tof``.

``camera.tof`` (:class:`TofCameraSettings`, on ``bpy.types.Camera``)
=====================  ======  ==========  ===================================================================
property               unit    default     meaning
=====================  ======  ==========  ===================================================================
``enabled``            –       False       this camera is a ToF sensor ("Add ToF Camera" turns it on)
``preset``             –       kinect_v2   a shipped preset (``tofcore.list_presets()``) or ``CUSTOM``
``preset_path``        –       ""          ``CUSTOM``: a preset .toml file (``//`` = next to the .blend)
``use_resolution``     –       False       override the preset's resolution (intrinsics scale, FOV is kept)
``width``, ``height``  px      preset      the overriding resolution
``use_led_override``   –       False       move the preset's LEDs: position = led_spread × preset + offset
``led_offset_m``       m       (0, 0, 0)   added to every LED position, sensor frame (x right, y down, z fwd)
``led_spread``         1       1.0         scale of the preset's LED positions (0 puts every LED on the lens)
``noise_model``        –       PRESET      ``PRESET`` or a ``Sensor.noise.model``: none, raw, li
``use_scattering``     –       True        keep the preset's lens scattering (off: ``scattering.model="none"``)
``depth_output``       –       PRESET      ``PRESET``, ``radial`` or ``z``
``use_range_m``        –       False       override the valid range
``range_m``            m       preset      (min, max) valid distance
``spp``                –       64          most samples per pixel
``time_budget_s``      s       0           stop before a pass that would end later (0: no budget)
``target_error_mm``    mm      0           stop at this estimated RMS depth error (0: no target)
``max_depth``          –       5           surface vertices per path (1 = direct light only)
``seed``               –       0           random seed (same seed, same frame)
``output_dir``         –       //tof/      folder of the written frame (``//`` = next to the .blend)
``formats``            –       all         any of exr, png, ply, json (``tofcore.write_frame``)
``live_preview``       –       False       re-render at low resolution whenever the scene or sensor changes
``preview_scale``      1       0.25        preview resolution as a fraction of the sensor's
``preview_spp``        –       8           most samples per pixel of a preview
=====================  ======  ==========  ===================================================================

Property names follow the ``tofcore`` field names (``range_m``, ``depth_output``,
``spp``, ``max_depth`` …). :func:`sensor_from_settings` turns the settings into a
:class:`tofcore.Sensor` and names the override at fault when one is invalid.

``material.tof`` (:class:`TofMaterialSettings`, on ``bpy.types.Material``):
``use_override`` replaces the near-IR values the exporter derives from the
Principled BSDF by ``reflectance`` (1, [0, 1]), ``roughness`` (radians) and
``extinction`` (1, conductor k).
"""

from __future__ import annotations

import math

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, FloatVectorProperty, IntProperty, \
    PointerProperty, StringProperty
from bpy.types import PropertyGroup

import tofcore

#: UI names of the shipped presets; other preset files show their file stem.
PRESET_LABELS = {"kinect_v2": "Kinect v2", "o3d303": "O3D303", "xtion2": "Xtion 2"}
CUSTOM = "CUSTOM"
FORMATS = ("exr", "png", "ply", "json")
#: Path properties accept "//" (relative to the .blend); Blender 5.0 made that an explicit option.
PATH_OPTIONS = {'PATH_SUPPORTS_BLEND_RELATIVE'} if bpy.app.version >= (5, 0, 0) else set()
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


# --------------------------------------------------------------------------- update callbacks

def _cameras_changed(self, context) -> None:
    """A setting that moves the LEDs or changes the intrinsics: update the cameras using this data."""
    from . import operators  # operators imports this module
    operators.apply_settings_to_cameras(self.id_data, context.scene if context else None)
    operators.settings_changed(self.id_data)


def _fill_resolution(self, context) -> None:
    """Turning the override on starts from the preset's resolution."""
    if self.use_resolution:
        camera = _preset_sensor(self)
        if camera is not None:
            self.width, self.height = camera.camera.width, camera.camera.height
    _cameras_changed(self, context)


def _fill_range(self, context) -> None:
    """Turning the override on starts from the preset's range."""
    if self.use_range_m:
        sensor = _preset_sensor(self)
        if sensor is not None:
            self.range_m = sensor.range_m
    _settings_changed(self, context)


def _settings_changed(self, context) -> None:
    """Any other sensor or quality setting: restart the live preview, if on."""
    from . import operators
    operators.settings_changed(self.id_data)


def _live_preview_toggled(self, context) -> None:
    from . import operators
    operators.live_preview_toggled(self.id_data, self.live_preview)


def _material_changed(self, context) -> None:
    from . import operators
    operators.settings_changed(None)


# --------------------------------------------------------------------------- property groups

class TofCameraSettings(PropertyGroup):
    """The ToF sensor of a camera (``camera.tof``)"""

    enabled: BoolProperty(
        name="ToF Sensor", default=False, update=_cameras_changed,
        description="Use this camera as a ToF sensor: its intrinsics and LED empties follow the sensor settings")
    preset: EnumProperty(
        name="Preset", items=PRESET_ITEMS, default=DEFAULT_PRESET, update=_cameras_changed,
        description="Sensor preset: intrinsics, LEDs, modulation, noise and lens scattering of a real camera")
    preset_path: StringProperty(
        name="Preset File", subtype='FILE_PATH', default="", options=PATH_OPTIONS, update=_cameras_changed,
        description="Custom preset: a .toml file in the format of the shipped presets (// = next to the .blend)")

    use_resolution: BoolProperty(
        name="Resolution", default=False, update=_fill_resolution,
        description="Override the preset's resolution; the intrinsics are scaled so the field of view is kept")
    width: IntProperty(
        name="Width", default=512, min=1, soft_max=4096, subtype='PIXEL', update=_cameras_changed,
        description="Image width in pixels (overrides the preset)")
    height: IntProperty(
        name="Height", default=424, min=1, soft_max=4096, subtype='PIXEL', update=_cameras_changed,
        description="Image height in pixels (overrides the preset)")

    use_led_override: BoolProperty(
        name="LED Offset", default=False, update=_cameras_changed,
        description="Move the preset's LEDs: position = LED Spread × preset position + LED Offset")
    led_offset_m: FloatVectorProperty(
        name="LED Offset", size=3, default=(0.0, 0.0, 0.0), subtype='TRANSLATION', unit='LENGTH',
        update=_cameras_changed,
        description="Added to every LED position, in metres, sensor frame: x right, y down, z forward")
    led_spread: FloatProperty(
        name="LED Spread", default=1.0, min=0.0, soft_max=10.0, update=_cameras_changed,
        description="Factor on the preset's LED positions (unitless): 0 puts every LED on the lens "
                    "(no LED shadows), 2 doubles their distance from it")

    noise_model: EnumProperty(
        name="Noise", default='PRESET', update=_settings_changed,
        items=(('PRESET', "Preset", "The preset's noise model"),
               ('none', "None", "No random noise"),
               ('raw', "Raw", "Shot noise (√charge) and read noise on every raw image, in electrons"),
               ('li', "Li", "Gaussian noise on the distance (thesis eq. 2.43); continuous-wave sensors only")),
        description="Random error model (sensor noise.model)")
    use_scattering: BoolProperty(
        name="Lens Scattering", default=True, update=_settings_changed,
        description="Keep the preset's lens scattering PSF (off: scattering.model = none)")
    depth_output: EnumProperty(
        name="Depth", default='PRESET', update=_settings_changed,
        items=(('PRESET', "Preset", "The preset's depth output"),
               ('radial', "Radial", "Distance along the ray from the lens centre, metres"),
               ('z', "Z", "Distance along the optical axis, metres")),
        description="What the depth image holds (sensor depth_output)")
    use_range_m: BoolProperty(
        name="Range", default=False, update=_fill_range,
        description="Override the preset's valid distance range")
    range_m: FloatVectorProperty(
        name="Range", size=2, default=(0.5, 4.5), min=0.0, unit='LENGTH', update=_settings_changed,
        description="Minimum and maximum valid distance in metres; at most the modulation's unambiguous range")

    spp: IntProperty(
        name="Samples", default=64, min=1, soft_max=1024, update=_settings_changed,
        description="Most samples (paths) per pixel; a time budget or target error may stop earlier")
    time_budget_s: FloatProperty(
        name="Time Budget", default=0.0, min=0.0, soft_max=600.0, update=_settings_changed,
        description="Stop before a pass that would end after this many seconds of tracing (0: no budget)")
    target_error_mm: FloatProperty(
        name="Target Error", default=0.0, min=0.0, soft_max=100.0, update=_settings_changed,
        description="Stop once the estimated RMS depth error (Monte Carlo) is at most this, in millimetres "
                    "(0: no target)")
    max_depth: IntProperty(
        name="Max Path Length", default=5, min=1, max=64, update=_settings_changed,
        description="Surface vertices per path (unitless): 1 = direct light only, 2 = one interreflection …")
    seed: IntProperty(
        name="Seed", default=0, min=0, update=_settings_changed,
        description="Random seed (integer); the same seed gives the same frame")

    output_dir: StringProperty(
        name="Output Folder", subtype='DIR_PATH', default="//tof/", options=PATH_OPTIONS,
        description="Folder of the written frame (// = next to the .blend file; a temporary folder while "
                    "the file is unsaved)")
    formats: EnumProperty(
        name="Formats", options={'ENUM_FLAG'}, default=set(FORMATS),
        items=(('exr', "EXR", "frame.exr: float32 depth, amplitude, raw images, ground truth (metres, electrons)"),
               ('png', "PNG", "depth_mm.png (16-bit millimetres) and 8-bit previews"),
               ('ply', "PLY", "points.ply: point cloud in the sensor frame, metres"),
               ('json', "JSON", "frame.json: metadata, convergence log, checksums")),
        description="Files written by Render ToF")

    live_preview: BoolProperty(
        name="Live Preview", default=False, update=_live_preview_toggled,
        description="Re-render at low resolution whenever the scene, this camera or its sensor settings change")
    preview_scale: FloatProperty(
        name="Preview Scale", default=0.25, min=0.05, max=1.0, subtype='FACTOR', update=_settings_changed,
        description="Preview resolution as a fraction of the sensor's (unitless)")
    preview_spp: IntProperty(
        name="Preview Samples", default=8, min=1, soft_max=64, update=_settings_changed,
        description="Most samples (paths) per pixel of a live preview")


class TofMaterialSettings(PropertyGroup):
    """Near-infrared surface parameters of a material (``material.tof``)"""

    use_override: BoolProperty(
        name="Near-IR Override", default=False, update=_material_changed,
        description="Use the values below instead of those derived from the Principled BSDF "
                    "(visible colour is not near-IR reflectance)")
    reflectance: FloatProperty(
        name="IR Reflectance", default=0.5, min=0.0, max=1.0, subtype='FACTOR', update=_material_changed,
        description="Near-IR diffuse albedo (unitless, 0..1) at the sensor's wavelength")
    roughness: FloatProperty(
        name="Roughness", default=0.5, min=0.0, soft_max=math.radians(60.0), subtype='ANGLE', unit='ROTATION',
        update=_material_changed,
        description="Slope deviation σ of the microfacets, radians (shown in the scene's rotation unit); "
                    "0 = smooth")
    extinction: FloatProperty(
        name="Extinction", default=0.0, min=0.0, soft_max=10.0, update=_material_changed,
        description="Conductor absorption coefficient k (unitless; metals only)")


classes = (TofCameraSettings, TofMaterialSettings)


def register() -> None:
    """Attach the groups (the classes are registered by the package first)."""
    bpy.types.Camera.tof = PointerProperty(type=TofCameraSettings)
    bpy.types.Material.tof = PointerProperty(type=TofMaterialSettings)


def unregister() -> None:
    for owner in (bpy.types.Material, bpy.types.Camera):
        if hasattr(owner, "tof"):
            del owner.tof


# --------------------------------------------------------------------------- settings → tofcore.Sensor

def preset_source(settings) -> str:
    """What :func:`tofcore.load_preset` reads: the preset name, or the absolute custom file path."""
    if settings.preset != CUSTOM:
        return settings.preset
    if not settings.preset_path.strip():
        raise tofcore.ConfigError("ToF sensor: preset_path must name a .toml file for preset 'CUSTOM', got ''")
    return bpy.path.abspath(settings.preset_path)


def _preset_sensor(settings):
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
        The preset cannot be read, or an override is invalid; the message starts with the override's
        UI name and property, e.g. ``"ToF override Range (range_m): …"``.
    """
    sensor = tofcore.load_preset(preset_source(settings))
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
