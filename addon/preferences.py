"""Add-on preferences: defaults for new ToF cameras, tracer threads, live-preview delay, the render device.

=======================  ====  ============  ==========================================================
preference               unit  default       meaning
=======================  ====  ============  ==========================================================
``default_output_dir``   –     //tof/####/   output folder of new ToF cameras (``//`` = next to the .blend)
``workers``              –     0             tracer threads per render; 0 = one per CPU
``preview_delay_s``      s     0.5           the live preview restarts this long after the last change
``device``               –     cpu           where Render ToF and the live preview run: ``cpu`` (NumPy),
                                             ``gpu`` (CuPy on an NVIDIA GPU) or ``auto`` (the GPU when it
                                             works, else the CPU with a warning) — ``tofcore``'s ``device``
``cupy_package``         –     cupy-cuda12x  the CuPy wheel "Install CuPy for GPU rendering" installs:
                                             ``cupy-cuda12x`` (CUDA 12, driver ≥ 525) or ``cupy-cuda13x``
                                             (CUDA 13, driver ≥ 580)
=======================  ====  ============  ==========================================================

The compiled-tracer box shows whether numba is installed and which tracer the last render used;
"Install numba for the compiled tracer" installs it the same way (:mod:`.compiled`).

The GPU box shows whether CuPy is installed in Blender's Python and, once checked (Check GPU) or rendered
with, which GPU runs; :mod:`.gpu` computes it lazily and caches it, and imports CuPy only for a check or a
GPU render, never at registration. "Install CuPy for GPU rendering" runs pip with Blender's own Python into
the extension's user folder (:mod:`.gpu` explains why there, and which packages); once the GPU answers, the
kernels a GPU render compiles are compiled in the background by one child process of Blender's Python
(``tofcore warmup --device gpu``, :class:`.gpu.Warmup`), its state a line of the GPU box (warming… with its
seconds, ready in N s, or failed: why). After "Install numba" the CPU tracer compiles the same way
(``tofcore.compiled.child_compile``), its state in the compiled-tracer box. These children are the only
processes the add-on starts besides pip; nothing forks the Blender process itself.

:func:`get` returns the preferences, or their defaults when the package is not
enabled through Blender's add-on system (tests import it as a plain package).
"""

from __future__ import annotations

import os
import sys
import textwrap
import time
from types import SimpleNamespace

import bpy
from bpy.props import EnumProperty, FloatProperty, IntProperty, StringProperty
from bpy.types import AddonPreferences, Operator

from . import compiled, gpu

DEFAULT_OUTPUT_DIR = "//tof/####/"
PREVIEW_DELAY_S = 0.5
DEFAULT_DEVICE = "cpu"
#: How often the installer's modal operator polls pip, seconds.
POLL_INTERVAL_S = 0.25
#: Characters per line of the status text in the preferences (labels do not wrap).
STATUS_WIDTH = 100

DEVICE_ITEMS = (
    ('cpu', "CPU", "NumPy on the processor: always available, the reference results; uses Tracer Threads"),
    ('gpu', "GPU (CUDA, CuPy)",
     "CuPy on an NVIDIA GPU, the same frame much faster; needs CuPy in Blender's Python (Install CuPy below) "
     "and an NVIDIA driver. Without a usable GPU a render stops with the reason"),
    ('auto', "Auto",
     "The GPU when CuPy and a CUDA device work, else the CPU, with a warning that names why"),
)


