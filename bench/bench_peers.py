"""Throughput beside the peers: tofcore, Mitsuba 3, mitransient and Blender Cycles on the same frame.

The transport benchmark's frame (``bench/bench_transport.py``): the demo room
(``tofcore.demo_scene("room", detail=10)``, 9,800 triangles; ``--sizes 10k,500k,1M`` for more), 512 × 424,
16 spp, path length 5 surface vertices, one point LED 2.5 cm beside the lens, Kinect-like pinhole
(70.6° × 60° FOV). Every renderer runs in a fresh subprocess, one after the other, and the
sequence is repeated ``--repeat`` times (medians reported) so that background load hits all alike.

* **tofcore** — ``bench/bench_transport.py --one`` with the project venv's Python (NumPy 1.26),
  2 worker threads, an 80 MHz phasor (2 correlation functions). Rays counted by the tracer.
* **Mitsuba 3** ``llvm_ad_rgb`` (bench venv) — ``path`` integrator, ``max_depth`` 6 (= 5 surface
  vertices; Mitsuba counts the camera ray), no Russian roulette, independent sampler, box filter;
  materials: ``diffuse`` with the demo's reflectance, the metal box ``roughconductor`` (GGX, α = σ).
  Timed: ``mi.render`` + evaluation, after one warm-up render (JIT kernels cached; the cold first
  render, with compilation and the BVH build, is reported apart).
* **mitransient** ``llvm_ad_mono`` (bench venv) — ``transient_path`` into a ``phasor_hdr_film``
  with 3 frequencies (16–120 MHz bins), otherwise as Mitsuba.
* **Cycles** CPU via ``bpy`` (project venv, Blender 5.0) — the same triangles, Principled BSDF (base
  colour = reflectance, roughness from σ by the add-on's mapping, metallic for the metal box), a
  point light with radius 0, ``max_bounces`` 4 (= 5 surface vertices), ``min_light_bounces`` 4 (no
  Russian roulette), no adaptive sampling, no denoising, box pixel filter, 2 threads, the exact
  intrinsics through the add-on's camera mapping. Timed: ``bpy.ops.render.render`` (includes the
  scene sync and BVH build of each render; Cycles rebuilds them per render).

Rays for the peers are estimated, not counted: in the closed room no path escapes, so every path
has exactly 5 surface vertices; Mitsuba and Cycles trace 6 closest-hit rays (camera, 4 bounces and
one more after the 5th vertex that looks for emitters — useless with a point light) and 5 shadow
rays: 11 rays per path. tofcore traces 5 closest-hit and 5 shadow rays (10 per path, minus shadow
rays it skips). The ratio printed is the frame-time ratio (same image, same paths), which does not
depend on how rays are counted; "tofcore-equivalent rays/s" = tofcore's ray count / peer's time.

Usage::

    .venv-bench/bin/python bench/bench_peers.py [--repeat 3] [--sizes 10k] [--peers tofcore,mitsuba,mitransient,cycles]

needs ``DRJIT_LIBLLVM_PATH`` (libLLVM 19) for the Mitsuba workers; see studies/crosscheck/README.md.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SIZES = {"10k": 10, "500k": 71, "1M": 101}
LED = (0.025, 0.0, 0.0)
HFOV, VFOV = 70.6, 60.0
FREQ = 80e6


def _setup(detail: int, width: int, height: int):
    import tofcore
    scene = tofcore.demo_scene("room", detail=detail)
    cam = tofcore.Camera.from_fov(width, height, HFOV, VFOV)
    pose = tofcore.suggested_pose(scene)
    led_world = pose[:3, :3] @ np.asarray(LED) + pose[:3, 3]
    return scene, cam, pose, led_world


def _rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


# ------------------------------------------------------------------------------------------- Mitsuba
def _mitsuba_scene(mi, scene, cam, pose, led_world, integrator: dict, film: dict, spp: int):
    tri = scene.triangles
    d = {"type": "scene", "integrator": integrator,
         "sensor": {"type": "perspective", "fov": HFOV, "fov_axis": "x", "near_clip": 1e-3, "far_clip": 1e3,
                    "to_world": mi.ScalarTransform4f((np.asarray(pose) @ np.diag([-1.0, -1, 1, 1])).tolist()),
                    "sampler": {"type": "independent", "sample_count": spp},
                    "film": dict(film, width=cam.width, height=cam.height, rfilter={"type": "box"})},
         "led": {"type": "point", "position": led_world.tolist(), "intensity": {"type": "uniform", "value": 1.0}}}
    for m, mat in enumerate(scene.materials):
        sel = np.flatnonzero(scene.material_ids == m)
        if not len(sel):
            continue
        used, inv = np.unique(tri[sel], return_inverse=True)
        mesh = mi.Mesh(f"m{m}", len(used), len(sel), has_vertex_normals=False, has_vertex_texcoords=False)
        params = mi.traverse(mesh)
        params["vertex_positions"] = mi.Float(np.ascontiguousarray(scene.vertices[used], np.float32).ravel())
        params["faces"] = mi.UInt32(inv.reshape(-1, 3).astype(np.uint32).ravel())
        params.update()
        if mat.metallic >= 1.0:
            bsdf = {"type": "roughconductor", "distribution": "ggx", "alpha": max(mat.roughness, 1e-3)}
        else:
            bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [mat.reflectance] * 3}
                    if mi.variant().endswith("rgb") else {"type": "uniform", "value": mat.reflectance}}
        mesh.set_bsdf(mi.load_dict({"type": "twosided", "bsdf": bsdf}))
        d[f"mesh{m}"] = mesh
    return mi.load_dict(d)


def mitsuba_integrator_film(transient: bool, max_depth: int) -> tuple[dict, dict]:
    """The integrator and film dicts of the Mitsuba (``path``, RGB ``hdrfilm``) or mitransient
    (``transient_path``, ``phasor_hdr_film``) frame; also used by ``bench/bench_gpu.py``."""
    integ = {"type": "transient_path" if transient else "path", "max_depth": max_depth + 1, "rr_depth": 1000}
    if transient:
        span = 299_792_458.0 / 8e6          # FFT bins k·8 MHz; k = 2..15 → 16..120 MHz (14 frequencies)
        film = {"type": "phasor_hdr_film", "temporal_bins": 64, "bin_width_opl": span / 64, "start_opl": 0.0,
                "wl_mean": span / 8.5, "wl_sigma": span / (6 * 6.4 / 3)}
    else:
        film = {"type": "hdrfilm", "pixel_format": "rgb"}
    return integ, film


def _save_preview(img: np.ndarray, path: str) -> None:
    """Grey PNG of an (H, W[, C]) radiance image, scaled to its 99th percentile (to check the view)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    g = img.mean(axis=-1) if img.ndim == 3 else img
    plt.imsave(path, np.clip(g / np.percentile(g, 99), 0, 1) ** (1 / 2.2), cmap="gray", vmin=0, vmax=1)


