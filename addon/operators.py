"""Operators: Add ToF Camera, Apply Sensor to Camera, Render ToF, and the live preview.

Render ToF
----------
``invoke`` (the UI) exports the evaluated scene (:func:`.export.export_scene`),
builds the sensor (:func:`.sensors.sensor_from_settings`) and starts a
:class:`RenderJob` in a worker thread that touches no ``bpy``: it runs
:func:`tofcore.render_progressive` and posts every pass to a queue. A modal
timer drains the queue, shows each pass in the images of :mod:`.images`
(:func:`_apply_pass`), the progress in the status bar and the progress
cursor, and the estimated depth error and elapsed time in the ToF panel. Esc
sets the job's cancel flag: tofcore raises :class:`tofcore.Cancelled` between
ray chunks, nothing is written, the images keep the last pass. The final frame
is written by :func:`tofcore.write_frame` (atomic files) to the output folder
(``####`` in it = the frame number, :func:`frame_path`);
its ``convergence.png`` is then loaded as the image "ToF Convergence"
(:func:`.images.load_convergence_image`).

``execute`` (background mode ``-b``, where timers never fire and
``INVOKE_DEFAULT`` calls ``execute``) runs the same job in the calling thread,
calling :func:`_apply_pass` after every pass.

Device
------
Both the render and the live preview run on the preferences' ``device``
(``cpu``, ``gpu`` or ``auto``, passed to :func:`tofcore.render_progressive`).
Before a ``gpu``/``auto`` job, :func:`.gpu.activate` makes the CuPy the add-on
installed importable (its CUDA libraries loaded); ``gpu`` without any CuPy
stops at once with the way to install it. The device that rendered
(``frame.stats["device"]["description"]``) is in the summary, the panel, the
status bar and the images' ``tof_device`` property; an ``auto`` render that fell
back to the CPU ends with a WARNING naming why. A GPU that fails
(:class:`tofcore.backend.GpuUnavailable`: no device, driver too old, out of
memory) is an ERROR with tofcore's one-line reason.

Live preview
------------
While a camera's ``live_preview`` is on, a ``depsgraph_update_post`` handler
and the settings' update callbacks call :func:`schedule_live_preview`: a
debounced ``bpy.app.timers`` callback (``preview_delay_s`` of the preferences,
0.5 s by default) starts a low-resolution job (``preview_scale`` ×
resolution, ``preview_spp``, the depth denoised with ``preview_denoise``:
:mod:`tofcore.sensor.denoise`), cancelling the previous one; a second timer
drains its queue into the same images. Nothing is written.

Every failure the user can cause is reported: no active camera, a camera
without ToF sensor, nothing visible to render, invalid overrides, an unusable
GPU (ERROR); skipped objects, missing textures, a GPU fallback (WARNING).
"""

from __future__ import annotations

import os
import queue
import re
import tempfile
import threading
import time

import bpy
from bpy.app.handlers import persistent
from bpy.props import BoolProperty, EnumProperty
from bpy.types import Operator
from bpy_extras.object_utils import AddObjectHelper, object_data_add
from mathutils import Matrix

import tofcore

from . import compiled, export, gpu, images, mapping, preferences, sensors

#: Custom property that marks an LED empty; its value is the LED number (1-based).
LED_KEY = "tof_led"
#: Radius of the LED empties (spheres), metres.
LED_EMPTY_SIZE_M = 0.004
#: Camera gizmo size of a new ToF camera, metres (small, so the LED offsets are visible beside it).
CAMERA_DISPLAY_SIZE_M = 0.1
#: How often the modal operator and the preview poll their worker, seconds.
POLL_INTERVAL_S = 0.1

#: The most recent pass shown in the images, for the panel: camera, kind ("render"/"preview"), state,
#: spp, spp_max, est_depth_error_m, seconds, files, out_dir, message, limits.
last_result: dict = {}


# --------------------------------------------------------------------------- the job (no bpy)