class TofPreferences(AddonPreferences):
    bl_idname = __package__

    default_output_dir: StringProperty(
        name="Default Output Folder", subtype='DIR_PATH', default=DEFAULT_OUTPUT_DIR,
        options={'PATH_SUPPORTS_BLEND_RELATIVE'} if bpy.app.version >= (5, 0, 0) else set(),
        description="Output folder of new ToF cameras (// = next to the .blend file)")
    workers: IntProperty(
        name="Tracer Threads", default=0, min=0, soft_max=64,
        description="Threads tracing rays per render on the CPU (count); 0 uses one per CPU")
    preview_delay_s: FloatProperty(
        name="Live Preview Delay", default=PREVIEW_DELAY_S, min=0.0, soft_max=5.0,
        description="The live preview restarts this many seconds after the last change to the scene or sensor")
    device: EnumProperty(
        name="Device", items=DEVICE_ITEMS, default=DEFAULT_DEVICE,
        description="Where Render ToF and the live preview run (tofcore device)")
    cupy_package: EnumProperty(
        name="CUDA", default=gpu.DEFAULT_PACKAGE,
        items=tuple((line.package, line.label, line.description) for line in gpu.CUDA_LINES),
        description="Which CuPy wheel Install CuPy downloads; pick by the NVIDIA driver installed "
                    "(nvidia-smi shows its version). Reinstall after changing it")

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.prop(self, "default_output_dir")
        layout.prop(self, "workers")
        layout.prop(self, "preview_delay_s")
        layout.prop(self, "device")
        draw_compiled(layout.box())
        draw_gpu(self, layout.box())


def status_line() -> tuple[str, str]:
    """(text, icon) of the GPU status: the install in progress, else :meth:`.gpu.Status.line`."""
    installer = _install.installer
    if installer is not None and installer.state == "running" and _install.what == "CuPy":
        return f"Installing CuPy: {installer.progress} (Esc cancels)", 'SORTTIME'
    return gpu.status().line()


def compiled_status_line() -> tuple[str, str]:
    """(text, icon) of the compiled tracer's status: the install in progress, else :func:`.compiled.status_line`
    with the last render's tracer."""
    installer = _install.installer
    if installer is not None and installer.state == "running" and _install.what == "numba":
        return f"Installing numba: {installer.progress} (Esc cancels)", 'SORTTIME'
    return compiled.status_line(compiled.last_tracer())


def _wrapped(layout, text: str, icon: str) -> None:
    for index, part in enumerate(textwrap.wrap(text, STATUS_WIDTH) or [""]):
        layout.label(text=part, icon=icon if index == 0 else 'BLANK1')


def draw_compiled(layout) -> None:
    """The compiled-tracer box: status, the Install button, the folder."""
    layout.label(text="Compiled CPU tracer (numba)", icon='SETTINGS')
    _wrapped(layout, *compiled_status_line())
    layout.operator(TOF_OT_install_numba.bl_idname, icon='IMPORT')
    layout.label(text=f"Installs into {numba_folder()}", icon='FILE_FOLDER')


def draw_gpu(prefs, layout) -> None:
    """The GPU box: status (wrapped over several labels), the kernels' warm-up after an install (warming…, ready in
    N s, failed: why), CUDA choice, Install and Check buttons, folder."""
    layout.label(text="GPU (CuPy)", icon='SETTINGS')
    _wrapped(layout, *status_line())
    if gpu.warmup() is not None:
        _wrapped(layout, *gpu.warmup().line())
    layout.prop(prefs, "cupy_package")
    row = layout.row(align=True)
    row.operator(TOF_OT_install_cupy.bl_idname, icon='IMPORT')
    row.operator(TOF_OT_check_gpu.bl_idname, icon='FILE_REFRESH')
    layout.label(text=f"Installs into {cupy_folder()}", icon='FILE_FOLDER')


_DEFAULTS = SimpleNamespace(default_output_dir=DEFAULT_OUTPUT_DIR, workers=0, preview_delay_s=PREVIEW_DELAY_S,
                            device=DEFAULT_DEVICE, cupy_package=gpu.DEFAULT_PACKAGE)


def get(context=None):
    """The add-on's preferences, or an object with their defaults when the add-on is not enabled."""
    context = context or bpy.context
    addon = context.preferences.addons.get(__package__) if context.preferences else None
    return addon.preferences if addon is not None and addon.preferences is not None else _DEFAULTS


def cupy_folder() -> str:
    """The folder the add-on installs CuPy into (:func:`.gpu.site_packages_dir`)."""
    return gpu.site_packages_dir(__package__)


