"""Sensor presets the Blender way: a preset menu with add and remove in the ToF Sensor panel.

Blender's preset mechanism (``bl_operators.presets.AddPresetBase``, ``Menu.draw_preset``)
saves the camera's ToF sensor settings — the tofcore preset or Preset File, every override,
the quality settings — as a small Python file in the user's preset folder
(``scripts/presets/tof_camera/sensor/<name>.py`` of Blender's user resources), listed in the
"Sensor Presets" menu of every .blend file. So a custom sensor (say, a Kinect v2 at half
resolution with its LEDs moved and no noise) is saved and reused without writing TOML.
Choosing a preset runs Blender's ``script.execute_preset`` on the camera shown in the
Properties editor (else the scene camera); "−" removes the preset last chosen.

The file is written by :func:`preset_text` (the operator's ``add``), not by ``AddPresetBase``'s
own writer: that one runs ``exec`` on ``preset_defines`` into a function's locals, which Python 3.13
no longer lets a later ``eval`` see (PEP 667), so on Blender 4.3 with Python 3.13 (Debian's)
every add failed with "name 'tof' is not defined" (found by the real-Blender GUI test).
"""

from __future__ import annotations

from bl_operators.presets import AddPresetBase
from bpy.types import Menu, Operator

#: Folder below Blender's ``scripts/presets``.
PRESET_SUBDIR = "tof_camera/sensor"
#: The camera.tof properties a preset stores (sensor and quality; not the output folder or the preview).
PRESET_PROPERTIES = ("preset", "preset_path", "use_resolution", "width", "height", "use_led_override",
                     "led_offset_m", "led_spread", "noise_model", "use_scattering", "depth_output", "use_range_m",
                     "range_m", "spp", "time_budget_s", "target_error_mm", "max_depth", "seed")


class TOF_MT_sensor_presets(Menu):
    """Saved ToF sensor settings: choose one to apply it to this camera"""

    bl_label = "Sensor Presets"
    preset_subdir = PRESET_SUBDIR
    preset_operator = "script.execute_preset"
    draw = Menu.draw_preset


class TOF_OT_sensor_preset_add(AddPresetBase, Operator):
    """Save this camera's ToF sensor and quality settings as a preset (or remove the preset last chosen)"""

    bl_idname = "tof.sensor_preset_add"
    bl_label = "Add Sensor Preset"
    bl_options = {'REGISTER', 'UNDO'}
    preset_menu = TOF_MT_sensor_presets.__name__
    preset_subdir = PRESET_SUBDIR

    def add(self, context, filepath: str) -> None:
        """Write the preset file (AddPresetBase calls this instead of its own writer)."""
        settings = (getattr(context, "camera", None) or context.scene.camera.data).tof
        with open(filepath, "w", encoding="utf-8") as fh:
            fh.write(preset_text(settings))


#: The preset file's first lines: the camera of the Properties editor when there is one, else the scene camera.
PRESET_HEADER = ('import bpy\n'
                 'tof = (getattr(bpy.context, "camera", None) or bpy.context.scene.camera.data).tof\n\n')


def preset_text(settings) -> str:
    """The Python preset file of ``camera.tof`` settings: the header, then ``tof.<name> = <value>`` lines."""
    lines = []
    for name in PRESET_PROPERTIES:
        value = getattr(settings, name)
        if not isinstance(value, (str, int, float, bool)):
            value = tuple(value)  # vector properties
        lines.append(f"tof.{name} = {value!r}\n")
    return PRESET_HEADER + "".join(lines)


def draw_preset_row(layout) -> None:
    """The menu and its + / − buttons, as in Blender's own panels."""
    row = layout.row(align=True)
    row.menu(TOF_MT_sensor_presets.__name__, text=TOF_MT_sensor_presets.bl_label)
    row.operator(TOF_OT_sensor_preset_add.bl_idname, text="", icon='ADD')
    row.operator(TOF_OT_sensor_preset_add.bl_idname, text="", icon='REMOVE').remove_active = True


classes = (TOF_MT_sensor_presets, TOF_OT_sensor_preset_add)
