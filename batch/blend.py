"""The Blender side of the batch generator: open a .blend, list its cameras, export a view.

Only processes that may import ``bpy`` use this module: the worker processes
(:mod:`batch.worker`), the inspection child process (``python -m batch.blend
inspect FILE.blend``, which prints one JSON line) and the in-Blender entry
(:mod:`batch.blender_entry`). The batch parent process never imports it: a
process that imported bpy must not start workers (it hangs on fork, and its
spawned children cannot import ``_bpy``).

The scene export is the add-on's (``addon.export.export_scene``): geometry,
materials, the camera's ``world_from_sensor`` and the world's ambient light
are read exactly as the add-on's Render button reads them.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import bpy  # noqa: F401  (the one guarded import: this module is bpy-only)

_REPO_ROOT = Path(__file__).resolve().parents[1]


def _ensure_repo_on_path() -> None:
    """``addon`` is imported from the repository next to ``batch``."""
    if str(_REPO_ROOT) not in sys.path:
        sys.path.insert(0, str(_REPO_ROOT))


def tof_properties_available() -> bool:
    """Whether ``camera.tof`` (the add-on's settings) is readable; registers the add-on's property groups if not.

    The add-on does not need to be enabled in the file: registering its two
    property groups is enough to read the settings stored in the .blend.
    """
    if "tof" in bpy.types.Camera.bl_rna.properties:
        return True
    _ensure_repo_on_path()
    try:
        from addon import properties
        for cls in properties.classes:
            if not getattr(cls, "is_registered", False):
                bpy.utils.register_class(cls)
        properties.register()
    except Exception:  # no add-on in this checkout, or an incompatible one: all cameras are used
        return False
    return "tof" in bpy.types.Camera.bl_rna.properties


def open_file(path: str) -> None:
    """Open ``path`` unless it is the file already open (the in-Blender entry renders the open file)."""
    current = bpy.data.filepath
    if current and os.path.exists(current) and os.path.samefile(current, path):
        return
    # Never run code from a scene file: no registered text blocks, no Python drivers (auto-run off too,
    # in case the process's preferences had it on).
    bpy.context.preferences.filepaths.use_scripts_auto_execute = False
    result = bpy.ops.wm.open_mainfile(filepath=str(path), load_ui=False, use_scripts=False)
    if "FINISHED" not in result:
        raise RuntimeError(f"{path}: Blender could not open the file ({result})")


def camera_names() -> tuple[list[str], list[str], bool]:
    """(all camera objects, those with ToF settings enabled, whether ToF settings were readable), sorted."""
    addon = tof_properties_available()
    cameras = sorted(obj.name for obj in bpy.data.objects if obj.type == "CAMERA")
    tof = []
    if addon:
        tof = [name for name in cameras if getattr(getattr(bpy.data.objects[name].data, "tof", None), "enabled",
                                                  False)]
    return cameras, tof, addon


def inspect(path: str) -> dict:
    """Cameras and frame range of ``path`` as a JSON-ready dict (see :class:`batch.jobs.BlendInfo`)."""
    open_file(path)
    cameras, tof, addon = camera_names()
    scene = bpy.context.scene
    return {"cameras": cameras, "tof_cameras": tof, "addon": addon, "frame_current": scene.frame_current,
            "frame_start": scene.frame_start, "frame_end": scene.frame_end}


def export_view(path: str, *, camera: str | None, frame: int | None):
    """Open ``path``, go to ``frame``, export the evaluated scene as seen from ``camera`` (None: the scene's
    active camera, if it has one).

    Returns
    -------
    (scene, world_from_sensor, ambient, warnings) : a ``tofcore.Scene``, the camera's 4×4 pose
    (None without a camera), a ``tofcore.Ambient`` or None, and the exporter's warnings.
    """
    open_file(path)
    _ensure_repo_on_path()
    from addon.export import export_scene

    scene = bpy.context.scene
    if frame is not None:
        scene.frame_set(int(frame))
    camera_obj = scene.camera
    if camera is not None:
        camera_obj = bpy.data.objects.get(camera)
        if camera_obj is None or camera_obj.type != "CAMERA":
            cameras = sorted(o.name for o in bpy.data.objects if o.type == "CAMERA")
            raise ValueError(f"{path}: camera must be one of {cameras}, got {camera!r}")
    depsgraph = bpy.context.evaluated_depsgraph_get()
    result = export_scene(depsgraph, camera_obj=camera_obj)
    return result.scene, result.world_from_sensor, result.ambient, list(result.warnings or [])


def export_to_file(path: str, camera: str | None, frame: int | None, out: str) -> None:
    """:func:`export_view`, pickled to ``out`` (atomically): for callers that must not use bpy themselves.

    bpy may only be used from a process's main thread; a Dask worker runs tasks
    on other threads, so it exports through ``python -m batch.blend export``.
    """
    import pickle

    from .dataset import write_bytes_atomic

    result = export_view(path, camera=camera, frame=frame)
    write_bytes_atomic(Path(out), pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL))


USAGE = ("usage: python -m batch.blend inspect FILE.blend\n"
         "       python -m batch.blend export FILE.blend --out RESULT.pickle [--camera NAME] [--frame N]")


def main(argv: list[str] | None = None) -> int:
    """``inspect`` prints the file's cameras and frames as one JSON line; ``export`` pickles a view's export."""
    import argparse

    args = sys.argv[1:] if argv is None else argv
    if len(args) == 2 and args[0] == "inspect":
        print(json.dumps(inspect(args[1])))
        sys.stdout.flush()
        return 0
    if args and args[0] == "export":
        parser = argparse.ArgumentParser(prog="python -m batch.blend export")
        parser.add_argument("file")
        parser.add_argument("--out", required=True)
        parser.add_argument("--camera", default=None)
        parser.add_argument("--frame", type=int, default=None)
        ns = parser.parse_args(args[1:])
        export_to_file(ns.file, ns.camera, ns.frame, ns.out)
        return 0
    print(USAGE, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