def numba_folder() -> str:
    """The folder the add-on installs numba into (:func:`.compiled.site_packages_dir`)."""
    return compiled.site_packages_dir(__package__)


# --------------------------------------------------------------------------- Install CuPy, Check GPU

class _InstallState:
    """The one running installation (its :class:`.gpu.Installer`) and what it installs ("CuPy", "numba")."""

    def __init__(self) -> None:
        self.installer: gpu.Installer | None = None
        self.what = ""


_install = _InstallState()


#: Where the Blender guide says how to install each package by hand (tests/test_docs.py checks the sections exist).
_BY_HAND = {"CuPy": "docs/blender.md, GPU in Blender", "numba": "docs/blender.md, The compiled tracer"}


def _online_problem(what: str) -> str | None:
    """Why the add-on may not download ``what`` now (Blender's "Allow Online Access"), or None."""
    if getattr(bpy.app, "online_access", True):
        return None
    if getattr(bpy.app, "online_access_override", False):
        return ("Blender runs offline (started with --offline-mode): start it without that option, "
                f"or install {what} by hand ({_BY_HAND[what]})")
    return ("Online access is off: allow it in Preferences > System > Network > Allow Online Access, "
            f"or install {what} by hand ({_BY_HAND[what]})")


def _blender_pip(what: str, platform_problem: str | None) -> tuple[str, list[str] | None, str | None]:
    """(Blender's Python, how to run pip there, why ``what`` cannot be installed or None)."""
    problem = platform_problem or _online_problem(what)
    python = sys.executable
    if problem is None and (not python or os.path.basename(python).lower().startswith("blender")):
        problem = f"Blender's Python executable was not found (sys.executable = {python!r})"
    pip = None
    if problem is None:
        try:
            pip = gpu.pip_command(python)
        except gpu.InstallError as err:
            problem = f"{err}; install {what} by hand ({_BY_HAND[what]})"
    return python, pip, problem


def prepare_install(package: str, report) -> gpu.Installer | None:
    """The :class:`.gpu.Installer` of ``package`` with Blender's Python, or None after ``report``-ing why not."""
    python, pip, problem = _blender_pip("CuPy", gpu.platform_problem())
    if problem is None:
        try:
            gpu.cuda_line(package)
        except gpu.InstallError as err:
            problem = str(err)
    if problem is not None:
        report({'ERROR'}, f"Cannot install CuPy: {problem}")
        return None
    target = cupy_folder()
    staging = target + ".partial"
    return gpu.Installer(gpu.cupy_install_command(python, staging, package, pip=pip), staging, target)


def finish_install(installer: gpu.Installer, report) -> set[str]:
    """Report how the installation ended; after success, put the folder on ``sys.path`` and check the GPU."""
    if installer.state == "cancelled":
        report({'WARNING'}, installer.message)
        return {'CANCELLED'}
    if installer.state != "done":
        report({'ERROR'}, f"Installing CuPy failed: {installer.message}")
        return {'CANCELLED'}
    gpu.add_to_sys_path(installer.target)
    if "cupy" in sys.modules:  # this Blender session already runs the CuPy it had before
        gpu.status(refresh=True)
        report({'WARNING'}, f"{installer.message}; restart Blender to use it")
        return {'FINISHED'}
    result = gpu.check(installer.target)
    if result.device:
        gpu.start_warmup(installer.target)
        watch_warmup()
        report({'INFO'}, f"{installer.message}; GPU ready: {result.device}; warming up its kernels in the "
                         f"background (compiled once)")
    else:
        report({'WARNING'}, f"{installer.message}, but the GPU cannot run: {result.problem}")
    return {'FINISHED'}


def prepare_numba_install(report) -> gpu.Installer | None:
    """The :class:`.gpu.Installer` of numba and llvmlite with Blender's Python, or None after ``report``-ing
    why not."""
    python, pip, problem = _blender_pip("numba", None)
    if problem is not None:
        report({'ERROR'}, f"Cannot install numba: {problem}")
        return None
    target = numba_folder()
    staging = target + ".partial"
    return gpu.Installer(compiled.numba_install_command(python, staging, pip=pip), staging, target, what="numba")


