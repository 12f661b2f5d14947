"""User interface: the "ToF Sensor" camera panel, the "Near-IR" material panel, menu entries.

* Properties editor › Camera data › **ToF Sensor** (header checkbox = ``camera.tof.enabled``):
  Sensor Presets (+/−), preset, Apply Sensor to Camera, Render ToF, Animation, Live Preview, the last
  result; sub-panels
  Overrides, Quality, Output, Live Preview.
* Properties editor › Material › **Near-IR**: the IR override of ``material.tof``.
* Image editor › sidebar › **ToF**: Render ToF and the last result beside the images.
* 3D Viewport › Add › **ToF Camera**; Topbar › Render › **Render ToF**, **Render ToF Animation**.

Operators are referred to by their ``bl_idname``.
"""

from __future__ import annotations

import bpy
from bpy.types import Panel

from . import compiled, gpu, operators, presets, sensors
from .animation import TOF_OT_render_animation
from .operators import TOF_OT_add_camera, TOF_OT_apply_sensor, TOF_OT_cancel_render, TOF_OT_render

_STATE_TEXT = {"running": "Rendering", "done": "Done", "cancelled": "Cancelled", "error": "Failed"}


def draw_result(layout, camera_name: str | None = None) -> None:
    """The last (or running) render: state, progress, estimated depth error, time, device, files."""
    result = operators.last_result
    if not result or (camera_name is not None and result.get("camera") != camera_name):
        return
    box = layout.box()
    kind = "Live preview" if result.get("kind") == "preview" else "Render"
    state = result.get("state", "")
    box.label(text=f"{kind} of {result.get('camera', '?')}: {_STATE_TEXT.get(state, state)}",
              icon='ERROR' if state == "error" else 'RENDER_RESULT')
    if state == "error":
        box.label(text=result.get("message", ""))
        return
    text = operators.progress_text(result)
    running = operators.active_render_job() or operators.active_preview_job()
    if state == "running" and running is not None and bpy.app.version >= (4, 0, 0):
        box.progress(factor=operators.progress_fraction(running), type='BAR', text=text)
    else:
        box.label(text=text)
    if state == "running" and not result.get("spp") and compiled.compiling():
        box.label(text="Compiling the tracer once, in the background (30 s to 3 min)…", icon='SORTTIME')
    if state == "running":
        box.operator(TOF_OT_cancel_render.bl_idname, icon='CANCEL')
    if result.get("device"):
        box.label(text=f"Device: {result['device']}", icon='MEMORY' if result.get("device_name") == "gpu"
                  else 'DESKTOP')
    if result.get("fallback_reason"):
        box.label(text=gpu.fallback_warning(result["fallback_reason"]), icon='ERROR')
    tracer = compiled.tracer_text(result.get("transport"))
    if tracer:
        box.label(text=tracer, icon='SETTINGS')
    if result.get("files"):
        box.label(text=f"{result['files']} files in {result.get('out_dir', '')}", icon='FILE_FOLDER')
    if "resolution" in result:
        width, height = result["resolution"]
        box.label(text=f"Images: {', '.join(operators.images.IMAGE_NAMES.values())} ({width} × {height})",
                  icon='IMAGE_DATA')
    if result.get("convergence_image"):
        box.label(text=f"Convergence plot: {result['convergence_image']}", icon='GRAPH')


def _settings_layout(panel, context):
    """The camera's ToF settings and the panel's layout, split, greyed out while ToF is off."""
    settings = context.camera.tof
    layout = panel.layout
    layout.use_property_split = True
    layout.use_property_decorate = False
    layout.active = settings.enabled
    return settings, layout


class _CameraPanel:
    bl_space_type = 'PROPERTIES'
    bl_region_type = 'WINDOW'
    bl_context = 'data'

    @classmethod
    def poll(cls, context):
        return context.camera is not None and hasattr(context.camera, "tof")


class TOF_PT_camera(_CameraPanel, Panel):
    """Time-of-Flight sensor of this camera"""

    bl_idname = "TOF_PT_camera"
    bl_label = "ToF Sensor"

    def draw_header(self, context):
        self.layout.prop(context.camera.tof, "enabled", text="")

    def draw(self, context):
        settings, layout = _settings_layout(self, context)
        presets.draw_preset_row(layout)
        layout.prop(settings, "preset")
        if settings.preset == sensors.CUSTOM:
            layout.prop(settings, "preset_path")
        layout.operator(TOF_OT_apply_sensor.bl_idname, icon='FILE_REFRESH')
        row = layout.row(align=True)
        row.scale_y = 1.5
        row.operator(TOF_OT_render.bl_idname, icon='RENDER_STILL')
        row.operator(TOF_OT_render_animation.bl_idname, icon='RENDER_ANIMATION', text="Animation")
        layout.prop(settings, "live_preview")
        draw_result(layout, context.object.name if context.object else None)


