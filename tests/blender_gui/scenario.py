"""The add-on as an artist uses it, inside a real Blender GUI (run by ``make test-blender``, see run.py).

Runs in Blender's own Python (``blender --python scenario.py``) with the extension zip installed, on a
virtual display. Blender's GUI is event-driven, so the scenario is a generator stepped by a
``bpy.app.timers`` callback: each ``yield`` gives the UI that many seconds to draw and run its modal
operators. Steps, each checked by files, by the add-on's state and by a screenshot whose pixels the step
looks at:

1. ``render``: Add ToF Camera, aim it at the default cube, Render ToF (INVOKE, as a click) → the 14 files
   in ``tof/0001/``, the "ToF Depth" image filled, the depth image colourful on screen, no red error
   icon in the status bar or the Info editor.
2. ``textured``: every mesh gets a material whose Principled BSDF reads an Image Texture (a checker made
   here: ``images.new``, pixels set, packed; no file) on Base Color and Roughness, and the World's
   Background an Environment Texture (an equirectangular sky made here: bright above the horizon, dark
   below); Render ToF (INVOKE) → the 14 files in ``textured/0001/``; the add-on's export holds both
   textures and the environment map with no warning; against step 1's untextured frame, the amplitude
   on the cube follows the checker (dark cells ≈ 0.13×, light ≈ 1×, several changes along a row) and the
   background's intensity follows the map (the ground at 0.2× the default World's grey, brighter towards
   the horizon); ``frame.json`` plans textures and ambient light and names the tracer (NumPy where numba
   is not installed, with the reason; compiled where it is); the ToF Amplitude image on screen, sampled
   at its pixel centres, is that image (the checker visible). The material and World are put back.
3. ``live_preview``: Live Preview on, the camera moved three times → the preview re-renders at preview
   resolution and the image follows the camera; nothing written.
4. ``cancel``: a long render (1024 spp) cancelled with Esc after its first pass → state cancelled within
   seconds, nothing written (no temp files), Blender alive.
5. ``animation``: Render ToF Animation over frames 1-3 with the camera keyed → ``anim/0001 … 0003`` with
   the 14 files each, the scene back on its frame.
6. ``preset``: a custom sensor saved with the Sensor Presets "+" and applied to a second camera.
7. The Info log is saved (``info_log.txt``); run.py checks that Blender printed no "Error:" report before
   step 8.
8. ``error_report``: an empty Preset File → an ERROR naming "Preset File"; a render whose output folder
   cannot be made → "ToF render failed" with the red error icon in the Info editor (which proves that the
   screenshot check of the earlier steps, status bar and Info editor, can see an error report).

Writes ``results.json`` (``[{step, ok, detail}]``) and screenshots ``screen-N.png`` into $TOF_GUI_OUT;
``shots.json`` names the screenshots and the screen rectangles of the image editor and the panels.
"""

import importlib
import json
import os
import subprocess
import time
import traceback

import bpy
import mathutils
import numpy as np

OUT = os.environ["TOF_GUI_OUT"]
ADDON = "bl_ext.user_default.tof_camera"
FILES = {"frame.exr", "depth.exr", "depth_mm.png", "ir.png", "depth.png", "intensity.png", "error.png", "reason.png",
         "convergence.png", "points.ply", "camera.json", "camera_opencv.yml", "camera_info.yaml", "frame.json"}
#: A screenshot pixel is "colourful" when max − min of its RGB (0..1) exceeds this (the turbo map is; the grey
#: UI is not); a depth image shown in the image editor has thousands of them.
COLOURFUL = 0.3
MIN_COLOURFUL_PX = 1500
#: Step 2's images, made in the scenario (packed, no file). The checker: CHECKER_PX² pixels, 8-bit sRGB like a
#: painted texture, CHECKER_CELLS cells a side on each face of the default cube (its UV map gives every face a
#: quarter of the image's side), light and dark cells of sRGB 0.9 and 0.35 (linear 0.79 and 0.10: 0.98× and
#: 0.13× the default material's 0.8). The sky: SKY_W × SKY_H float radiance, equirectangular (Blender's
#: mapping, Z up), 0.02 at the horizon to 0.10 at the zenith, SKY_GROUND below the horizon (0.2× the default
#: World's grey 0.05), a 2.0 "sun" patch.
CHECKER_PX, CHECKER_CELLS, CHECKER_SRGB = 64, 4, (0.9, 0.35)
SKY_W, SKY_H, SKY_GROUND = 64, 32, 0.01

