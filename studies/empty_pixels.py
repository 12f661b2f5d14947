"""Valid pixels where there is nothing (issue 34): the share of background pixels a preset marks valid with
no surface, or with a depth more than 0.3 m off the surface (a wrong unwrap), with sensor noise on.

Scenes:

* ``api``: the issue's API case — a 0.4 m white quad 2 m in front of the camera and a bright 1.5 m quad at
  6.4 m beside it (beyond the Kinect v2's 4.5 m), nothing else; a uniform ambient radiance;
* ``blender_cube``: the issue's add-on scenario, Blender's default 2 m cube seen from (4, −4, 3), 6.4 m away
  (Blender's default grey world is 0.0509 W/(m² sr) of ambient light through the add-on);
* the demo scenes (``plane``, ``corner``, ``box_on_wall``, ``room``, ``textured_room``) from their suggested poses.

For every preset × scene × ambient × spp × seed one render at ``--scale`` of the preset's resolution;
counted over the background pixels (those where the camera sees no surface: ``gt_distance`` NaN, or whose
depth is wrong): a pixel is **bad** when it is valid and

* ``empty``: its pixel-centre ray hits nothing and no pixel of its 3 × 3 neighbourhood has a surface within
  0.3 m of its depth (a partly covered border pixel reports the surface it partly sees: that is a real
  return, not empty space);
* ``off``: it sees a surface, but its depth is more than 0.3 m from the ground truth of every pixel of its
  3 × 3 neighbourhood (not a mixed pixel at an edge) and from the noise-free decoded depth of every pixel
  of it (``distance_per_k``: not the multipath or range ambiguity that the camera's physics gives without
  noise): a wrong unwrap caused by the noise;
* ``aliased``: counted apart, not bad — valid, more than 0.3 m from the ground truth, but where the
  noise-free decode says the same (a single-frequency camera's wrap beyond its unambiguous range, strong
  multipath).

The strict count (``gt`` NaN at the centre, whatever the neighbours) is reported beside it. The share is
taken over the background pixels (no surface at the centre) where a scene has them, else over all pixels.

    .venv/bin/python studies/empty_pixels.py --out out/studies                     # the default grid
    .venv/bin/python studies/empty_pixels.py --presets kinect_v2 --scenes api --spp 1 8 64 --ambient 0.05
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import tofcore

OFF_M = 0.3


def api_scene() -> tofcore.Scene:
    """The issue's API scene in the camera's frame turned to world: camera at the origin looking along +y."""
    def quad(cx, cy, cz, size):
        h = size / 2
        return np.array([[cx - h, cy, cz - h], [cx + h, cy, cz - h], [cx + h, cy, cz + h], [cx - h, cy, cz + h]])
    verts = np.concatenate([quad(0.0, 2.0, 0.0, 0.4), quad(1.2, 6.4, 0.3, 1.5)])
    tris = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    near = tofcore.Material(name="near", reflectance=0.8, roughness=0.5)
    bright = tofcore.Material(name="bright", reflectance=1.0, roughness=0.5)
    return tofcore.Scene.from_arrays(verts, tris, np.array([0, 0, 1, 1]), [near, bright],
                                     object_ids=np.array([0, 0, 1, 1]), object_names=("near quad", "bright quad"),
                                     name="api")


API_POSE = tofcore.look_at((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def bad_pixels(frame: tofcore.Frame) -> dict:
    """Counts of valid pixels with no surface / a depth > 0.3 m off (see the module docstring)."""
    gt = frame.gt_depth.astype(np.float64)
    depth = frame.depth.astype(np.float64)
    valid = frame.valid
    h, w = gt.shape
    padded = np.pad(gt, 1, constant_values=np.nan)
    near = np.zeros((h, w), bool)
    for dy in range(3):
        for dx in range(3):
            with np.errstate(invalid="ignore"):
                near |= np.abs(padded[dy:dy + h, dx:dx + w] - depth) <= OFF_M
    clean = np.full((h, w), np.nan)
    if frame.distance_per_k is not None:
        clean = frame.distance_per_k[-1].astype(np.float64)
        if frame.depth_output == "z":
            clean = clean * np.abs(frame.ray_directions[..., 2])
    padded = np.pad(clean, 1, constant_values=np.nan)
    near_clean = np.zeros((h, w), bool)
    for dy in range(3):
        for dx in range(3):
            with np.errstate(invalid="ignore"):
                near_clean |= np.abs(padded[dy:dy + h, dx:dx + w] - depth) <= OFF_M
    empty_centre = ~np.isfinite(gt)
    with np.errstate(invalid="ignore"):
        off_centre = np.isfinite(gt) & (np.abs(depth - gt) > OFF_M)
    background = empty_centre | off_centre  # pixels where a valid depth would be wrong at the centre
    return {"pixels": int(gt.size), "no_surface_pixels": int(empty_centre.sum()),
            "valid_no_surface_strict": int((valid & empty_centre).sum()),
            "valid_empty": int((valid & empty_centre & ~near).sum()),
            "valid_off": int((valid & off_centre & ~near & ~near_clean).sum()),
            "valid_aliased": int((valid & off_centre & ~near & near_clean).sum()),
            "background_pixels": int(empty_centre.sum()) if empty_centre.any() else int(gt.size),
            "valid_share": float(valid.mean()), "valid_on_surface": float(valid[~empty_centre].mean())
            if (~empty_centre).any() else None,
            "reasons": {r.name: int((frame.reason == int(r)).sum()) for r in tofcore.Reason},
            "_background": background}


def blender_cube() -> tofcore.Scene:
    """Blender's default scene as the issue's add-on scenario: the 2 m cube at the origin (Principled BSDF
    defaults: base colour 0.8, roughness 0.5), seen from (4, −4, 3), 6.4 m away, beyond the Kinect's 4.5 m."""
    corners = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = np.array([t for a, b, c, d in faces for t in ((a, b, c), (a, c, d))])
    return tofcore.Scene.from_arrays(corners, tris, np.zeros(len(tris), int),
                                     [tofcore.Material(name="Material", reflectance=0.8, roughness=0.5)],
                                     name="blender default cube")