def finish_numba_install(installer: gpu.Installer, report) -> set[str]:
    """Report how the installation ended; after success, put the folder on ``sys.path`` and start compiling
    the tracer in a background process (:func:`.compiled.start_compiling`), so the first render need not."""
    if installer.state == "cancelled":
        report({'WARNING'}, installer.message)
        return {'CANCELLED'}
    if installer.state != "done":
        report({'ERROR'}, f"Installing numba failed: {installer.message}")
        return {'CANCELLED'}
    gpu.add_to_sys_path(installer.target)
    if "numba" in sys.modules:  # this Blender session already runs the numba it had before
        report({'WARNING'}, f"{installer.message}; restart Blender to use it")
    elif compiled.start_compiling():
        watch_warmup()
        report({'INFO'}, f"{installer.message}; compiling the tracer in the background now (30 s to 3 min, once)")
    else:
        report({'INFO'}, f"{installer.message}; the next render compiles the tracer once (30 s to 3 min)")
    return {'FINISHED'}


#: How often the preferences are redrawn while a warm-up runs in the background, seconds.
WARMUP_REDRAW_S = 1.0


def _warming() -> bool:
    """Whether a background warm-up (the GPU's, or the CPU tracer's compile) runs now."""
    warmup = gpu.warmup()
    return (warmup is not None and warmup.state == "running") or compiled.compiling()


def _redraw_while_warming():
    """A ``bpy.app.timers`` function: redraw the preferences (the warm-up's seconds) until the warm-up ends."""
    _redraw_preferences(bpy.context)
    return WARMUP_REDRAW_S if _warming() else None


def watch_warmup() -> None:
    """Keep the preferences' warm-up line current while it runs (a timer; none fire in background mode, where
    nothing is drawn)."""
    if not bpy.app.background and not bpy.app.timers.is_registered(_redraw_while_warming):
        bpy.app.timers.register(_redraw_while_warming, first_interval=WARMUP_REDRAW_S)


class _InstallOperator:
    """An install with pip: in the calling thread in background mode, else in a worker thread with its
    progress in the status bar (Esc cancels). Subclasses name ``what``, ``download`` and implement
    ``prepare(context)`` → :class:`.gpu.Installer` or None and ``finish(installer)`` → the operator's result."""

    what = ""
    download = ""

    @classmethod
    def install_problem(cls) -> str | None:
        if _install.installer is not None and _install.installer.state == "running":
            return f"{_install.what} is being installed (Esc cancels)"
        return None

    @classmethod
    def poll(cls, context):
        problem = cls.install_problem()
        if problem:
            cls.poll_message_set(problem)
            return False
        return True

    def _start(self, context) -> gpu.Installer | None:
        installer = self.prepare(context)
        _install.installer, _install.what = installer, self.what
        return installer

    # Background mode and scripts: pip runs in this thread.
    def execute(self, context):
        installer = self._start(context)
        if installer is None:
            return {'CANCELLED'}
        installer.run()
        return self.finish(installer)

    # The UI: pip in a worker thread, a modal timer shows its progress in the status bar.
    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        installer = self._start(context)
        if installer is None:
            return {'CANCELLED'}
        wm = context.window_manager
        self._installer = installer
        self._timer = wm.event_timer_add(POLL_INTERVAL_S, window=context.window)
        self._started = time.monotonic()
        wm.modal_handler_add(self)
        installer.start()
        self.report({'INFO'}, f"{self.bl_label}: this downloads {self.download} (Esc cancels)")
        return {'RUNNING_MODAL'}

    def modal(self, context, event):
        installer = self._installer
        if event.type == 'ESC' and event.value == 'PRESS':
            installer.cancel()
            return {'RUNNING_MODAL'}
        if event.type != 'TIMER':
            return {'PASS_THROUGH'}
        if installer.state == "running":
            _status_text(context, f"Installing {self.what} ({time.monotonic() - self._started:.0f} s): "
                                  f"{installer.progress} (Esc cancels)")
            _redraw_preferences(context)
            return {'PASS_THROUGH'}
        installer.join()
        self._cleanup(context)
        return self.finish(installer)

    def _cleanup(self, context) -> None:
        context.window_manager.event_timer_remove(self._timer)
        _status_text(context, None)
        _redraw_preferences(context)

    def cancel(self, context):
        """Blender ends the modal (quit, file load): stop pip; nothing is replaced."""
        self._installer.cancel()
        self._cleanup(context)