results: list = []
shots: dict = {}
layout: dict = {}


def check(step: str, ok: bool, detail: str) -> None:
    results.append({"step": step, "ok": bool(ok), "detail": detail})
    print(f"GUI-TEST {step}: {'PASS' if ok else 'FAIL'} {detail}", flush=True)


def operators():
    return importlib.import_module(f"{ADDON}.operators")


def files_in(folder: str) -> set:
    return set(os.listdir(folder)) if os.path.isdir(folder) else set()


def screenshot(name: str) -> np.ndarray:
    """Save the screen as screen-N.png (remembered as ``name``) and return its pixels, row 0 at the bottom
    (Blender's area coordinates)."""
    subprocess.run(os.environ["SCREENSHOT_CMD"], shell=True, check=True)
    path = max((os.path.join(OUT, f) for f in os.listdir(OUT) if f.startswith("screen-")), key=os.path.getmtime)
    shots[name] = os.path.basename(path)
    image = bpy.data.images.load(path)
    width, height = image.size
    pixels = np.empty(width * height * 4, np.float32)
    image.pixels.foreach_get(pixels)
    bpy.data.images.remove(image)
    return pixels.reshape(height, width, 4)


def rect(area) -> tuple:
    return (area.x, area.y, area.width, area.height)


def colourful_px(pixels: np.ndarray, box: tuple) -> int:
    x, y, w, h = box
    rgb = pixels[y:y + h, x:x + w, :3]
    return int(((rgb.max(axis=-1) - rgb.min(axis=-1)) > COLOURFUL).sum())


def red_px(rgb: np.ndarray) -> int:
    """Pixels of an ERROR report's red icon (RGB about 180, 80, 55) or banner; grey UI, text and the blue INFO
    icon have none."""
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return int(((r > 0.45) & (r - g > 0.2) & (r - b > 0.2)).sum())


def info_error_px(pixels: np.ndarray) -> int:
    """Red pixels in the Info editor, which keeps every report with its icon (the newest at the bottom)."""
    x, y, w, h = rect(layout["info"])
    return red_px(pixels[y:y + h, x:x + w, :3])


def error_banner_px(pixels: np.ndarray) -> int:
    """Red pixels of an ERROR report on screen: in the status bar (the bottom 22 rows; Blender shows a report
    there for a few seconds) and in the Info editor."""
    return red_px(pixels[:22, :, :3]) + info_error_px(pixels)


def depth_pixels() -> np.ndarray:
    image = bpy.data.images["ToF Depth"]
    pixels = np.empty(len(image.pixels), np.float32)
    image.pixels.foreach_get(pixels)
    return pixels.reshape(image.size[1], image.size[0], 4)


def info_log() -> str:
    """Every report in the Info editor, one a line."""
    area = layout["info"]
    bpy.context.window_manager.clipboard = ""
    with bpy.context.temp_override(area=area, region=next(r for r in area.regions if r.type == 'WINDOW')):
        bpy.ops.info.select_all(action='SELECT')
        bpy.ops.info.report_copy()
    return bpy.context.window_manager.clipboard


