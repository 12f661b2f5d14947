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
``panels``          the ToF Sensor and Near-IR panels, menu entries
``export``          evaluated depsgraph → ``tofcore.Scene``
``mapping``         Blender ↔ tofcore conversions without bpy (materials, world, intrinsics)
``images``          a ``tofcore.Frame`` as Blender images
==================  ============================================================================

The package also works as a plain add-on folder (``import addon;
addon.register()``), which is how the tests load it into the ``bpy`` module.
"""

from __future__ import annotations

import bpy

from . import operators, panels, preferences, properties

#: Registered in this order (property groups before the panels that draw them), unregistered in reverse.
classes = (*preferences.classes, *properties.classes, *operators.classes, *panels.classes)

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