def run_mitsuba(detail, spp, max_depth, width, height, transient: bool, repeat: int, image=None) -> dict:
    import drjit as dr
    import mitsuba as mi
    mi.set_variant("llvm_ad_mono" if transient else "llvm_ad_rgb")
    if transient:
        import mitransient  # noqa: F401
    scene, cam, pose, led_world = _setup(detail, width, height)
    integ, film = mitsuba_integrator_film(transient, max_depth)
    t0 = time.perf_counter()
    sc = _mitsuba_scene(mi, scene, cam, pose, led_world, integ, film, spp)
    load_s = time.perf_counter() - t0
    integrator = sc.integrator()

    def one(seed):
        t = time.perf_counter()
        img = integrator.render(sc, seed=seed, spp=spp) if transient else mi.render(sc, seed=seed, spp=spp)
        dr.eval(img)
        np.asarray(img[1] if transient else img)   # forces completion
        return time.perf_counter() - t

    cold = one(0)
    warm = [one(1 + i) for i in range(repeat)]
    if image:
        img = integrator.render(sc, seed=0, spp=spp)[0] if transient else mi.render(sc, seed=0, spp=spp)
        _save_preview(np.asarray(img, dtype=np.float64), image)
    n_freq = len(np.asarray(sc.sensors()[0].film().frequencies).ravel()) if transient else 0
    return {"renderer": "mitransient" if transient else "mitsuba", "variant": mi.variant(),
            "version": mi.__version__, "triangles": scene.triangle_count, "load_s": load_s,
            "cold_s": cold, "frame_s": statistics.median(warm), "frames_s": warm, "frequencies": n_freq,
            "threads": dr.thread_count(), "peak_rss_mib": _rss_mib()}