class RenderJob:
    """One ToF render with everything it needs and nothing of ``bpy``, so it can run in a worker thread.

    Parameters
    ----------
    scene, sensor, pose, ambient : :func:`tofcore.render_progressive` inputs (``pose`` = world_from_sensor).
    settings : ``spp``, ``max_depth``, ``seed``, ``time_budget_s``, ``target_error_m``.
    workers : tracer threads (None: all CPUs).
    out_dir : folder of the final frame; None writes nothing (previews).
    formats : :func:`tofcore.write_frame` formats.
    camera : name of the Blender camera (for the UI).
    kind : ``"render"`` or ``"preview"``.
    device : tofcore's ``device``: ``"cpu"``, ``"gpu"`` or ``"auto"``.
    exported : the scene export the job renders (the live preview reuses it after a camera move).
    """

    def __init__(self, *, scene, sensor, pose, ambient=None, settings: dict, workers: int | None = None,
                 out_dir: str | None = None, formats: tuple[str, ...] = (), camera: str = "",
                 kind: str = "render", device: str = "cpu", exported=None) -> None:
        self.scene, self.sensor, self.pose, self.ambient = scene, sensor, pose, ambient
        self.exported = exported
        self.settings = dict(settings)
        self.workers = workers
        self.device = device
        self.out_dir = out_dir
        self.formats = tuple(formats)
        self.camera = camera
        self.kind = kind
        self.messages: queue.Queue = queue.Queue()
        self.thread: threading.Thread | None = None
        self._cancel = threading.Event()

    def cancel(self) -> None:
        """Ask the render to stop; tofcore raises Cancelled between ray chunks (within about a second)."""
        self._cancel.set()

    @property
    def cancelled(self) -> bool:
        return self._cancel.is_set()

    def run(self, on_pass) -> tuple:
        """Render in the calling thread, ``on_pass(frame)`` after every pass; write the final frame.

        The frames before the final one are preview frames (``preview_frames=True``): the images show no
        per-path-length distances, and skipping their K decodes saves ≈ 10 % of the render.

        Returns (final frame, ``{kind: path}`` written). Raises :class:`tofcore.Cancelled` when cancelled,
        also after the last pass: then nothing is written.
        """
        frame = None
        for frame in tofcore.render_progressive(self.scene, self.sensor, self.pose, ambient=self.ambient,
                                                cancel=self._cancel.is_set, workers=self.workers,
                                                device=self.device, preview_frames=True, **self.settings):
            on_pass(frame)
        if self.cancelled:
            raise tofcore.Cancelled("render cancelled after its last pass; nothing written")
        written = tofcore.write_frame(frame, self.out_dir, self.formats) if self.out_dir and self.formats else {}
        return frame, written

    def start(self) -> None:
        """Run in a daemon thread posting ``("pass", frame)`` per pass, then one of ``("done", (frame,
        written))``, ``("cancelled", None)``, ``("error", message)``."""
        def work() -> None:
            try:
                result = self.run(lambda frame: self.messages.put(("pass", frame)))
                self.messages.put(("done", result))
            except tofcore.Cancelled:
                self.messages.put(("cancelled", None))
            except Exception as err:  # reported in the UI; the thread must not die silently
                self.messages.put(("error", error_text(err)))

        self.thread = threading.Thread(target=work, name=f"tof-{self.kind}-{self.camera}", daemon=True)
        self.thread.start()

    def poll(self) -> tuple:
        """Drain the queue: (the newest pass or None, the end message ``(kind, payload)`` or None)."""
        newest, end = None, None
        while True:
            try:
                kind, payload = self.messages.get_nowait()
            except queue.Empty:
                return newest, end
            if kind == "pass":
                newest = payload
            else:
                end = (kind, payload)

    def join(self, timeout: float | None = None) -> None:
        if self.thread is not None:
            self.thread.join(timeout)


def error_text(err: BaseException) -> str:
    """One line for a failed job: tofcore's own errors as they are (they name their cause), others with
    their type."""
    if isinstance(err, tofcore.TofError):
        return str(err)
    return f"{type(err).__name__}: {err}"


# --------------------------------------------------------------------------- scene → job

def render_target(context) -> tuple:
    """(camera object, None) when the scene camera has a ToF sensor, else (None, the reason)."""
    scene = context.scene
    obj = scene.camera if scene is not None else None
    if obj is None:
        return None, ("No active camera: set the scene camera (Scene properties) or add one with "
                      "Add > ToF Camera")
    if obj.type != 'CAMERA' or not hasattr(obj.data, "tof"):
        return None, (f"Camera {obj.name!r} has no ToF settings: the scene camera is not a camera "
                      f"(object type {obj.type}); add one with Add > ToF Camera")
    if not obj.data.tof.enabled:
        return None, (f"Camera {obj.name!r} has no ToF settings: enable 'ToF Sensor' in its camera properties "
                      f"or add one with Add > ToF Camera")
    return obj, None


def output_folder(path: str, frame: int | None = None, *, numbered: bool = False) -> str:
    """Absolute output folder; ``//`` of an unsaved .blend goes to the system temporary folder.

    With ``frame``, every run of ``#`` becomes the frame number zero-padded to its length (Blender's
    convention: ``//tof/####/`` → ``//tof/0007/``); ``numbered`` (animations) adds a ``NNNN`` folder
    when the path has no ``#``, so no frame overwrites another.
    """
    if frame is not None:
        path = frame_path(path, frame, numbered=numbered)
    if path.startswith("//") and not bpy.data.filepath:
        return os.path.join(unsaved_folder(), path[2:])
    return os.path.normpath(bpy.path.abspath(path))


def unsaved_folder() -> str:
    """Where ``//`` points while the .blend file is unsaved."""
    return os.path.join(tempfile.gettempdir(), "tof-unsaved")


