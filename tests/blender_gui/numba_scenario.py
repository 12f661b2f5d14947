"""The compiled tracer (numba) in a real Blender, one step per Blender process (run by numba_run.py).

    blender -b --python numba_scenario.py -- install|install-nopip|render LABEL

Runs in Blender's own Python with the extension zip installed (``bl_ext.user_default.tof_camera``) and writes
``$TOF_GUI_OUT/<step>.json``:

* ``install``: the add-on's own "Install numba for the compiled tracer" operator (``tof.install_numba``,
  ``execute`` in background mode: pip in this thread), then what the numba folder holds and the box's status.
* ``install-nopip``: the same operator where Blender's Python has no pip (Debian's Blender): its error.
* ``cancel-cold``: on an empty kernel cache, the Render ToF job cancelled 3 s into the compile, then a second
  job: how fast the cancel took effect, whether the compile went on in its child process, and the second
  job's frame (``stats["transport"]["compile"]``).
* ``render LABEL``: the default cube and World (constant ambient light) seen by a ToF camera (as
  scenario.py's step 1), the add-on's Render ToF operator; records the operator's wall time,
  ``frame.stats["transport"]``, the add-on's tracer text and status line, numba's threading layer and where
  the kernels' machine code is cached (with its files), and saves the frame's float64 depth as
  ``depth-LABEL.npy`` for numba_run.py to compare tracers. A LABEL starting with ``textured`` renders
  scenario.py's step 2 scene instead: the checker Image Texture on Base Color and Roughness of every mesh
  and the World's Environment Texture (an HDRI sky), both generated and packed (:func:`textured_scene`,
  the same images as scenario.py's); then the record also holds what the export made of them
  (``export``: textures per material, the ambient map's shape, warnings) and ``frame.stats["plan"]``.
"""

import importlib
import json
import os
import sys
import time

import bpy
import mathutils
import numpy as np

OUT = os.environ["TOF_GUI_OUT"]
ADDON = "bl_ext.user_default.tof_camera"


def addon(name: str):
    return importlib.import_module(f"{ADDON}.{name}")


def cache_files(folder: str) -> dict:
    """``{path relative to folder: (size, mtime)}`` of every file in numba's cache folder (numba keeps them in
    a subfolder per source folder); empty if there is none."""
    found = {}
    for parent, _, names in os.walk(folder or "/nonexistent"):
        for name in names:
            path = os.path.join(parent, name)
            found[os.path.relpath(path, folder)] = (os.path.getsize(path), os.path.getmtime(path))
    return dict(sorted(found.items()))


def install_nopip() -> dict:
    try:
        result, error = sorted(bpy.ops.tof.install_numba()), ""
    except RuntimeError as err:   # bpy.ops raises the ERROR report of an operator called from Python
        result, error = ["ERROR"], str(err)
    return {"operator": result, "error": error, "python": sys.executable}


def install() -> dict:
    prefs = addon("preferences")
    started = time.perf_counter()
    result = bpy.ops.tof.install_numba()
    seconds = time.perf_counter() - started
    folder = prefs.numba_folder()
    installer = prefs._install.installer
    return {"operator": sorted(result), "seconds": round(seconds, 1), "folder": folder,
            "contents": sorted(os.listdir(folder)) if os.path.isdir(folder) else [],
            "installer_state": installer.state if installer else None,
            "installer_message": installer.message if installer else None,
            "pip_tail": installer.lines[-8:] if installer else [],
            "on_sys_path": folder in sys.path, "status_line": list(prefs.compiled_status_line()),
            "python": sys.executable, "online_access": bpy.app.online_access}


#: scenario.py's step 2 images (keep the two in step): a checker on the default cube, a sky with a sun.
CHECKER_PX, CHECKER_CELLS, CHECKER_SRGB = 64, 4, (0.9, 0.35)
SKY_W, SKY_H, SKY_GROUND = 64, 32, 0.01


