"""Codes and sizes shared by the compiled kernels and the NumPy code that packs their arrays (no numba here)."""

from __future__ import annotations

from ..scene.led import KINDS as LED_KINDS  # index = LED kind code: 0 point, 1 Lambertian
from ..scene.material import PARAMETER_NAMES as MATERIAL_COLUMNS  # reflectance, roughness, metallic, ior, extinction

PHASOR, SINE, SQUARE, PULSED = 0, 1, 2, 3
"""Kinds of correlation channel (tofcore.modulation's functions)."""

POINT, LAMBERTIAN = LED_KINDS.index("point"), LED_KINDS.index("lambertian")

N_COUNTERS = 5
"""Ray counters per pixel: camera, bounce, shadow and light rays, skipped first-hit shadow rays."""

STACK_SIZE = 128
"""Traversal stack entries per ray (a 4-wide tree pushes at most 3 a level)."""