def frame_path(path: str, frame: int, *, numbered: bool = False) -> str:
    """``path`` with each run of ``#`` replaced by ``frame``, zero-padded to the run's length (a negative
    frame keeps its sign); without ``#`` and with ``numbered``, ``path/NNNN``."""
    if "#" not in path:
        return os.path.join(path, f"{frame:04d}") if numbered else path
    return re.sub(r"#+", lambda m: f"{frame:0{len(m.group())}d}", path)


def prepare_render(context, report, *, preview: bool = False, numbered: bool = False,
                   exported: "export.ExportResult | None" = None) -> RenderJob | None:
    """Export the scene and build the :class:`RenderJob` of the scene camera, or report why not.

    Parameters
    ----------
    context : a Blender context (scene, evaluated depsgraph).
    report : ``report(levels, message)`` like ``Operator.report``: ERROR for every reason to stop
        (then None is returned), WARNING for what the exporter skipped.
    preview : the live-preview job (``preview_scale``, ``preview_spp``, nothing written).
    numbered : an animation frame: the output folder gets the frame number even without ``#``.
    exported : an export of the scene as it still is (the live preview after a camera move): its
        triangles, materials and ambient light are used, only the camera's pose is read anew.
    """
    camera_obj, problem = render_target(context)
    if problem:
        report({'ERROR'}, problem)
        return None
    device = prepare_device(preferences.get(context).device, report)
    if device is None:
        return None
    settings = camera_obj.data.tof
    try:
        sensor = sensors.sensor_from_settings(settings, scale=settings.preview_scale if preview else 1.0)
    except tofcore.ConfigError as err:
        report({'ERROR'}, f"Camera {camera_obj.name!r}: {err}")
        return None
    quality = sensors.render_settings(settings)
    out_dir, formats = None, ()
    if preview:
        quality.update(spp=int(settings.preview_spp), time_budget_s=None, target_error_m=None,
                       preview_denoise=bool(settings.preview_denoise))
    else:
        out_dir = (output_folder(settings.output_dir, context.scene.frame_current, numbered=numbered)
                   if settings.output_dir.strip() else None)
        formats = tuple(f for f in sensors.FORMATS if f in settings.formats)
        if out_dir is None and formats:
            report({'ERROR'}, f"Camera {camera_obj.name!r}: output_dir (Output Folder) is empty; choose a folder")
            return None
    try:  # resource limits (tofcore.limits) before the scene is exported or anything allocated
        tofcore.limits.check_render(sensor, max_depth=quality["max_depth"], spp=quality["spp"],
                                    where=f"Camera {camera_obj.name!r}")
    except tofcore.ConfigError as err:
        report({'ERROR'}, str(err))
        return None
    if exported is not None:
        result = exported
        pose = export.camera_pose(camera_obj, context.evaluated_depsgraph_get())
    else:
        try:
            result = export.export_scene(context.evaluated_depsgraph_get(), camera_obj)
        except tofcore.SceneError as err:  # "nothing visible to render: …"
            report({'ERROR'}, f"Cannot render: {err}")
            return None
        except tofcore.TofError as err:  # e.g. a material override tofcore rejects
            report({'ERROR'}, f"Scene export failed: {err}")
            return None
        pose = result.world_from_sensor
    for warning in result.warnings:
        report({'WARNING'}, warning)
    if pose is None:
        pose = tofcore.from_blender_matrix_world(camera_obj.matrix_world)
    return RenderJob(scene=result.scene, sensor=sensor, pose=pose, ambient=result.ambient, settings=quality,
                     workers=preferences.get(context).workers or None, out_dir=out_dir, formats=formats,
                     camera=camera_obj.name, kind="preview" if preview else "render", device=device,
                     exported=result)


def prepare_device(device: str, report) -> str | None:
    """The preferences' ``device`` ready to render with, or None after an ERROR ``report``.

    ``gpu``/``auto``: the add-on's CuPy folder goes on ``sys.path`` and its CUDA libraries are loaded
    (:func:`.gpu.activate`; CuPy itself is imported by tofcore in the worker). ``gpu`` without any CuPy
    stops here, naming the Blender way to install it (tofcore's own message suggests ``pip``).
    """
    if device not in ("cpu", "gpu", "auto"):
        report({'ERROR'}, f"Preferences: device must be one of ['cpu', 'gpu', 'auto'], got {device!r}")
        return None
    if device == "cpu":
        return device
    gpu.activate(preferences.cupy_folder())
    if device == "gpu" and not gpu.installed_cupy():
        problem = gpu.platform_problem()
        report({'ERROR'}, f"Device GPU: {problem}" if problem else
               "Device GPU needs CuPy in Blender's Python: Preferences > Add-ons > ToF Camera Simulator > "
               "Install CuPy for GPU rendering (or set Device to CPU or Auto)")
        return None
    return device


# --------------------------------------------------------------------------- showing passes