def textured_scene() -> None:
    """scenario.py's :func:`textured_scene` (that file runs its GUI scenario when imported): a checker Image
    Texture on the Base Color and Roughness of a material given to every mesh, a World whose Background colour
    is an Environment Texture; both images generated and packed."""
    n, cell = CHECKER_PX, CHECKER_PX // (4 * CHECKER_CELLS)
    rows, cols = np.indices((n, n)) // cell
    rgba = np.ones((n, n, 4), np.float32)
    rgba[..., :3] = np.where((rows + cols) % 2 == 0, *CHECKER_SRGB)[..., None]
    checker = bpy.data.images.new("GUI Checker", n, n)
    checker.pixels.foreach_set(rgba.ravel())
    checker.pack()
    material = bpy.data.materials.new("GUI Checker")
    material.use_nodes = True
    tree = material.node_tree
    bsdf = next(node for node in tree.nodes if node.type == 'BSDF_PRINCIPLED')
    texture = tree.nodes.new("ShaderNodeTexImage")
    texture.image = checker
    tree.links.new(texture.outputs["Color"], bsdf.inputs["Base Color"])
    tree.links.new(texture.outputs["Color"], bsdf.inputs["Roughness"])
    elevation = ((np.arange(SKY_H) + 0.5) / SKY_H - 0.5) * np.pi    # rows bottom-up: row 0 = nadir
    sky = np.ones((SKY_H, SKY_W, 4), np.float32)
    sky[..., :3] = np.where(elevation > 0, 0.02 + 0.08 * np.sin(elevation), SKY_GROUND)[:, None, None]
    sky[24:27, 8:12, :3] = 2.0
    hdri = bpy.data.images.new("GUI Sky", SKY_W, SKY_H, float_buffer=True)
    hdri.pixels.foreach_set(sky.ravel())
    hdri.pack()
    world = bpy.data.worlds.new("GUI HDRI")
    world.use_nodes = True
    nodes = world.node_tree.nodes
    environment = nodes.new("ShaderNodeTexEnvironment")
    environment.image = hdri
    background = next(node for node in nodes if node.type == 'BACKGROUND')
    world.node_tree.links.new(environment.outputs["Color"], background.inputs["Color"])
    for mesh in {obj.data for obj in bpy.context.scene.objects if obj.type == 'MESH'}:
        mesh.materials.clear()
        mesh.materials.append(material)
    bpy.context.scene.world = world


def export_record() -> dict:
    """What the add-on's export makes of the scene: textures per material, the ambient light, warnings."""
    result = addon("export").export_scene(bpy.context.evaluated_depsgraph_get(), bpy.context.scene.camera)
    ambient = result.ambient
    environment = ambient.environment if ambient is not None else None
    return {"textures": {m.name: {k: list(t.data.shape) for k, t in m.textures.items()}
                         for m in result.scene.materials},
            "environment": list(environment.data.shape) if environment is not None else None,
            "ambient_constant": ambient.radiance_w_m2_sr if ambient is not None else None,
            "warnings": result.warnings}


def add_tof_camera(label: str) -> None:
    """A ToF camera looking at the default cube, 128 × 106, 8 spp, 3 vertices, writing into OUT/tof-LABEL."""
    bpy.ops.tof.add_camera()
    camera = bpy.context.active_object
    camera.location = (2.6, -2.6, 2.0)
    camera.rotation_euler = (mathutils.Vector((0, 0, 0)) - camera.location).to_track_quat('-Z', 'Y').to_euler()
    tof = camera.data.tof
    tof.use_resolution, tof.width, tof.height, tof.spp, tof.max_depth = True, 128, 106, 8, 3
    tof.output_dir = os.path.join(OUT, f"tof-{label}", "")


