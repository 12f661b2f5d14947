"""ToF Camera Simulator: Time-of-Flight sensors (Kinect v2, O3D303, Xtion 2 or your own) for Blender.

The extension's metadata lives in ``blender_manifest.toml``; this package only
delegates:

==================  ============================================================================
module              concept
==================  ============================================================================
``preferences``     add-on preferences (default output folder, tracer threads, preview delay, device),
                    Install CuPy for GPU rendering, Check GPU
``gpu``             CuPy in Blender's Python: its folder, the pip command, CUDA libraries, GPU status
``properties``      ``camera.tof`` and ``material.tof`` (the property groups)
``sensors``         the preset choices, ``camera.tof`` → ``tofcore.Sensor`` and render keywords
``updates``         the settings' update callbacks: cameras and LED empties follow, the live preview restarts
``operators``       Add ToF Camera, Apply Sensor to Camera, Render ToF, the live preview
``animation``       Render ToF Animation: the scene's frame range into numbered folders
``presets``         the Sensor Presets menu with add/remove (Blender's preset mechanism)
``panels``          the ToF Sensor and Near-IR panels, menu entries
``export``          evaluated depsgraph → ``tofcore.Scene``
``mapping``         Blender ↔ tofcore conversions without bpy (materials, world, intrinsics)
``images``          a ``tofcore.Frame`` as Blender images
==================  ============================================================================

The package also works as a plain add-on folder (``import addon;
addon.register()``), which is how the tests load it into the ``bpy`` module.
"""

from __future__ import annotations

import sys

import bpy

#: The oldest Blender (extensions, ``blender_manifest.toml``'s ``blender_version_min``) and Python it runs on.
MIN_BLENDER = (4, 2, 0)
MIN_PYTHON = (3, 11)


def host_problem(blender: tuple[int, ...], python: tuple[int, ...]) -> str | None:
    """Why this Blender cannot run the add-on, in one line, or None."""
    if tuple(blender[:3]) < MIN_BLENDER:
        return (f"ToF Camera Simulator needs Blender {'.'.join(map(str, MIN_BLENDER))} or newer (it is an "
                f"extension), this is Blender {'.'.join(map(str, blender[:3]))}")
    if tuple(python[:2]) < MIN_PYTHON:
        return (f"ToF Camera Simulator needs Python {'.'.join(map(str, MIN_PYTHON))} or newer in Blender, "
                f"this Blender has Python {'.'.join(map(str, python[:2]))}")
    return None


# Before the modules that import tofcore: on an older Blender (where the bundled wheel is not installed) the
# user reads this line instead of "No module named 'tofcore'".
if (_problem := host_problem(bpy.app.version, sys.version_info)) is not None:
    raise ImportError(_problem)

from . import animation, operators, panels, preferences, presets, properties  # noqa: E402

#: Registered in this order (property groups before the panels that draw them), unregistered in reverse.
classes = (*preferences.classes, *properties.classes, *operators.classes, *animation.classes, *presets.classes,
           *panels.classes)

#: Their ``register()`` hooks (pointer properties, handlers, menus) run after the classes.
_modules = (preferences, properties, operators, panels)


def register() -> None:
    if any(cls.is_registered for cls in classes):  # registered already: start over cleanly
        unregister()
    for cls in classes:
        bpy.utils.register_class(cls)
    for module in _modules:
        module.register()


def unregister() -> None:
    for module in reversed(_modules):
        module.unregister()
    for cls in reversed(classes):
        if cls.is_registered:
            bpy.utils.unregister_class(cls)