def _apply_pass(frame) -> None:
    """Show one progressive pass: update the four ToF images and the panel's numbers."""
    limits = images.update_images(frame)
    row = frame.stats.get("convergence", [{}])[-1]
    last_result.update(spp=int(frame.stats.get("spp", row.get("spp", 0))),
                       spp_max=int(frame.stats.get("spp_max", 0)),
                       est_depth_error_m=row.get("est_depth_error_m"),
                       seconds=float(frame.stats.get("seconds", row.get("seconds", 0.0))),
                       final=bool(frame.stats.get("final")), limits=limits,
                       resolution=(frame.width, frame.height))
    device = frame.stats.get("device") or {}
    last_result.update(device=device.get("description", ""), device_name=device.get("name", ""),
                       fallback_reason=device.get("fallback_reason"))
    transport = frame.stats.get("transport") or {}
    last_result["transport"] = {key: transport.get(key) for key in ("tracer", "tracer_reason", "parallel")}


def device_report(frame, report) -> None:
    """After a job: the status learns which device rendered; an ``auto`` render that fell back to the CPU
    is a WARNING naming why."""
    device = frame.stats.get("device") or {}
    gpu.note_device(device)
    compiled.note_tracer(frame.stats.get("transport"))
    if device.get("fallback_reason"):
        report({'WARNING'}, gpu.fallback_warning(device["fallback_reason"]))
    parallel = (frame.stats.get("transport") or {}).get("parallel", "")
    if parallel.startswith("threads: "):  # worker processes could not start here (tofcore.tracer.workers)
        report({'WARNING'}, f"ToF render ran on CPU threads, not worker processes: {parallel[len('threads: '):]}")


def _begin_result(job: RenderJob) -> None:
    last_result.clear()
    last_result.update(camera=job.camera, kind=job.kind, state="running", spp=0, spp_max=job.settings["spp"],
                       est_depth_error_m=None, seconds=0.0, started=time.perf_counter())


def progress_text(result: dict | None = None) -> str:
    """One line for the status bar and the panel: samples, estimated error, time."""
    result = last_result if result is None else result
    error = result.get("est_depth_error_m")
    error_text = "–" if error is None else f"{error * 1000:.2f} mm"
    return (f"{result.get('spp', 0)}/{result.get('spp_max', 0)} spp, est. depth error {error_text}, "
            f"{result.get('seconds', 0.0):.1f} s")


def progress_fraction(job: RenderJob) -> float:
    """Render progress in [0, 1]: samples done, or time used of the budget, whichever is further."""
    fraction = last_result.get("spp", 0) / max(1, job.settings["spp"])
    budget = job.settings.get("time_budget_s")
    if budget:
        fraction = max(fraction, last_result.get("seconds", 0.0) / budget)
    return min(1.0, fraction)


def _show_convergence(frame, written: dict) -> None:
    """The final frame's written ``convergence.png`` (formats with ``png``) as the image "ToF Convergence"."""
    path = written.get("convergence")
    if path is None:
        last_result.pop("convergence_image", None)
        return
    device = (frame.stats.get("device") or {}).get("description", "")
    last_result["convergence_image"] = images.load_convergence_image(path, device).name


def _summary(frame, written: dict, job: RenderJob) -> str:
    error = frame.stats["convergence"][-1].get("est_depth_error_m")
    error_text = "–" if error is None else f"{error * 1000:.2f} mm"
    where = f"{len(written)} files written to {job.out_dir}" if written else "no files written (no formats)"
    device = (frame.stats.get("device") or {}).get("description")
    on = f" on {device}" if device else ""
    tracer = compiled.tracer_text(frame.stats.get("transport"))
    return (f"ToF render of {job.camera!r}: {where}; {frame.stats['spp']} spp, "
            f"est. depth error {error_text}, {frame.stats['seconds']:.1f} s{on}" + (f"; {tracer}" if tracer else ""))


def _redraw(context) -> None:
    """Redraw the ToF panel and image editors (nothing to do without a screen, e.g. in background mode)."""
    wm = context.window_manager if context else None
    for window in (wm.windows if wm else ()):
        for area in window.screen.areas:
            if area.type in {'PROPERTIES', 'IMAGE_EDITOR'}:
                area.tag_redraw()


def _show_in_image_editors(context) -> None:
    """Image editors that show nothing start showing "ToF Depth"."""
    image = bpy.data.images.get(images.IMAGE_NAMES["depth"])
    wm = context.window_manager
    if image is None or wm is None:
        return
    for window in wm.windows:
        for area in window.screen.areas:
            if area.type == 'IMAGE_EDITOR' and area.spaces.active.image is None:
                area.spaces.active.image = image


def _set_status(context, text: str | None) -> None:
    workspace = getattr(context, "workspace", None)
    if workspace is not None:
        workspace.status_text_set(text)


# --------------------------------------------------------------------------- Render ToF

#: The running full render (one at a time); the live preview pauses meanwhile.
_render_job: RenderJob | None = None


def active_render_job() -> RenderJob | None:
    return _render_job


def claim_render(job: RenderJob | None) -> None:
    """Make ``job`` the running full render (None: no render runs); the live preview pauses meanwhile."""
    global _render_job
    _render_job = job