def render(label: str) -> dict:
    ops, compiled, prefs = addon("operators"), addon("compiled"), addon("preferences")
    context = bpy.context
    frames = []
    job_run = ops.RenderJob.run

    def keep_frame(self, on_pass):   # the final frame, as the operator got it
        frame, written = job_run(self, on_pass)
        frames.append(frame)
        return frame, written

    ops.RenderJob.run = keep_frame
    if label.startswith("textured"):
        textured_scene()
    add_tof_camera(label)
    status_before = list(prefs.compiled_status_line())
    started = time.perf_counter()
    result = bpy.ops.tof.render()
    seconds = time.perf_counter() - started
    frame = frames[-1]
    np.save(os.path.join(OUT, f"depth-{label}.npy"), np.asarray(frame.depth, dtype=np.float64))
    transport = frame.stats.get("transport") or {}
    record = {"operator": sorted(result), "seconds": round(seconds, 2), "state": ops.last_result.get("state"),
              "transport": {k: transport.get(k) for k in ("tracer", "tracer_reason", "parallel", "compile")},
              "tracer_text": compiled.tracer_text(transport), "status_before": status_before,
              "status_after": list(prefs.compiled_status_line()), "numba_folder": prefs.numba_folder(),
              "sys_path_has_numba_folder": prefs.numba_folder() in sys.path}
    if label.startswith("textured"):
        record.update(export=export_record(), plan=frame.stats.get("plan"))
    if "numba" in sys.modules:
        import numba

        import tofcore.compiled
        folder = tofcore.compiled.cache_location()
        try:
            layer = numba.threading_layer()
        except ValueError as err:   # no parallel function has run in this process
            layer = f"none ({err})"
        record.update(numba=numba.__version__, numba_file=numba.__file__, threading_layer=layer,
                      cache_folder=folder, cache_files=cache_files(folder), tofcore_file=tofcore.compiled.__file__)
    return record


def cancel_cold() -> dict:
    """The Render ToF job (the modal operator's worker thread) on an empty kernel cache, cancelled 3 s in
    (what Esc does: ``job.cancel()``), then a second job that waits for the same background compile."""
    import tofcore.compiled
    from tofcore.compiled import child_compile

    ops = addon("operators")
    reports = []
    add_tof_camera("cancel")
    record = {"cached_before": tofcore.compiled.cpu_kernels_cached(), "cache_folder": tofcore.compiled.cache_location()}
    first = ops.prepare_render(bpy.context, lambda level, text: reports.append(text))
    first.start()
    time.sleep(3.0)
    first.cancel()
    asked = time.perf_counter()
    first.join(60)
    record.update(cancel_seconds=round(time.perf_counter() - asked, 2), first_end=list(map(str, first.poll()[1] or [])),
                  compiling_after_cancel=child_compile.running())
    second = ops.prepare_render(bpy.context, lambda level, text: reports.append(text))
    started = time.perf_counter()
    second.start()
    second.join(900)
    _, end = second.poll()
    kind, payload = end if end else ("none", None)
    transport = payload[0].stats.get("transport", {}) if kind == "done" else {}
    record.update(second_end=kind, second_seconds=round(time.perf_counter() - started, 1),
                  transport={k: transport.get(k) for k in ("tracer", "tracer_reason", "compile")},
                  cached_after=tofcore.compiled.cpu_kernels_cached(), reports=reports,
                  python=sys.executable)
    return record


def main() -> None:
    args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    step = args[0]
    bpy.ops.preferences.addon_enable(module=ADDON)
    if step == "render":
        record, name = render(args[1]), f"render-{args[1]}"
    elif step == "cancel-cold":
        record, name = cancel_cold(), step
    else:
        record, name = {"install": install, "install-nopip": install_nopip}[step](), step
    with open(os.path.join(OUT, f"{name}.json"), "w") as fh:
        json.dump(record, fh, indent=1)
    print(f"NUMBA-CHECK {name}: {json.dumps(record)[:2000]}", flush=True)


try:
    main()
except Exception:
    import traceback
    traceback.print_exc()
    sys.stdout.flush()
    os._exit(1)
