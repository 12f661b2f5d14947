"""Add-on preferences: defaults for new ToF cameras, tracer threads, live-preview delay.

=======================  ====  =========  ==============================================================
preference               unit  default    meaning
=======================  ====  =========  ==============================================================
``default_output_dir``   –     //tof/     output folder of new ToF cameras (``//`` = next to the .blend)
``workers``              –     0          tracer threads per render; 0 = one per CPU
``preview_delay_s``      s     0.5        the live preview restarts this long after the last change
=======================  ====  =========  ==============================================================

:func:`get` returns the preferences, or their defaults when the package is not
enabled through Blender's add-on system (tests import it as a plain package).
"""

from __future__ import annotations

from types import SimpleNamespace

import bpy
from bpy.props import FloatProperty, IntProperty, StringProperty
from bpy.types import AddonPreferences

DEFAULT_OUTPUT_DIR = "//tof/"
PREVIEW_DELAY_S = 0.5


class TofPreferences(AddonPreferences):
    bl_idname = __package__

    default_output_dir: StringProperty(
        name="Default Output Folder", subtype='DIR_PATH', default=DEFAULT_OUTPUT_DIR,
        options={'PATH_SUPPORTS_BLEND_RELATIVE'} if bpy.app.version >= (5, 0, 0) else set(),
        description="Output folder of new ToF cameras (// = next to the .blend file)")
    workers: IntProperty(
        name="Tracer Threads", default=0, min=0, soft_max=64,
        description="Threads tracing rays per render (count); 0 uses one per CPU")
    preview_delay_s: FloatProperty(
        name="Live Preview Delay", default=PREVIEW_DELAY_S, min=0.0, soft_max=5.0,
        description="The live preview restarts this many seconds after the last change to the scene or sensor")

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.prop(self, "default_output_dir")
        layout.prop(self, "workers")
        layout.prop(self, "preview_delay_s")


_DEFAULTS = SimpleNamespace(default_output_dir=DEFAULT_OUTPUT_DIR, workers=0, preview_delay_s=PREVIEW_DELAY_S)


def get(context=None):
    """The add-on's preferences, or an object with their defaults when the add-on is not enabled."""
    context = context or bpy.context
    addon = context.preferences.addons.get(__package__) if context.preferences else None
    return addon.preferences if addon is not None and addon.preferences is not None else _DEFAULTS


classes = (TofPreferences,)


def register() -> None:
    pass


def unregister() -> None:
    pass
