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
``time_budget_s``      s       0           render in about this long, set-up to frame (0: no budget)
``target_error_mm``    mm      0           stop at this estimated RMS depth error (0: no target)
``max_depth``          –       5           surface vertices per path (1 = direct light only)
``seed``               –       0           random seed (same seed, same frame)
``output_dir``         –       //tof/####/  folder of the written frame (``//`` = next to the .blend, ``####``
                                            = the frame number)
``formats``            –       all         any of exr, png, ply, json (``tofcore.write_frame``)
``live_preview``       –       False       re-render at low resolution whenever the scene or sensor changes
``preview_scale``      1       0.25        preview resolution as a fraction of the sensor's
``preview_spp``        –       8           most samples per pixel of a preview
``preview_denoise``    –       True        amplitude-guided bilateral filter on the preview's depth
=====================  ======  ==========  ===================================================================

Property names follow the ``tofcore`` field names (``range_m``, ``depth_output``,
``spp``, ``max_depth`` …). :func:`.sensors.sensor_from_settings` turns the settings into a
:class:`tofcore.Sensor` and names the override at fault when one is invalid; the
update callbacks (restart the live preview, move the LED empties) live in :mod:`.updates`.

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

from . import sensors, updates

#: Path properties accept "//" (relative to the .blend); Blender 5.0 made that an explicit option.
PATH_OPTIONS = {'PATH_SUPPORTS_BLEND_RELATIVE'} if bpy.app.version >= (5, 0, 0) else set()


# --------------------------------------------------------------------------- property groups