class TOF_PT_camera_overrides(_CameraPanel, Panel):
    """Changes to the preset's fields"""

    bl_label = "Overrides"
    bl_parent_id = TOF_PT_camera.bl_idname
    bl_options = {'DEFAULT_CLOSED'}

    def draw(self, context):
        settings, layout = _settings_layout(self, context)
        for toggle, fields in (("use_resolution", ("width", "height")),
                               ("use_led_override", ("led_offset_m", "led_spread")),
                               ("use_range_m", ("range_m",))):
            col = layout.column(heading=settings.bl_rna.properties[toggle].name)
            col.prop(settings, toggle, text="Override")
            sub = col.column(align=True)
            sub.active = getattr(settings, toggle)
            for field in fields:
                sub.prop(settings, field)
        layout.prop(settings, "noise_model")
        layout.prop(settings, "use_scattering")
        layout.prop(settings, "depth_output")


class TOF_PT_camera_quality(_CameraPanel, Panel):
    """When the progressive render stops, and how long paths may be"""

    bl_label = "Quality"
    bl_parent_id = TOF_PT_camera.bl_idname

    def draw(self, context):
        settings, layout = _settings_layout(self, context)
        col = layout.column(align=True)
        col.prop(settings, "spp")
        col.prop(settings, "time_budget_s")
        col.prop(settings, "target_error_mm")
        layout.prop(settings, "max_depth")
        layout.prop(settings, "seed")


class TOF_PT_camera_output(_CameraPanel, Panel):
    """Where Render ToF writes the final frame"""

    bl_label = "Output"
    bl_parent_id = TOF_PT_camera.bl_idname

    def draw(self, context):
        settings, layout = _settings_layout(self, context)
        layout.prop(settings, "output_dir")
        path = settings.output_dir
        if path.startswith("//") and not bpy.data.filepath:  # say where "//" goes while the file is unsaved
            layout.label(text=f"Unsaved file: // is {operators.unsaved_folder()}", icon='INFO')
        if "#" in path:
            frame = context.scene.frame_current
            layout.label(text=f"Frame {frame}: {operators.output_folder(path, frame)}", icon='FILE_FOLDER')
        row = layout.row(heading="Formats", align=True)
        row.prop(settings, "formats")


class TOF_PT_camera_preview(_CameraPanel, Panel):
    """Low-resolution re-render whenever the scene or the sensor changes"""

    bl_label = "Live Preview"
    bl_parent_id = TOF_PT_camera.bl_idname
    bl_options = {'DEFAULT_CLOSED'}

    def draw_header(self, context):
        self.layout.prop(context.camera.tof, "live_preview", text="")

    def draw(self, context):
        settings = context.camera.tof
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        layout.active = settings.enabled and settings.live_preview
        layout.prop(settings, "preview_scale")
        layout.prop(settings, "preview_spp")
        layout.prop(settings, "preview_denoise")


class TOF_PT_material(Panel):
    """Near-infrared surface parameters; by default derived from the Principled BSDF"""

    bl_label = "Near-IR"
    bl_space_type = 'PROPERTIES'
    bl_region_type = 'WINDOW'
    bl_context = 'material'

    @classmethod
    def poll(cls, context):
        return context.material is not None and hasattr(context.material, "tof")

    def draw_header(self, context):
        self.layout.prop(context.material.tof, "use_override", text="")

    def draw(self, context):
        settings = context.material.tof
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        if not settings.use_override:
            layout.label(text="Derived from the Principled BSDF (tick to override)", icon='INFO')
        col = layout.column()
        col.active = settings.use_override
        col.prop(settings, "reflectance")
        col.prop(settings, "roughness")
        col.prop(settings, "extinction")


class TOF_PT_image(Panel):
    """Render ToF and its progress beside the result images"""

    bl_label = "ToF"
    bl_space_type = 'IMAGE_EDITOR'
    bl_region_type = 'UI'
    bl_category = "ToF"

    def draw(self, context):
        layout = self.layout
        layout.operator(TOF_OT_render.bl_idname, icon='RENDER_STILL')
        draw_result(layout)


def draw_add_menu(self, context):
    self.layout.operator(TOF_OT_add_camera.bl_idname, text="ToF Camera", icon='OUTLINER_OB_CAMERA')


def draw_render_menu(self, context):
    self.layout.separator()
    self.layout.operator(TOF_OT_render.bl_idname, icon='RENDER_STILL')
    self.layout.operator(TOF_OT_render_animation.bl_idname, icon='RENDER_ANIMATION')


_MENUS = (("VIEW3D_MT_add", draw_add_menu), ("TOPBAR_MT_render", draw_render_menu))

classes = (TOF_PT_camera, TOF_PT_camera_overrides, TOF_PT_camera_quality, TOF_PT_camera_output,
           TOF_PT_camera_preview, TOF_PT_material, TOF_PT_image)


def register() -> None:
    """Menu entries (the classes are registered by the package first)."""
    for menu, draw in _MENUS:
        menu_type = getattr(bpy.types, menu, None)
        if menu_type is not None:
            menu_type.remove(draw)  # no duplicate entry if registered twice
            menu_type.append(draw)


def unregister() -> None:
    for menu, draw in _MENUS:
        menu_type = getattr(bpy.types, menu, None)
        if menu_type is not None:
            menu_type.remove(draw)