class TOF_OT_install_cupy(_InstallOperator, Operator):
    """Download CuPy (the CUDA choice above) and the NVIDIA CUDA libraries it loads, about 1 GB, with pip \
into this add-on's own folder; Blender's NumPy and Python stay as they are. Needs online access"""

    bl_idname = "tof.install_cupy"
    bl_label = "Install CuPy for GPU rendering"
    what = "CuPy"
    download = "about 1 GB"

    @classmethod
    def install_problem(cls) -> str | None:
        return gpu.platform_problem() or super().install_problem()

    def prepare(self, context) -> gpu.Installer | None:
        return prepare_install(get(context).cupy_package, self.report)

    def finish(self, installer: gpu.Installer) -> set[str]:
        return finish_install(installer, self.report)


class TOF_OT_install_numba(_InstallOperator, Operator):
    """Download numba and llvmlite (about 65 MB) with pip into this add-on's own folder, for the compiled \
CPU tracer (about 2× faster per core than NumPy, the same frame); Blender's NumPy and Python stay as they \
are. Needs online access"""

    bl_idname = "tof.install_numba"
    bl_label = "Install numba for the compiled tracer"
    what = "numba"
    download = "about 65 MB"

    def prepare(self, context) -> gpu.Installer | None:
        return prepare_numba_install(self.report)

    def finish(self, installer: gpu.Installer) -> set[str]:
        return finish_numba_install(installer, self.report)


class TOF_OT_check_gpu(Operator):
    """Load CuPy and run a small kernel on the GPU: shows which GPU renders, or why none can. \
Takes a few seconds the first time"""

    bl_idname = "tof.check_gpu"
    bl_label = "Check GPU"

    @classmethod
    def poll(cls, context):
        problem = gpu.platform_problem()
        if problem:
            cls.poll_message_set(problem)
            return False
        return True

    def execute(self, context):
        result = gpu.check(cupy_folder())
        _redraw_preferences(context)
        if result.device:
            self.report({'INFO'}, f"GPU ready: {result.device}")
            return {'FINISHED'}
        text, _icon = result.line()
        self.report({'WARNING'}, text)
        return {'FINISHED'}


def _status_text(context, text: str | None) -> None:
    workspace = getattr(context, "workspace", None)
    if workspace is not None:
        workspace.status_text_set(text)


def _redraw_preferences(context) -> None:
    wm = context.window_manager if context else None
    for window in (wm.windows if wm else ()):
        for area in window.screen.areas:
            if area.type == 'PREFERENCES':
                area.tag_redraw()


classes = (TofPreferences, TOF_OT_install_cupy, TOF_OT_install_numba, TOF_OT_check_gpu)


def register() -> None:
    """CuPy and numba installed by the add-on become importable (``sys.path``); nothing is created or imported."""
    gpu.add_to_sys_path(cupy_folder())
    gpu.add_to_sys_path(numba_folder())


def unregister() -> None:
    if _install.installer is not None and _install.installer.state == "running":
        _install.installer.cancel()
    if bpy.app.timers.is_registered(_redraw_while_warming):
        bpy.app.timers.unregister(_redraw_while_warming)
    gpu.remove_from_sys_path(cupy_folder())
    gpu.remove_from_sys_path(numba_folder())
