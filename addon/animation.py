"""Render ToF Animation: every frame of the scene's frame range, one ToF frame each.

For each frame of ``frame_start … frame_end`` (step ``frame_step``) the scene is set to
that frame (``scene.frame_set``: animated cameras, objects and materials follow), the scene
is exported and rendered as by Render ToF (:func:`.operators.prepare_render`), and the frame
is written to the Output Folder with ``#`` replaced by the frame number (``//tof/####/`` →
``//tof/0001/``; a folder without ``#`` gets a ``NNNN`` sub-folder, so frames never overwrite
each other). The UI runs one :class:`.operators.RenderJob` at a time in a worker thread,
polled by a modal timer: the images update after every pass, the status bar shows the frame
and the pass, Esc cancels the running frame (frames already written stay, nothing of the
cancelled one is written) and the scene returns to the frame it was on. Background mode
(``-b``) renders the frames in the calling thread.
"""

from __future__ import annotations

import bpy
from bpy.types import Operator

import tofcore

from . import operators


def frame_numbers(scene) -> list[int]:
    """The scene's frame range: ``frame_start`` to ``frame_end`` inclusive, every ``frame_step``."""
    return list(range(scene.frame_start, scene.frame_end + 1, max(1, scene.frame_step)))


class TOF_OT_render_animation(Operator):
    """Render ToF for every frame of the scene's frame range into numbered output folders (#### = frame). \
Esc cancels"""

    bl_idname = "tof.render_animation"
    bl_label = "Render ToF Animation"
    bl_options = {'REGISTER'}

    @classmethod
    def poll(cls, context):
        _, problem = operators.render_target(context)
        if problem:
            cls.poll_message_set(problem)
            return False
        return True

    def _next_job(self, context) -> operators.RenderJob | None:
        """Set the scene to the next frame and prepare its job (None after an ERROR report)."""
        frame = self._frames[self._index]
        context.scene.frame_set(frame)
        job = operators.prepare_render(context, self.report, numbered=True)
        if job is not None:
            operators.claim_render(job)
            operators._begin_result(job)
            operators.last_result["frame"] = frame
        return job

    def _begin(self, context) -> bool:
        if operators.active_render_job() is not None:
            self.report({'ERROR'}, "A ToF render is already running (Esc cancels it)")
            return False
        operators.stop_live_preview()
        self._frames = frame_numbers(context.scene)
        self._index, self._written, self._start_frame = 0, [], context.scene.frame_current
        if not self._frames:
            self.report({'ERROR'}, f"Scene {context.scene.name!r}: the frame range "
                                   f"{context.scene.frame_start}-{context.scene.frame_end} is empty")
            return False
        return True

    def _status(self) -> str:
        return (f"ToF animation: frame {self._frames[self._index]} ({self._index + 1}/{len(self._frames)}), "
                f"{operators.progress_text()}")

    def _end(self, context, state: str):
        """Back to the starting frame; the summary report; the operator's return set."""
        operators.claim_render(None)
        context.scene.frame_set(self._start_frame)
        done = len(self._written)
        where = f" in {self._written[0]} …" if self._written else ""
        if state == "done":
            operators.last_result.update(state="done", files=done, out_dir=self._written[-1] if done else "")
            self.report({'INFO'}, f"ToF animation: {done} frames written{where}")
            return {'FINISHED'}
        operators.last_result["state"] = state
        if state == "cancelled":
            self.report({'WARNING'}, f"ToF animation cancelled at frame {self._frames[self._index]}: "
                                     f"{done} frames written{where}")
        return {'CANCELLED'}

    # Background mode and scripts: every frame in this thread.
    def execute(self, context):
        if not self._begin(context):
            return {'CANCELLED'}
        wm = context.window_manager
        wm.progress_begin(0, len(self._frames))
        try:
            for self._index in range(len(self._frames)):
                job = self._next_job(context)
                if job is None:
                    return self._end(context, "error")
                try:
                    job.run(operators._apply_pass)
                except tofcore.Cancelled:
                    return self._end(context, "cancelled")
                except (tofcore.TofError, OSError, ValueError) as err:
                    self.report({'ERROR'}, f"ToF render of frame {self._frames[self._index]} failed: {err}")
                    return self._end(context, "error")
                self._written.append(job.out_dir)
                wm.progress_update(self._index + 1)
        finally:
            wm.progress_end()
        return self._end(context, "done")

    # The UI: one worker thread per frame, a modal timer.
    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        if not self._begin(context):
            return {'CANCELLED'}
        self._job = self._next_job(context)
        if self._job is None:
            return self._end(context, "error")
        wm = context.window_manager
        self._timer = wm.event_timer_add(operators.POLL_INTERVAL_S, window=context.window)
        wm.modal_handler_add(self)
        wm.progress_begin(0, len(self._frames))
        operators._set_status(context, self._status() + " (Esc to cancel)")
        self._job.start()
        return {'RUNNING_MODAL'}

    def modal(self, context, event):
        job = self._job
        if event.type == 'ESC' and event.value == 'PRESS':
            job.cancel()
            operators._set_status(context, "ToF animation: cancelling…")
            return {'RUNNING_MODAL'}
        if event.type != 'TIMER':
            return {'PASS_THROUGH'}
        newest, end = job.poll()
        if newest is not None and not job.cancelled:
            operators._apply_pass(newest)
            operators._show_in_image_editors(context)
            operators._set_status(context, self._status() + " (Esc to cancel)")
            operators._redraw(context)
        if end is None:
            return {'PASS_THROUGH'}
        kind, payload = end
        if kind != "done":
            if kind == "error":
                self.report({'ERROR'}, f"ToF render of frame {self._frames[self._index]} failed: {payload}")
            return self._finish(context, "cancelled" if kind == "cancelled" else "error")
        self._written.append(job.out_dir)
        operators.device_report(payload[0], self.report)
        operators.coverage_report(payload[0], self.report)
        context.window_manager.progress_update(len(self._written))
        if self._index + 1 == len(self._frames):
            return self._finish(context, "done")
        self._index += 1
        self._job = self._next_job(context)
        if self._job is None:
            return self._finish(context, "error")
        self._job.start()
        return {'PASS_THROUGH'}

    def _finish(self, context, state: str):
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        operators._set_status(context, None)
        result = self._end(context, state)
        operators._redraw(context)
        return result

    def cancel(self, context):
        """Blender ends the modal (file load, quit): stop the worker."""
        self._job.cancel()
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        operators.claim_render(None)


classes = (TOF_OT_render_animation,)