class TofCameraSettings(PropertyGroup):
    """The ToF sensor of a camera (``camera.tof``)"""

    enabled: BoolProperty(
        name="ToF Sensor", default=False, update=updates.cameras_changed,
        description="Use this camera as a ToF sensor: its intrinsics and LED empties follow the sensor settings")
    preset: EnumProperty(
        name="Preset", items=sensors.PRESET_ITEMS, default=sensors.DEFAULT_PRESET, update=updates.cameras_changed,
        description="Sensor preset: intrinsics, LEDs, modulation, noise and lens scattering of a real camera")
    preset_path: StringProperty(
        name="Preset File", subtype='FILE_PATH', default="", options=PATH_OPTIONS, update=updates.cameras_changed,
        description="Custom preset: a .toml file in the format of the shipped presets (// = next to the .blend)")

    use_resolution: BoolProperty(
        name="Resolution", default=False, update=updates.fill_resolution,
        description="Override the preset's resolution; the intrinsics are scaled so the field of view is kept")
    width: IntProperty(
        name="Width", default=512, min=1, soft_max=4096, subtype='PIXEL', update=updates.cameras_changed,
        description="Image width in pixels (overrides the preset)")
    height: IntProperty(
        name="Height", default=424, min=1, soft_max=4096, subtype='PIXEL', update=updates.cameras_changed,
        description="Image height in pixels (overrides the preset)")

    use_led_override: BoolProperty(
        name="LED Offset", default=False, update=updates.cameras_changed,
        description="Move the preset's LEDs: position = LED Spread × preset position + LED Offset")
    led_offset_m: FloatVectorProperty(
        name="LED Offset", size=3, default=(0.0, 0.0, 0.0), subtype='TRANSLATION', unit='LENGTH',
        update=updates.cameras_changed,
        description="Added to every LED position, in metres, sensor frame: x right, y down, z forward")
    led_spread: FloatProperty(
        name="LED Spread", default=1.0, min=0.0, soft_max=10.0, update=updates.cameras_changed,
        description="Factor on the preset's LED positions (unitless): 0 puts every LED on the lens "
                    "(no LED shadows), 2 doubles their distance from it")

    noise_model: EnumProperty(
        name="Noise", default='PRESET', update=updates.settings_changed,
        items=(('PRESET', "Preset", "The preset's noise model"),
               ('none', "None", "No random noise"),
               ('raw', "Raw", "Shot noise (√charge) and read noise on every raw image, in electrons"),
               ('li', "Li", "Gaussian noise on the distance (thesis eq. 2.43); continuous-wave sensors only")),
        description="Random error model (sensor noise.model)")
    use_scattering: BoolProperty(
        name="Lens Scattering", default=True, update=updates.settings_changed,
        description="Keep the preset's lens scattering PSF (off: scattering.model = none)")
    depth_output: EnumProperty(
        name="Depth", default='PRESET', update=updates.settings_changed,
        items=(('PRESET', "Preset", "The preset's depth output"),
               ('radial', "Radial", "Distance along the ray from the lens centre, metres"),
               ('z', "Z", "Distance along the optical axis, metres")),
        description="What the depth image holds (sensor depth_output)")
    use_range_m: BoolProperty(
        name="Range", default=False, update=updates.fill_range,
        description="Override the preset's valid distance range")
    range_m: FloatVectorProperty(
        name="Range", size=2, default=(0.5, 4.5), min=0.0, unit='LENGTH', update=updates.settings_changed,
        description="Minimum and maximum valid distance in metres; at most the modulation's unambiguous range")

    spp: IntProperty(
        name="Samples", default=64, min=1, soft_max=1024, update=updates.settings_changed,
        description="Most samples (paths) per pixel; a time budget or target error may stop earlier")
    time_budget_s: FloatProperty(
        name="Time Budget", default=0.0, min=0.0, soft_max=600.0, update=updates.settings_changed,
        description="Render in about this many seconds, set-up to final frame: the last passes are sized to "
                    "use it (0: no budget)")
    target_error_mm: FloatProperty(
        name="Target Error", default=0.0, min=0.0, soft_max=100.0, update=updates.settings_changed,
        description="Stop once the estimated RMS depth error (Monte Carlo) is at most this, in millimetres "
                    "(0: no target)")
    max_depth: IntProperty(
        name="Max Path Length", default=5, min=1, max=64, update=updates.settings_changed,
        description="Surface vertices per path (unitless): 1 = direct light only, 2 = one interreflection …")
    seed: IntProperty(
        name="Seed", default=0, min=0, update=updates.settings_changed,
        description="Random seed (integer); the same seed gives the same frame")

    output_dir: StringProperty(
        name="Output Folder", subtype='DIR_PATH', default="//tof/####/", options=PATH_OPTIONS,
        description="Folder of the written frame; #### = the frame number, zero-padded (// = next to the "
                    ".blend file; a temporary folder while the file is unsaved)")
    formats: EnumProperty(
        name="Formats", options={'ENUM_FLAG'}, default=set(sensors.FORMATS),
        items=(('exr', "EXR", "frame.exr: float32 depth, amplitude, raw images, ground truth (metres, electrons)"),
               ('png', "PNG", "depth_mm.png (16-bit millimetres) and 8-bit previews"),
               ('ply', "PLY", "points.ply: point cloud in the sensor frame, metres"),
               ('json', "JSON", "frame.json: metadata, convergence log, checksums")),
        description="Files written by Render ToF")

    live_preview: BoolProperty(
        name="Live Preview", default=False, update=updates.live_preview_toggled,
        description="Re-render at low resolution whenever the scene, this camera or its sensor settings change")
    preview_scale: FloatProperty(
        name="Preview Scale", default=0.25, min=0.05, max=1.0, subtype='FACTOR', update=updates.settings_changed,
        description="Preview resolution as a fraction of the sensor's (unitless)")
    preview_spp: IntProperty(
        name="Preview Samples", default=8, min=1, soft_max=64, update=updates.settings_changed,
        description="Most samples (paths) per pixel of a live preview")
    preview_denoise: BoolProperty(
        name="Denoise Preview", default=True, update=updates.settings_changed,
        description="Smooth the live preview's depth with a joint bilateral filter guided by the amplitude "
                    "image: less render noise, a small bias at depth edges. Never applied to Render ToF")


class TofMaterialSettings(PropertyGroup):
    """Near-infrared surface parameters of a material (``material.tof``)"""

    use_override: BoolProperty(
        name="Near-IR Override", default=False, update=updates.material_changed,
        description="Use the values below instead of those derived from the Principled BSDF "
                    "(visible colour is not near-IR reflectance)")
    reflectance: FloatProperty(
        name="IR Reflectance", default=0.5, min=0.0, max=1.0, subtype='FACTOR', update=updates.material_changed,
        description="Near-IR diffuse albedo (unitless, 0..1) at the sensor's wavelength")
    roughness: FloatProperty(
        name="Roughness", default=0.5, min=0.0, soft_max=math.radians(60.0), subtype='ANGLE', unit='ROTATION',
        update=updates.material_changed,
        description="Slope deviation σ of the microfacets, radians (shown in the scene's rotation unit); "
                    "0 = smooth")
    extinction: FloatProperty(
        name="Extinction", default=0.0, min=0.0, soft_max=10.0, update=updates.material_changed,
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
