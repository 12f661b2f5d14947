"""Codes and sizes shared by the compiled kernels and the NumPy code that packs their arrays (no numba here)."""

from __future__ import annotations

from ..scene.led import KINDS as LED_KINDS  # index = LED kind code: 0 point, 1 Lambertian
from ..scene.material import PARAMETER_NAMES as MATERIAL_COLUMNS  # reflectance … extinction, coat, coat_roughness
from ..scene.material import TEXTURE_SLOTS

PHASOR, SINE, SQUARE, PULSED, HARMONIC, TABLE = 0, 1, 2, 3, 4, 5
"""Kinds of correlation channel (tofcore.sensor.modulation's functions; HARMONIC and TABLE are custom
waveforms given as data: a Fourier series, a table over one period)."""

REFLECTANCE, ROUGHNESS, METALLIC, IOR, EXTINCTION, COAT, COAT_ROUGHNESS = (
    MATERIAL_COLUMNS.index(name) for name in ("reflectance", "roughness", "metallic", "ior", "extinction", "coat",
                                              "coat_roughness"))
"""The named fields of the kernels' ``params`` tuple and material columns (tofcore.scene.material.PARAMETERS)."""

REFLECTANCE_MAP, ROUGHNESS_MAP, METALLIC_MAP, NORMAL_MAP = (TEXTURE_SLOTS.index(name) for name in (
    "reflectance_texture", "roughness_texture", "metallic_texture", "normal_texture"))
"""A material's row of the kernels' texture slots, by name (the texture's index, −1: none)."""

POINT, LAMBERTIAN = LED_KINDS.index("point"), LED_KINDS.index("lambertian")

LED_COLUMNS = ("kind", "intensity_w_sr", "power_w", "probability", "skip_first_shadow")
"""The kernels' LED table, one row per LED: kind code, intensity (W/sr), power (W), emission probability,
whether the first hit's shadow ray is skipped (tofcore.compiled.setup.led_arrays)."""
LED_KIND, LED_INTENSITY, LED_POWER, LED_PROBABILITY, LED_SKIP_FIRST_SHADOW = range(len(LED_COLUMNS))

N_COUNTERS = 5
"""Ray counters per pixel: camera, bounce, shadow and light rays, skipped first-hit shadow rays."""

STACK_SIZE = 128
"""Traversal stack entries per ray (a 4-wide tree pushes at most 3 a level)."""
STACK_T_SIZE = STACK_SIZE + 4
"""float32 entries beside the stack: its entry distances, then the 4 children's of the node being opened."""