# -------------------------------------------------------------------------------------------- Cycles
def run_cycles(detail, spp, max_depth, width, height, repeat: int, image=None) -> dict:
    import importlib.util

    import bpy
    spec = importlib.util.spec_from_file_location("tof_mapping", ROOT / "addon" / "mapping.py")
    mapping = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mapping)

    scene, cam, pose, led_world = _setup(detail, width, height)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bs = bpy.context.scene
    mesh = bpy.data.meshes.new("room")
    v = scene.vertices.astype(np.float32)
    t = scene.triangles.astype(np.int32)
    mesh.vertices.add(len(v))
    mesh.vertices.foreach_set("co", v.ravel())
    mesh.loops.add(t.size)
    mesh.loops.foreach_set("vertex_index", t.ravel())
    mesh.polygons.add(len(t))
    mesh.polygons.foreach_set("loop_start", np.arange(0, t.size, 3, dtype=np.int32))
    mesh.polygons.foreach_set("loop_total", np.full(len(t), 3, np.int32))
    mesh.polygons.foreach_set("material_index", scene.material_ids.astype(np.int32))
    mesh.update()
    mesh.validate()
    for mat in scene.materials:
        m = bpy.data.materials.new(mat.name)
        m.use_nodes = True
        p = m.node_tree.nodes["Principled BSDF"]
        p.inputs["Base Color"].default_value = (mat.reflectance,) * 3 + (1.0,)
        p.inputs["Roughness"].default_value = float(mapping.blender_roughness_from_sigma(mat.roughness))
        p.inputs["Metallic"].default_value = float(mat.metallic)
        mesh.materials.append(m)
    obj = bpy.data.objects.new("room", mesh)
    bs.collection.objects.link(obj)

    c = bpy.data.cameras.new("tof")
    s = mapping.blender_camera_from_intrinsics(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    c.sensor_fit = s["sensor_fit"]
    c.sensor_width, c.sensor_height = s["sensor_width_mm"], s["sensor_height_mm"]
    c.lens_unit = "MILLIMETERS"
    c.lens = s["lens_mm"]
    c.shift_x, c.shift_y = s["shift_x"], s["shift_y"]
    c.clip_start, c.clip_end = 1e-3, 1e3
    co = bpy.data.objects.new("tof", c)
    import mathutils
    co.matrix_world = mathutils.Matrix((np.asarray(pose) @ np.diag([1.0, -1, -1, 1])).tolist())
    bs.collection.objects.link(co)
    bs.camera = co
    light = bpy.data.lights.new("led", type="POINT")
    light.shadow_soft_size = 0.0
    light.energy = 4 * np.pi   # 1 W/sr-ish; irrelevant for timing
    lo = bpy.data.objects.new("led", light)
    lo.location = led_world.tolist()
    bs.collection.objects.link(lo)
    world = bpy.data.worlds.new("black")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    bs.world = world

    r = bs.render
    r.engine = "CYCLES"
    r.resolution_x, r.resolution_y, r.resolution_percentage = s["resolution_x"], s["resolution_y"], 100
    r.pixel_aspect_x, r.pixel_aspect_y = s["pixel_aspect_x"], s["pixel_aspect_y"]
    r.threads_mode = "FIXED"
    r.threads = os.cpu_count() or 1
    r.filepath = os.path.join(tempfile.mkdtemp(), "cycles.exr")
    r.image_settings.file_format = "OPEN_EXR"
    cy = bs.cycles
    cy.device = "CPU"
    cy.samples = spp
    cy.use_adaptive_sampling = False
    cy.use_denoising = False
    cy.max_bounces = max_depth - 1
    cy.diffuse_bounces = max_depth - 1
    cy.glossy_bounces = max_depth - 1
    cy.transmission_bounces = 0
    cy.volume_bounces = 0
    cy.transparent_max_bounces = 0
    cy.min_light_bounces = max_depth - 1          # no Russian roulette before the last bounce
    cy.min_transparent_bounces = 0
    cy.pixel_filter_type = "BOX"
    cy.sample_clamp_direct = 0.0
    cy.sample_clamp_indirect = 0.0
    cy.caustics_reflective = True
    cy.seed = 0
    for attr, value in (("use_light_tree", False), ("light_sampling_threshold", 0.0),
                        ("use_auto_tile", False)):
        if hasattr(cy, attr):
            setattr(cy, attr, value)

    def one(seed):
        cy.seed = seed
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=False)
        return time.perf_counter() - t0

    cold = one(0)
    warm = [one(1 + i) for i in range(repeat)]
    if image:
        r.filepath = image
        r.image_settings.file_format = "PNG"
        bs.view_settings.view_transform = "Standard"
        bpy.ops.render.render(write_still=True)
    return {"renderer": "cycles", "version": bpy.app.version_string, "triangles": scene.triangle_count,
            "cold_s": cold, "frame_s": statistics.median(warm), "frames_s": warm, "threads": r.threads,
            "peak_rss_mib": _rss_mib()}