class TOF_OT_render(Operator):
    """Render the scene camera's ToF sensor: depth, IR, amplitude and error images update after every pass; \
the final frame is written to the output folder. Esc cancels"""

    bl_idname = "tof.render"
    bl_label = "Render ToF"
    bl_options = {'REGISTER'}

    @classmethod
    def poll(cls, context):
        _, problem = render_target(context)
        if problem:
            cls.poll_message_set(problem)
            return False
        return True

    def _start(self, context) -> RenderJob | None:
        global _render_job
        if _render_job is not None:
            self.report({'ERROR'}, f"A ToF render of {_render_job.camera!r} is already running (Esc cancels it)")
            return None
        stop_live_preview()
        job = prepare_render(context, self.report)
        if job is not None:
            _render_job = job
            _begin_result(job)
        return job

    @staticmethod
    def _end() -> None:
        global _render_job
        _render_job = None

    # Background mode and scripts: the same loop in this thread.
    def execute(self, context):
        job = self._start(context)
        if job is None:
            return {'CANCELLED'}
        wm = context.window_manager
        wm.progress_begin(0, 100)

        def on_pass(frame) -> None:
            _apply_pass(frame)
            wm.progress_update(int(100 * progress_fraction(job)))

        try:
            frame, written = job.run(on_pass)
        except tofcore.Cancelled:
            last_result["state"] = "cancelled"
            self.report({'WARNING'}, "ToF render cancelled: nothing written, the images keep the last pass")
            return {'CANCELLED'}
        except (tofcore.TofError, OSError, ImportError, ValueError) as err:
            last_result.update(state="error", message=str(err))
            self.report({'ERROR'}, f"ToF render failed: {err}")
            return {'CANCELLED'}
        finally:
            wm.progress_end()
            self._end()
        last_result.update(state="done", files=len(written), out_dir=job.out_dir or "")
        _show_convergence(frame, written)
        device_report(frame, self.report)
        self.report({'INFO'}, _summary(frame, written, job))
        return {'FINISHED'}

    # The UI: a worker thread and a modal timer.
    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        job = self._start(context)
        if job is None:
            return {'CANCELLED'}
        self._job = job
        wm = context.window_manager
        self._timer = wm.event_timer_add(POLL_INTERVAL_S, window=context.window)
        wm.modal_handler_add(self)
        wm.progress_begin(0, 100)
        _set_status(context, compiled.first_status(job.camera, job.device))
        job.start()
        return {'RUNNING_MODAL'}

    def modal(self, context, event):
        job = self._job
        if event.type == 'ESC' and event.value == 'PRESS':
            if not job.cancelled:
                job.cancel()
                _set_status(context, "ToF render: cancelling…")
            return {'RUNNING_MODAL'}
        if event.type != 'TIMER':  # any window timer: polling an empty queue costs nothing
            return {'PASS_THROUGH'}
        newest, end = job.poll()
        if newest is not None:
            _apply_pass(newest)
            _show_in_image_editors(context)
            context.window_manager.progress_update(int(100 * progress_fraction(job)))
            if not job.cancelled:
                on = f" on {last_result['device']}" if last_result.get("device") else ""
                _set_status(context, f"ToF render of {job.camera!r}{on}: {progress_text()} (Esc to cancel)")
            _redraw(context)
        if end is None:
            return {'PASS_THROUGH'}
        return self._finish(context, *end)

    def _finish(self, context, kind: str, payload):
        self._cleanup(context)
        if kind == "done":
            frame, written = payload
            last_result.update(state="done", files=len(written), out_dir=self._job.out_dir or "")
            _show_convergence(frame, written)
            device_report(frame, self.report)
            self.report({'INFO'}, _summary(frame, written, self._job))
            return {'FINISHED'}
        if kind == "cancelled":
            last_result["state"] = "cancelled"
            self.report({'WARNING'}, "ToF render cancelled: nothing written, the images keep the last pass")
        else:
            last_result.update(state="error", message=payload)
            self.report({'ERROR'}, f"ToF render failed: {payload}")
        return {'CANCELLED'}

    def _cleanup(self, context) -> None:
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        _set_status(context, None)
        self._end()
        _redraw(context)

    def cancel(self, context):
        """Blender ends the modal (file load, quit): stop the worker, write nothing."""
        self._job.cancel()
        last_result["state"] = "cancelled"
        self._cleanup(context)


# --------------------------------------------------------------------------- cameras and LEDs

def cameras_using(camera_data) -> list:
    """Objects whose data is ``camera_data``."""
    return [obj for obj in bpy.data.objects if obj.type == 'CAMERA' and obj.data == camera_data]


def led_empties(obj) -> list:
    """The LED empties of a ToF camera object, in LED order."""
    return sorted((child for child in obj.children if LED_KEY in child), key=lambda child: child[LED_KEY])


