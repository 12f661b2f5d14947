"""Optional native packages (OpenCV, matplotlib), and the one rule for loading them: never inside Blender.

tofcore needs only NumPy and the standard library. OpenCV (``cv2``: faster PNG encoding and PSF
convolution, a drawing backend) and matplotlib (the convergence plot) are used when importable,
for speed or looks, never for a different result.

Inside Blender's process they are not imported. Blender has already loaded its own native
libraries — OpenEXR, OpenImageIO, libpng, libjpeg, zlib, FreeType, TBB — and a Python extension
that brings a second copy of one of them can have its calls resolved against Blender's copy of a
different version (ELF symbol interposition). Issue 19 saw exactly that: the ``OpenEXR`` wheel
inside Blender 4.3 first failed ("Unable to set long name support flag"), then crashed Blender in
Blender's own ``libOpenEXRCore``. The ``opencv-python`` wheels bundle OpenEXR, libpng, libjpeg,
libtiff, libwebp and FFmpeg; matplotlib bundles FreeType. So when ``bpy`` is loaded (Blender, or
the ``bpy`` module, which is Blender in a Python process), :func:`optional_module` answers None
and tofcore takes its NumPy paths, which give the same images (tested).
"""

from __future__ import annotations

import importlib
import sys
from types import ModuleType


def inside_blender() -> bool:
    """Whether this process has Blender loaded (``bpy`` imported: Blender itself or the bpy module)."""
    return "bpy" in sys.modules


def optional_module(name: str) -> ModuleType | None:
    """The module ``name`` (e.g. ``"cv2"``), or None when it is not installed or this is Blender's process."""
    if inside_blender():
        return None
    try:
        return importlib.import_module(name)
    except ImportError:
        return None