# ------------------------------------------------------------------------------------------- driver
def _worker(python: str, args: list[str], env: dict | None = None) -> dict:
    out = subprocess.run([python] + args, check=True, capture_output=True, text=True, env=env or os.environ)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="10k", help="comma list of 10k, 500k, 1M (default: 10k)")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--max-depth", type=int, default=5, help="surface vertices per path")
    ap.add_argument("--resolution", default="512x424")
    ap.add_argument("--repeat", type=int, default=3, help="rounds over all renderers (medians reported)")
    ap.add_argument("--peers", default="tofcore,mitsuba,mitransient,cycles")
    ap.add_argument("--tofcore-python", default=str(ROOT / ".venv" / "bin" / "python"))
    ap.add_argument("--mitsuba-python", default=str(ROOT / ".venv-bench" / "bin" / "python"))
    ap.add_argument("--bpy-python", default=str(ROOT / ".venv" / "bin" / "python"))
    ap.add_argument("--json", help="write all runs to this JSON file")
    ap.add_argument("--table", help="print the table from a JSON written by --json, render nothing")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--detail", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--image", help=argparse.SUPPRESS)  # worker: also save a preview PNG here
    args = ap.parse_args()
    width, height = (int(x) for x in args.resolution.split("x"))

    if args.worker:   # one renderer in this process; print JSON
        if args.worker in ("mitsuba", "mitransient"):
            r = run_mitsuba(args.detail, args.spp, args.max_depth, width, height, args.worker == "mitransient", 1,
                            args.image)
        elif args.worker == "cycles":
            r = run_cycles(args.detail, args.spp, args.max_depth, width, height, 1, args.image)
        else:
            raise SystemExit(f"unknown worker {args.worker}")
        print(json.dumps(r))
        return 0

    if args.table:
        with open(args.table) as fh:
            table(json.load(fh), args)
        return 0
    peers = args.peers.split(",")
    tmp = tempfile.mkdtemp(prefix="bench_peers_")
    bpy_env = dict(os.environ, BLENDER_USER_RESOURCES=tmp, BLENDER_USER_CONFIG=tmp, BLENDER_USER_SCRIPTS=tmp,
                   XDG_CONFIG_HOME=tmp, XDG_CACHE_HOME=tmp, XDG_DATA_HOME=tmp)
    common = ["--spp", str(args.spp), "--max-depth", str(args.max_depth), "--resolution", args.resolution]
    runs: dict = {}
    for size in args.sizes.split(","):
        detail = SIZES[size]
        runs[size] = {p: [] for p in peers}
        for rnd in range(args.repeat):
            for p in peers:
                t0 = time.perf_counter()
                if p == "tofcore":
                    r = _worker(args.tofcore_python, [str(ROOT / "bench" / "bench_transport.py"), "--one",
                                                      str(detail)] + common)
                elif p == "cycles":
                    r = _worker(args.bpy_python, [__file__, "--worker", "cycles", "--detail", str(detail)] + common,
                                bpy_env)
                else:
                    r = _worker(args.mitsuba_python, [__file__, "--worker", p, "--detail", str(detail)] + common)
                r["wall_s"] = time.perf_counter() - t0
                r["load_avg_1min"] = os.getloadavg()[0]
                runs[size][p].append(r)
                print(f"# {size} round {rnd + 1} {p}: frame {r['frame_s']:.2f} s "
                      f"(load {r['load_avg_1min']:.1f})", file=sys.stderr, flush=True)

    if args.json:
        with open(args.json, "w") as fh:
            json.dump(runs, fh, indent=1)
    table(runs, args)
    return 0