def sync_led_empties(obj, leds) -> list:
    """One small sphere empty per LED, child of ``obj`` at the LED's position.

    LED positions are in the OpenCV sensor frame (x right, y down, z forward); the
    Blender camera's local frame looks down −Z with +Y up, so the local position is
    diag(1, −1, −1) · position. Extra empties are removed; an empty list removes all.
    """
    existing = led_empties(obj)
    result = []
    for index, led in enumerate(leds, start=1):
        if index <= len(existing):
            empty = existing[index - 1]
        else:
            empty = bpy.data.objects.new(f"LED {index}", None)
            for collection in obj.users_collection:
                collection.objects.link(empty)
            empty[LED_KEY] = index
        if empty.parent != obj:
            empty.parent = obj
        empty.matrix_parent_inverse = Matrix.Identity(4)
        x, y, z = led.position_m
        empty.location = (x, -y, -z)
        empty.rotation_euler = (0.0, 0.0, 0.0)
        empty.scale = (1.0, 1.0, 1.0)
        empty.empty_display_type = 'SPHERE'
        empty.empty_display_size = LED_EMPTY_SIZE_M
        empty.show_in_front = True
        empty.hide_render = True
        empty.lock_location = empty.lock_rotation = empty.lock_scale = (True, True, True)
        result.append(empty)
    for extra in existing[len(leds):]:
        bpy.data.objects.remove(extra)
    return result