def wait_for(condition, timeout_s: float, poll_s: float = 0.25):
    """Yield until ``condition()`` is true or the time is up; the generator's value is whether it came true."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if condition():
            return True
        yield poll_s
    return condition()


def set_up_screen(context) -> None:
    """Left: Image Editor; middle: a tall Properties editor on the camera data; right column: Properties, Info."""
    screen = context.screen
    view3d = next(a for a in screen.areas if a.type == 'VIEW_3D')
    with context.temp_override(area=view3d):
        bpy.ops.screen.area_split(direction='VERTICAL', factor=0.5)
    left, middle = sorted((a for a in screen.areas if a.type == 'VIEW_3D'), key=lambda a: a.x)
    left.type = 'IMAGE_EDITOR'
    middle.type = 'PROPERTIES'
    for area in screen.areas:
        if area.type == 'OUTLINER':
            area.type = 'INFO'
    layout.update(image=left, panels=middle, info=next(a for a in screen.areas if a.type == 'INFO'))


def click(operator: str, area_key: str = "panels", **kwargs):
    """Run ``bpy.ops.tof.<operator>('INVOKE_DEFAULT')`` in the Properties editor, as a click on its button."""
    area = layout[area_key]
    region = next(r for r in area.regions if r.type == 'WINDOW')
    with bpy.context.temp_override(area=area, region=region):
        return getattr(bpy.ops.tof, operator)('INVOKE_DEFAULT', **kwargs)


def scroll_panels(steps: int):
    """Scroll the middle Properties editor down, one step a redraw (a generator: ``yield from``)."""
    area = layout["panels"]
    region = next(r for r in area.regions if r.type == 'WINDOW')
    for _ in range(steps):
        with bpy.context.temp_override(area=area, region=region):
            bpy.ops.view2d.scroll_down(deltax=0, deltay=200)
        yield 0.3
    yield 0.5


def show_depth() -> None:
    image = bpy.data.images.get("ToF Depth")
    if image is not None:
        layout["image"].spaces.active.image = image
        with bpy.context.temp_override(area=layout["image"],
                                       region=next(r for r in layout["image"].regions if r.type == 'WINDOW')):
            bpy.ops.image.view_all(fit_view=True)


def textured_scene() -> tuple:
    """Step 2's scene: a checker Image Texture on the Base Color and Roughness of a new material given to every
    mesh, and a new World whose Background colour is an Environment Texture (a sky); both images generated here
    and packed. Returns what :func:`untextured_scene` puts back: ([(mesh, its materials)], the old World)."""
    n, cell = CHECKER_PX, CHECKER_PX // (4 * CHECKER_CELLS)
    rows, cols = np.indices((n, n)) // cell
    light = (rows + cols) % 2 == 0
    rgba = np.ones((n, n, 4), np.float32)
    rgba[..., :3] = np.where(light, *CHECKER_SRGB)[..., None]
    checker = bpy.data.images.new("GUI Checker", n, n)                # 8-bit, sRGB
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

    v = (np.arange(SKY_H) + 0.5) / SKY_H                          # Blender stores rows bottom-up: row 0 = nadir
    elevation = (v - 0.5) * np.pi
    radiance = np.where(elevation > 0, 0.02 + 0.08 * np.sin(elevation), SKY_GROUND)
    sky = np.ones((SKY_H, SKY_W, 4), np.float32)
    sky[..., :3] = radiance[:, None, None]
    sky[24:27, 8:12, :3] = 2.0                                    # a sun, 48° up, on the camera's side
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

    scene = bpy.context.scene
    meshes = {obj.data for obj in scene.objects if obj.type == 'MESH'}
    kept = [(mesh, list(mesh.materials)) for mesh in meshes]
    for mesh in meshes:
        mesh.materials.clear()
        mesh.materials.append(material)
    old_world, scene.world = scene.world, world
    return kept, old_world


def untextured_scene(kept: tuple) -> None:
    meshes, world = kept
    for mesh, materials in meshes:
        mesh.materials.clear()
        for material in materials:
            mesh.materials.append(material)
    bpy.context.scene.world = world


def read_frame(folder: str) -> dict:
    """The float channels of ``folder/frame.exr`` the textured step compares (tofcore's own EXR reader)."""
    from tofcore.output.writers import read_exr

    return read_exr(os.path.join(folder, "frame.exr"), ["amplitude", "intensity", "gt_depth"])


def checker_in_amplitude(plain: dict, textured: dict) -> tuple:
    """(share of dark cells, share of light cells, mean changes dark↔light along a row) on the cube's pixels:
    the amplitude ratio textured / untextured (same camera, samples and seed) is ~0.13 on dark cells, ~1 on
    light ones."""
    cube = np.isfinite(plain["gt_depth"]) & np.isfinite(textured["gt_depth"]) & (plain["amplitude"] > 0)
    ratio = np.where(cube, textured["amplitude"] / np.where(cube, plain["amplitude"], 1.0), np.nan)
    dark, light = cube & (ratio < 0.4), cube & (ratio > 0.7)
    changes = [np.count_nonzero(np.diff(dark[y][cube[y]].astype(np.int8))) for y in range(cube.shape[0])
               if cube[y].sum() >= 10]
    n = max(int(cube.sum()), 1)
    return dark.sum() / n, light.sum() / n, float(np.mean(changes)) if changes else 0.0


def sky_in_intensity(plain: dict, textured: dict) -> tuple:
    """(median intensity ratio textured / untextured on the background's lower half, mean intensity of the
    background's top 3 rows / its lower half's median, textured): where no surface is hit the sensor sees the
    ambient light itself, the map's ground (SKY_GROUND against the default World's 0.0509) and, at the top of
    the image, just above the horizon."""
    background = ~np.isfinite(plain["gt_depth"]) & ~np.isfinite(textured["gt_depth"])
    lower = background.copy()
    lower[:background.shape[0] // 2] = False
    top = background.copy()
    top[3:] = False
    ground = float(np.median(textured["intensity"][lower]))
    ratio = float(np.median(textured["intensity"][lower] / np.maximum(plain["intensity"][lower], 1e-12)))
    return ratio, float(textured["intensity"][top].mean()) / max(ground, 1e-12)


def image_on_screen(pixels: np.ndarray, name: str) -> tuple:
    """(correlation, rectangle): the screen at the centres of image ``name``'s pixels, placed where the image
    editor draws them (its view: the image spans 0..1), against that image's grey values; r near 1: the image
    is on screen as stored. The rectangle is the image's on the screen (x, y from the bottom, width, height)."""
    image = bpy.data.images[name]
    width, height = image.size
    data = np.empty(width * height * 4, np.float32)
    image.pixels.foreach_get(data)
    grey = data.reshape(height, width, 4)[..., :3].mean(axis=-1)        # row 0 at the bottom, as the screen's
    region = next(r for r in layout["image"].regions if r.type == 'WINDOW')
    (left, bottom), (right, top) = (region.view2d.view_to_region(u, v, clip=False) for u, v in ((0, 0), (1, 1)))
    left, right, bottom, top = left + region.x, right + region.x, bottom + region.y, top + region.y
    box = (int(left), int(bottom), int(right - left), int(top - bottom))
    cx = np.floor(left + (np.arange(width) + 0.5) * (right - left) / width).astype(int)
    cy = np.floor(bottom + (np.arange(height) + 0.5) * (top - bottom) / height).astype(int)
    if min(cx.min(), cy.min()) < 0 or cx.max() >= pixels.shape[1] or cy.max() >= pixels.shape[0]:
        return 0.0, box
    seen = pixels[np.ix_(cy, cx)][..., :3].mean(axis=-1)
    return float(np.corrcoef(seen.ravel(), grey.ravel())[0, 1]), box


def scenario():
    context = bpy.context
    bpy.ops.preferences.addon_enable(module=ADDON)
    set_up_screen(context)
    yield 0.5

    # 1. Render ToF -----------------------------------------------------------------------------------
    bpy.ops.tof.add_camera()
    camera = context.active_object
    camera.location = (2.6, -2.6, 2.0)
    camera.rotation_euler = (mathutils.Vector((0, 0, 0)) - camera.location).to_track_quat('-Z', 'Y').to_euler()
    tof = camera.data.tof
    tof.use_resolution, tof.width, tof.height, tof.spp, tof.max_depth = True, 128, 106, 8, 3
    tof.output_dir = os.path.join(OUT, "tof", "####", "")
    yield 0.5   # the new Properties editor learns its tabs when it has drawn once
    for area in context.screen.areas:
        if area.type == 'PROPERTIES':
            area.spaces.active.context = 'DATA'
    yield 0.5
    returned = click("render")
    check("render", returned == {'RUNNING_MODAL'}, f"Render ToF returned {returned}")
    ops = operators()
    finished = yield from wait_for(lambda: ops.active_render_job() is None, 60)
    folder = os.path.join(OUT, "tof", "0001")
    show_depth()
    yield from scroll_panels(4)
    pixels = screenshot("render")
    written = files_in(folder)
    depth = depth_pixels()
    state = ops.last_result.get("state")
    check("render", finished and state == "done" and written == FILES,
          f"state {state!r}, files in tof/0001: {sorted(written)}")
    check("render", (depth[..., 3] == 1).sum() > 0.05 * depth[..., 3].size,
          f"ToF Depth {depth.shape[1]}x{depth.shape[0]}: {(depth[..., 3] == 1).mean():.0%} of the pixels valid")
    colourful = colourful_px(pixels, rect(layout["image"]))
    check("render", colourful >= MIN_COLOURFUL_PX, f"screenshot: {colourful} colourful pixels in the image editor")
    check("render", error_banner_px(pixels) < 20,
          f"screenshot: {error_banner_px(pixels)} red pixels in the status bar and the Info editor")

    # 2. A textured scene under an HDRI World ---------------------------------------------------------
    kept = textured_scene()
    exported = importlib.import_module(f"{ADDON}.export").export_scene(context.evaluated_depsgraph_get(), camera)
    textures = {m.name: {k: t.data.shape for k, t in m.textures.items()} for m in exported.scene.materials}
    ambient = exported.ambient
    environment = ambient.environment.data if ambient is not None and ambient.environment is not None else None
    check("textured", textures == {"GUI Checker": {"reflectance_texture": (CHECKER_PX, CHECKER_PX),
                                                   "roughness_texture": (CHECKER_PX, CHECKER_PX)}}
          and environment is not None and environment.shape == (SKY_H, SKY_W) and ambient.radiance_w_m2_sr == 0
          and abs(float(environment[-1, 0]) - SKY_GROUND) < 1e-4 and not exported.warnings,
          f"export: textures {textures}; ambient map {None if environment is None else environment.shape}, "
          f"nadir {None if environment is None else float(environment[-1, 0]):.4g}, constant "
          f"{None if ambient is None else ambient.radiance_w_m2_sr}; warnings {exported.warnings}")
    tof.output_dir = os.path.join(OUT, "textured", "####", "")
    returned = click("render")
    finished = yield from wait_for(lambda: ops.active_render_job() is None, 120)
    folder = os.path.join(OUT, "textured", "0001")
    written, state = files_in(folder), ops.last_result.get("state")
    check("textured", returned == {'RUNNING_MODAL'} and finished and state == "done" and written == FILES,
          f"Render ToF returned {returned}, state {state!r}, files in textured/0001: {len(written)}")
    stats = json.load(open(os.path.join(folder, "frame.json")))["stats"] if "frame.json" in written else {}
    plan, transport = stats.get("plan", {}), stats.get("transport", {})
    tracer, reason = transport.get("tracer"), transport.get("tracer_reason") or ""
    check("textured", plan.get("textures") is True and plan.get("ambient") is True
          and ((tracer == "compiled" and not reason) or (tracer == "numpy" and reason.startswith("numba is not"))),
          f"frame.json: plan textures {plan.get('textures')}, ambient {plan.get('ambient')}; tracer {tracer!r} "
          f"({reason!r}), {transport.get('parallel')!r}; add-on: "
          f"{importlib.import_module(f'{ADDON}.compiled').tracer_text(transport)!r}")
    plain, textured = read_frame(os.path.join(OUT, "tof", "0001")), read_frame(folder)
    dark, light, changes = checker_in_amplitude(plain, textured)
    check("textured", 0.2 <= dark <= 0.7 and 0.2 <= light <= 0.7 and changes >= 3,
          f"amplitude on the cube against the untextured frame: {dark:.0%} dark cells (< 0.4x), {light:.0%} light "
          f"(> 0.7x), {changes:.1f} dark/light changes a row")
    ground, horizon = sky_in_intensity(plain, textured)
    check("textured", 0.1 <= ground <= 0.3 and horizon > 1.2,
          f"background intensity (the ambient map seen directly): ground {ground:.3f}x the default World's "
          f"(map {SKY_GROUND / 0.0509:.3f}x), top rows {horizon:.2f}x the ground")
    layout["image"].spaces.active.image = bpy.data.images["ToF Amplitude"]
    layout["image"].spaces.active.display_channels = 'COLOR'      # invalid pixels black, not the alpha checker
    with context.temp_override(area=layout["image"],
                               region=next(r for r in layout["image"].regions if r.type == 'WINDOW')):
        bpy.ops.image.view_all(fit_view=True)
    yield 1.0
    pixels = screenshot("textured")
    r, box = image_on_screen(pixels, "ToF Amplitude")
    aspect = box[2] / box[3] if box else 0.0
    check("textured", r > 0.8 and abs(aspect / (128 / 106) - 1) < 0.05 and error_banner_px(pixels) < 20,
          f"screenshot: ToF Amplitude at {box} (aspect {aspect:.3f}, image 1.208) matches the image, r = {r:.3f}; "
          f"{error_banner_px(pixels)} red pixels")
    layout["image"].spaces.active.display_channels = 'COLOR_ALPHA'
    untextured_scene(kept)
    show_depth()
    yield 0.5

    # 3. Live Preview while the camera moves ----------------------------------------------------------
    before = files_in(os.path.join(OUT, "tof"))
    tof.live_preview = True
    came = yield from wait_for(lambda: ops.last_result.get("kind") == "preview"
                               and ops.last_result.get("state") == "done", 30)
    first = depth_pixels().copy()
    for step in range(3):
        camera.location.x -= 0.6
        camera.rotation_euler = (mathutils.Vector((0, 0, 0)) - camera.location).to_track_quat('-Z', 'Y').to_euler()
        yield 0.3
    yield 1.0   # the debounce delay (0.5 s) after the last move
    again = yield from wait_for(lambda: ops.last_result.get("kind") == "preview"
                                and ops.last_result.get("state") == "done" and ops.active_preview_job() is None, 30)
    second = depth_pixels()
    show_depth()
    yield 1.0
    pixels = screenshot("live_preview")
    check("live_preview", came and again and first.shape == second.shape == (26, 32, 4),
          f"previews done: {came}, {again}; image {second.shape[1]}x{second.shape[0]} (preview scale 0.25)")
    check("live_preview", not np.array_equal(first, second), "the preview image changed with the camera")
    check("live_preview", files_in(os.path.join(OUT, "tof")) == before, "nothing written by the preview")
    check("live_preview", error_banner_px(pixels) < 20, "no error banner")
    tof.live_preview = False
    yield 0.5

    # 4. Esc cancels a long render --------------------------------------------------------------------
    tof.spp, tof.max_depth = 1024, 5
    tof.output_dir = os.path.join(OUT, "cancel", "####", "")
    click("render")
    started = yield from wait_for(lambda: ops.last_result.get("spp", 0) > 0, 60)
    pressed = time.monotonic()
    context.window.event_simulate(type='ESC', value='PRESS')
    context.window.event_simulate(type='ESC', value='RELEASE')
    stopped = yield from wait_for(lambda: ops.active_render_job() is None, 30)
    seconds = time.monotonic() - pressed
    yield 0.5
    pixels = screenshot("cancel")
    state = ops.last_result.get("state")
    leftovers = [os.path.join(r, f) for r, _, fs in os.walk(os.path.join(OUT, "cancel")) for f in fs]
    check("cancel", started and stopped and state == "cancelled",
          f"first pass seen: {started}; after Esc: state {state!r} in {seconds:.1f} s")
    check("cancel", leftovers == [], f"nothing written: {leftovers}")
    check("cancel", error_banner_px(pixels) < 20, "no error banner")

    # 5. Render ToF Animation, frames 1-3 -------------------------------------------------------------
    scene = context.scene
    tof.spp, tof.max_depth = 4, 2
    tof.output_dir = os.path.join(OUT, "anim", "####", "")
    scene.frame_start, scene.frame_end = 1, 3
    scene.frame_set(1)
    camera.keyframe_insert("location", frame=1)
    camera.location.z += 1.0
    camera.keyframe_insert("location", frame=3)
    scene.frame_set(1)
    returned = click("render_animation")
    done = yield from wait_for(lambda: ops.active_render_job() is None and ops.last_result.get("state") != "running",
                               120)
    show_depth()
    yield 1.0
    pixels = screenshot("animation")
    folders = {name: files_in(os.path.join(OUT, "anim", name)) for name in sorted(files_in(os.path.join(OUT, "anim")))}
    check("animation", returned == {'RUNNING_MODAL'} and done and ops.last_result.get("state") == "done",
          f"returned {returned}, state {ops.last_result.get('state')!r}")
    check("animation", list(folders) == ["0001", "0002", "0003"] and all(f == FILES for f in folders.values()),
          f"folders: { {k: len(v) for k, v in folders.items()} }")
    check("animation", scene.frame_current == 1, f"back on frame {scene.frame_current}")
    check("animation", colourful_px(pixels, rect(layout["image"])) >= MIN_COLOURFUL_PX and error_banner_px(pixels) < 20,
          "the last frame on screen, no error banner")

    # 6. A custom sensor as a Blender preset ----------------------------------------------------------
    tof.width, tof.height, tof.noise_model = 64, 53, 'none'
    bpy.ops.tof.sensor_preset_add(name="GUI Custom Sensor")
    saved = os.path.join(bpy.utils.user_resource('SCRIPTS', path="presets"), "tof_camera", "sensor",
                         "GUI_Custom_Sensor.py")
    bpy.ops.tof.add_camera(preset="o3d303", location=(3.0, -3.0, 2.0))
    other = context.active_object
    other.rotation_euler = (mathutils.Vector((0, 0, 0)) - other.location).to_track_quat('-Z', 'Y').to_euler()
    bpy.ops.script.execute_preset(filepath=saved, menu_idname="TOF_MT_sensor_presets")
    applied = other.data.tof
    applied.output_dir = "//tof/####/"   # the default: the Output panel says where it goes while unsaved
    yield from scroll_panels(8)
    pixels = screenshot("preset")
    check("preset", os.path.isfile(saved), f"saved {saved}")
    check("preset", (applied.preset, applied.width, applied.height, applied.noise_model) == ("kinect_v2", 64, 53, 'none'),
          f"applied to {other.name!r}: {applied.preset}, {applied.width}x{applied.height}, noise {applied.noise_model}")

    # 7. The Info log, as a record (run.py checks Blender's log for "Error:" lines) --------------------
    with open(os.path.join(OUT, "info_log.txt"), "w") as fh:
        fh.write(info_log())

    # 8. Errors the user causes, on purpose: reported, naming the field; the detectors see them ------------
    print("GUI-TEST: an error report on purpose follows", flush=True)
    applied.preset, applied.preset_path = 'CUSTOM', ""
    yield 0.5
    try:
        click("render")
        error = ""
    except RuntimeError as err:   # bpy.ops raises the ERROR report of an operator called from Python
        error = str(err)
    check("error_report", "Camera 'ToF Camera.001': Preset File (preset_path) must name a .toml" in error,
          f"Render ToF reported {error!r}")
    applied.preset, applied.spp, applied.max_depth = "kinect_v2", 1, 1
    blocker = os.path.join(OUT, "blocker")
    open(blocker, "w").close()   # a file where the output folder's parent should be: the worker cannot write
    applied.output_dir = os.path.join(blocker, "####", "")
    click("render")
    failed = yield from wait_for(lambda: ops.active_render_job() is None, 60)
    yield 1.0
    pixels = screenshot("error")
    check("error_report", failed and ops.last_result.get("state") == "error",
          f"a render that cannot write: state {ops.last_result.get('state')!r}, {ops.last_result.get('message')!r}")
    check("error_report", info_error_px(pixels) >= 20,
          f"screenshot: {info_error_px(pixels)} red pixels in the Info editor (the detector sees a real error)")
    shots["areas"] = {key: rect(area) for key, area in layout.items()}


def run():
    steps = scenario()

    def tick():
        try:
            return next(steps)
        except StopIteration:
            pass
        except Exception:
            check("scenario", False, traceback.format_exc().replace("\n", " | "))
        with open(os.path.join(OUT, "results.json"), "w") as fh:
            json.dump(results, fh, indent=1)
        with open(os.path.join(OUT, "shots.json"), "w") as fh:
            json.dump(shots, fh, indent=1)
        bpy.ops.wm.quit_blender()
        return None

    bpy.app.timers.register(tick, first_interval=2.0)


run()