def table(runs: dict, args) -> None:
    width, height = (int(x) for x in args.resolution.split("x"))
    paths = width * height * args.spp
    print(f"\n{args.resolution}, {args.spp} spp, path length {args.max_depth}, demo room, 1 point LED 2.5 cm beside "
          f"the lens; medians of {args.repeat} rounds (min–max in brackets)\n")
    print("| triangles | renderer | frame s | M paths/s | M rays/s (own count) | M tofcore-equiv. rays/s "
          "| × tofcore | × tofcore per round | cold first frame s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for size, by_peer in runs.items():
        t_rays = statistics.median([r["rays"] for r in by_peer["tofcore"]]) if "tofcore" in by_peer else None
        t_frame = statistics.median([r["frame_s"] for r in by_peer["tofcore"]]) if "tofcore" in by_peer else None
        for p, rs in by_peer.items():
            frames = [r["frame_s"] for r in rs]
            f = statistics.median(frames)
            if p == "tofcore":
                rays = statistics.median([r["rays"] for r in rs])
                own, cold = rays / f, "–"
            else:
                rays = paths * (2 * args.max_depth + 1)
                own, cold = rays / f, f"{statistics.median([r['cold_s'] for r in rs]):.2f}"
            equiv = f"{t_rays / f / 1e6:.2f}" if t_rays else "–"
            ratio = f"{t_frame / f:.1f}" if t_frame else "–"
            # Same-round ratios: the load changes between rounds more than within one.
            if "tofcore" in by_peer:
                per_round = [t["frame_s"] / r["frame_s"] for t, r in zip(by_peer["tofcore"], rs)]
                rounds = f"{statistics.median(per_round):.1f} [{min(per_round):.1f}–{max(per_round):.1f}]"
            else:
                rounds = "–"
            tri = rs[0]["triangles"]
            print(f"| {tri:,} | {p} | {f:.2f} [{min(frames):.2f}–{max(frames):.2f}] | {paths / f / 1e6:.2f} "
                  f"| {own / 1e6:.2f} | {equiv} | {ratio} | {rounds} | {cold} |")
    print("\nown count: tofcore counts its rays; peers: paths × 11 (6 closest-hit + 5 shadow rays, closed room). "
          "× tofcore = median tofcore frame time / median peer frame time; per round: median [min–max] of the "
          "ratios within each round. Mitsuba/mitransient frame: warm render (kernels "
          "cached); cold: first render in a fresh process (JIT + BVH). Cycles frame includes its per-render "
          "scene sync and BVH build. tofcore frame excludes its BVH build (bench_transport.py).")


if __name__ == "__main__":
    sys.exit(main())