BLENDER_POSE = tofcore.look_at((4.0, -4.0, 3.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))


def scene_and_pose(name: str):
    if name == "api":
        return api_scene(), API_POSE
    if name == "blender_cube":
        return blender_cube(), BLENDER_POSE
    scene = tofcore.demo_scene(name)
    return scene, tofcore.suggested_pose(scene)


def run(presets, scenes, ambients, spps, seeds, scale, max_depth, verbose=True) -> list[dict]:
    rows = []
    for preset in presets:
        sensor = tofcore.load_preset(preset).scaled(scale)
        for scene_name in scenes:
            scene, pose = scene_and_pose(scene_name)
            demo_amb = tofcore.demo_ambient(scene_name) if scene_name not in ("api", "blender_cube") else None
            for ambient in ambients:
                amb = tofcore.Ambient(radiance_w_m2_sr=ambient, environment=None if demo_amb is None
                                      else demo_amb.environment) if ambient or demo_amb else None
                for spp in spps:
                    for seed in seeds:
                        t0 = time.perf_counter()
                        frame = tofcore.render(scene, sensor, pose, spp=spp, seed=seed, max_depth=max_depth,
                                               ambient=amb)
                        counts = bad_pixels(frame)
                        counts.pop("_background")
                        row = {"preset": preset, "scene": scene_name, "ambient_w_m2_sr": ambient, "spp": spp,
                               "seed": seed, "seconds": round(time.perf_counter() - t0, 2), **counts}
                        rows.append(row)
                        if verbose:
                            print(f"{preset:9s} {scene_name:13s} amb {ambient:<5g} {spp:5d} spp seed {seed}: "
                                  f"empty {row['valid_empty']:3d} off {row['valid_off']:3d} "
                                  f"aliased {row['valid_aliased']:4d} "
                                  f"(strict {row['valid_no_surface_strict']:3d}) of {row['background_pixels']:5d} "
                                  f"background; valid on surfaces {row['valid_on_surface'] or 0:.3f}; "
                                  f"{row['seconds']:.1f} s", flush=True)
    return rows


def summary(rows: list[dict]) -> dict:
    out = {}
    for key in sorted({(r["preset"], r["scene"]) for r in rows}):
        sel = [r for r in rows if (r["preset"], r["scene"]) == key]
        bad = sum(r["valid_empty"] + r["valid_off"] for r in sel)
        strict = sum(r["valid_no_surface_strict"] for r in sel)
        aliased = sum(r["valid_aliased"] for r in sel)
        background = sum(r["background_pixels"] for r in sel)
        out[f"{key[0]} {key[1]}"] = {"renders": len(sel), "bad": bad, "strict": strict, "background": background,
                                     "bad_share": bad / background, "strict_share": strict / background,
                                     "aliased": aliased, "worst_render_share": max(
                                         (r["valid_empty"] + r["valid_off"]) / r["background_pixels"] for r in sel)}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", nargs="+", default=["kinect_v2", "o3d303", "xtion2"])
    ap.add_argument("--scenes", nargs="+", default=["api", "blender_cube", "plane", "corner", "box_on_wall", "room",
                                                     "textured_room"])
    ap.add_argument("--ambient", nargs="+", type=float, default=[0.0, 0.05, 0.5])
    ap.add_argument("--spp", nargs="+", type=int, default=[1, 8, 64])
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--max-depth", type=int, default=3)
    ap.add_argument("--out", default=None, help="folder for empty_pixels.json")
    args = ap.parse_args()
    started = time.perf_counter()
    rows = run(args.presets, args.scenes, args.ambient, args.spp, range(args.seeds), args.scale, args.max_depth)
    result = {"settings": vars(args), "summary": summary(rows), "rows": rows,
              "seconds": round(time.perf_counter() - started, 1)}
    for name, s in result["summary"].items():
        print(f"{name:24s} bad {s['bad']:4d} / {s['background']:7d} background = {100 * s['bad_share']:.4f} % "
              f"(worst render {100 * s['worst_render_share']:.4f} %, strict {100 * s['strict_share']:.4f} %); "
              f"aliased / multipath {s['aliased']}")
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        Path(args.out, "empty_pixels.json").write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