def apply_sensor_to_camera(obj, sensor, scene=None) -> None:
    """Blender intrinsics (lens, sensor, shift) and LED empties of ``sensor`` on camera ``obj``;
    with ``scene``, also its render resolution and pixel aspect (at 100 %). Distortion has no Blender
    counterpart and is left out."""
    cam = sensor.camera
    values = mapping.blender_camera_from_intrinsics(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    data = obj.data
    data.type = 'PERSP'
    data.lens_unit = 'MILLIMETERS'
    data.sensor_fit = values["sensor_fit"]
    data.sensor_width = values["sensor_width_mm"]
    data.sensor_height = values["sensor_height_mm"]
    data.lens = values["lens_mm"]
    data.shift_x, data.shift_y = values["shift_x"], values["shift_y"]
    if scene is not None:
        render = scene.render
        render.resolution_x, render.resolution_y = values["resolution_x"], values["resolution_y"]
        render.resolution_percentage = 100
        render.pixel_aspect_x, render.pixel_aspect_y = values["pixel_aspect_x"], values["pixel_aspect_y"]
    sync_led_empties(obj, sensor.leds)


def apply_settings_to_cameras(camera_data, scene=None) -> None:
    """After a sensor setting changed: update every object using ``camera_data`` (and the render
    resolution of ``scene`` when its scene camera is one of them). A disabled sensor loses its LED
    empties; an invalid setting changes nothing (Render ToF reports it)."""
    objects = cameras_using(camera_data)
    if not camera_data.tof.enabled:
        for obj in objects:
            sync_led_empties(obj, ())
        return
    try:
        sensor = sensors.sensor_from_settings(camera_data.tof)
    except tofcore.ConfigError:
        return
    for obj in objects:
        apply_sensor_to_camera(obj, sensor, scene if scene is not None and scene.camera == obj else None)


def _camera_preset_items():
    return [item for item in sensors.PRESET_ITEMS if item[0] != sensors.CUSTOM]


class TOF_OT_add_camera(Operator, AddObjectHelper):
    """Add a camera with a ToF sensor: the preset's intrinsics, its LEDs as small sphere empties, \
and make it the scene camera"""

    bl_idname = "tof.add_camera"
    bl_label = "Add ToF Camera"
    bl_options = {'REGISTER', 'UNDO'}

    preset: EnumProperty(name="Preset", items=_camera_preset_items(), default=sensors.DEFAULT_PRESET,
                         description="Sensor preset of the new camera")
    make_active: BoolProperty(name="Set as Scene Camera", default=True,
                              description="Make the new camera the scene camera (Render ToF renders that one)")

    @classmethod
    def poll(cls, context):
        return context.scene is not None and context.mode == 'OBJECT'

    def execute(self, context):
        data = bpy.data.cameras.new("ToF Camera")
        data.display_size = CAMERA_DISPLAY_SIZE_M
        data.tof.output_dir = preferences.get().default_output_dir
        data.tof.preset = self.preset
        obj = object_data_add(context, data, operator=self, name="ToF Camera")
        if self.make_active:
            context.scene.camera = obj
        data.tof.enabled = True  # update callback: intrinsics, LEDs, render resolution of the scene camera
        try:
            sensor = sensors.sensor_from_settings(data.tof)
        except tofcore.ConfigError as err:
            self.report({'ERROR'}, str(err))
            return {'CANCELLED'}
        apply_sensor_to_camera(obj, sensor, context.scene if self.make_active else None)
        return {'FINISHED'}


class TOF_OT_apply_sensor(Operator):
    """Set this camera's lens, sensor, shift, the render resolution and the LED empties from its ToF sensor \
settings"""

    bl_idname = "tof.apply_sensor"
    bl_label = "Apply Sensor to Camera"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        obj = context.object
        if obj is None or obj.type != 'CAMERA' or not obj.data.tof.enabled:
            cls.poll_message_set("The active object must be a camera with a ToF sensor")
            return False
        return True

    def execute(self, context):
        obj = context.object
        try:
            sensor = sensors.sensor_from_settings(obj.data.tof)
        except tofcore.ConfigError as err:
            self.report({'ERROR'}, f"Camera {obj.name!r}: {err}")
            return {'CANCELLED'}
        apply_sensor_to_camera(obj, sensor, context.scene)
        return {'FINISHED'}


class TOF_OT_cancel_render(Operator):
    """Stop the running ToF render or live preview; nothing is written"""

    bl_idname = "tof.cancel_render"
    bl_label = "Cancel ToF Render"

    @classmethod
    def poll(cls, context):
        return _render_job is not None or _preview.job is not None

    def execute(self, context):
        if _render_job is not None:
            _render_job.cancel()
        stop_live_preview()
        return {'FINISHED'}


# --------------------------------------------------------------------------- live preview

class _PreviewState:
    """The live preview's one running job and the debounce deadline (``time.monotonic``)."""

    def __init__(self) -> None:
        self.job: RenderJob | None = None
        self.deadline = 0.0
        self.camera = ""      # the camera object of the last preview started
        self.messages: list[tuple[str, str]] = []
        # The last preview's scene export, reused while only the preview camera (its pose, its ToF
        # settings) changed: a camera move then exports nothing and the BVH is the one built before.
        self.exported = None
        self.scene_changed = True


_preview = _PreviewState()


def active_preview_job() -> RenderJob | None:
    return _preview.job


def live_preview_camera(scene):
    """The scene camera if its live preview is on, else None."""
    obj = scene.camera if scene is not None else None
    if obj is None or obj.type != 'CAMERA' or not hasattr(obj.data, "tof"):
        return None
    settings = obj.data.tof
    return obj if settings.enabled and settings.live_preview else None


def _scene_changed(depsgraph, camera_obj) -> bool:
    """Whether an update touched anything the export reads: anything but the preview camera object, its
    camera data (pose, lens, ToF settings), its LED empties (they move with it) and the IDs tagged along
    with every change."""
    camera_ids = {camera_obj.name_full, camera_obj.data.name_full}
    for update in depsgraph.updates:
        data = getattr(update.id, "original", update.id)
        if isinstance(data, (bpy.types.Object, bpy.types.Camera)) and data.name_full in camera_ids:
            continue
        if isinstance(data, bpy.types.Object) and LED_KEY in data and data.parent == camera_obj.original:
            continue
        if isinstance(data, (bpy.types.Scene, bpy.types.WorkSpace, bpy.types.Screen, bpy.types.WindowManager)):
            continue
        if isinstance(data, bpy.types.Image) and (data.name in images.IMAGE_NAMES.values()
                                                  or data.name == images.CONVERGENCE_IMAGE):
            continue
        return True
    return False


def _relevant(depsgraph) -> bool:
    """Whether an update can change the ToF image: anything but our own result images."""
    for update in depsgraph.updates:
        data = update.id
        if isinstance(data, bpy.types.Image) and (data.name in images.IMAGE_NAMES.values()
                                                  or data.name == images.CONVERGENCE_IMAGE):
            continue
        if isinstance(data, (bpy.types.Scene, bpy.types.WorkSpace, bpy.types.Screen, bpy.types.WindowManager)):
            continue  # tagged along with everything; the objects themselves come as their own updates
        return True
    return False


@persistent
def _on_depsgraph_update(scene, depsgraph) -> None:
    """``depsgraph_update_post``: restart the preview (debounced) when the scene or the scene camera changed."""
    obj = live_preview_camera(scene) if _render_job is None else None
    if obj is None:
        _preview.scene_changed = True  # a render or another camera: export afresh next time
        return
    if _scene_changed(depsgraph, obj):
        _preview.scene_changed = True
    if obj.name != _preview.camera or _relevant(depsgraph):
        schedule_live_preview()


def schedule_live_preview(delay_s: float | None = None) -> None:
    """Start a preview after ``delay_s`` (default: the preferences' delay) without further changes."""
    delay_s = preferences.get().preview_delay_s if delay_s is None else delay_s
    _preview.deadline = time.monotonic() + delay_s
    if not bpy.app.timers.is_registered(_preview_timer):
        bpy.app.timers.register(_preview_timer, first_interval=max(delay_s, 0.0))


def _preview_timer():
    remaining = _preview.deadline - time.monotonic()
    if remaining > 1e-3:
        return remaining
    start_live_preview(bpy.context)
    return None


def start_live_preview(context) -> RenderJob | None:
    """Cancel the running preview and start one for the scene camera (None if there is none to start)."""
    stop_live_preview(keep_schedule=True)
    obj = live_preview_camera(context.scene)
    if _render_job is not None or obj is None:
        return None
    reuse = _preview.exported if (obj.name == _preview.camera and not _preview.scene_changed) else None
    _preview.camera = obj.name
    _preview.messages = []
    job = prepare_render(context, lambda levels, message: _preview.messages.append((min(levels), message)),
                         preview=True, exported=reuse)
    _preview.exported, _preview.scene_changed = (job.exported, False) if job is not None else (None, True)
    if job is None:
        last_result.update(kind="preview", state="error", message=_preview.messages[-1][1])
        _redraw(context)
        return None
    _preview.job = job
    _begin_result(job)
    job.start()
    if not bpy.app.timers.is_registered(_preview_poll):
        bpy.app.timers.register(_preview_poll, first_interval=POLL_INTERVAL_S)
    return job


def poll_live_preview(context=None) -> bool:
    """Show the preview's newest pass; True while it is still running."""
    job = _preview.job
    if job is None:
        return False
    newest, end = job.poll()
    if newest is not None and not job.cancelled:
        _apply_pass(newest)
    if end is not None:
        kind, payload = end
        last_result["state"] = {"done": "done", "cancelled": "cancelled"}.get(kind, "error")
        if kind == "error":
            last_result["message"] = payload
        elif kind == "done":
            device_report(payload[0], lambda levels, message: _preview.messages.append((min(levels), message)))
        _preview.job = None
    _redraw(context or bpy.context)
    return _preview.job is not None


def _preview_poll():
    return POLL_INTERVAL_S if poll_live_preview() else None


def stop_live_preview(*, keep_schedule: bool = False) -> None:
    """Cancel the running preview (its thread ends within about a second) and, unless ``keep_schedule``,
    a scheduled one."""
    if _preview.job is not None:
        _preview.job.cancel()
        _preview.job = None
    for timer in ((_preview_poll,) if keep_schedule else (_preview_poll, _preview_timer)):
        if bpy.app.timers.is_registered(timer):
            bpy.app.timers.unregister(timer)


def settings_changed(camera_data) -> None:
    """A sensor, quality or material setting changed: restart the preview if it is on for it."""
    if _render_job is not None:
        return
    scene = bpy.context.scene
    obj = live_preview_camera(scene)
    if camera_data is None:  # a material setting: the export changes
        _preview.scene_changed = True
    if obj is not None and (camera_data is None or obj.data == camera_data):
        schedule_live_preview()


def _handler_registered(handlers, function) -> bool:
    return any(getattr(h, "__name__", None) == function.__name__ and
               getattr(h, "__module__", None) == function.__module__ for h in handlers)


def _remove_handler(handlers, function) -> None:
    """Remove ``function`` (also an older copy of it from before a reload of the add-on)."""
    for handler in list(handlers):
        if handler is function or (getattr(handler, "__name__", None) == function.__name__ and
                                   getattr(handler, "__module__", None) == function.__module__):
            handlers.remove(handler)


def preview_handler_registered() -> bool:
    return _handler_registered(bpy.app.handlers.depsgraph_update_post, _on_depsgraph_update)


def sync_preview_handler() -> None:
    """Install the depsgraph handler while any ToF camera has its live preview on, remove it otherwise."""
    try:
        wanted = any(cam.tof.enabled and cam.tof.live_preview for cam in bpy.data.cameras)
    except AttributeError:  # bpy.data is restricted while add-ons register at start-up; load_post follows
        return
    handlers = bpy.app.handlers.depsgraph_update_post
    if wanted and not preview_handler_registered():
        handlers.append(_on_depsgraph_update)
    elif not wanted:
        _remove_handler(handlers, _on_depsgraph_update)


def live_preview_toggled(camera_data, on: bool) -> None:
    """``live_preview`` was switched (from :func:`.updates.live_preview_toggled`)."""
    sync_preview_handler()
    if on:
        if live_preview_camera(bpy.context.scene) is not None:
            schedule_live_preview(0.0)
    else:
        stop_live_preview()


@persistent
def _on_load_post(*_args) -> None:
    """A file was loaded: previews of the old file end, the new file's toggles decide about the handler."""
    stop_live_preview()
    sync_preview_handler()


# --------------------------------------------------------------------------- registration

classes = (TOF_OT_add_camera, TOF_OT_apply_sensor, TOF_OT_render, TOF_OT_cancel_render)


def register() -> None:
    """Handlers (the classes are registered by the package first)."""
    if not _handler_registered(bpy.app.handlers.load_post, _on_load_post):
        bpy.app.handlers.load_post.append(_on_load_post)
    sync_preview_handler()


def unregister() -> None:
    """Stop the workers (without waiting: they hold no bpy data) and remove handlers and timers."""
    global _render_job
    stop_live_preview()
    if _render_job is not None:
        _render_job.cancel()
        _render_job = None
    _remove_handler(bpy.app.handlers.depsgraph_update_post, _on_depsgraph_update)
    _remove_handler(bpy.app.handlers.load_post, _on_load_post)
