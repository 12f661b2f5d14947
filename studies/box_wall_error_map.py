"""Box in front of a bright wall, Kinect v2: error map against the scene without the box.

Thesis §6.1 (Abbildung 6.2, 6.3) and §6.2 (Abbildung 6.6): a box in front of a strongly reflecting
background; a depth image of the background alone, then one with the box; the difference shows where the
box changes the background's depth. The thesis saw the deviations partly at the same places as the real
Kinect v2 — "especially at the floor and below the box", caused mostly by indirect light — the floor's
point cloud strongly distorted by indirect light (weaker in the simulation, which lacked the LED's
vignetting), flying pixels and rounded box edges from lens scattering, and a falsified background right
of the box caused by the LED 2.5 cm to the side.

Two cases, each rendered with and without the box (same seed), Kinect v2 preset at its full 512 × 424
with the LED 2.5 cm left of the lens and its Airy lens scattering, noise off (the maps compare systematic
deviations; single-frame noise would hide them):

* ``box_on_wall`` (the demo scene): wall ρ 0.9 at 2 m, a 0.3 m box ρ 0.5 hanging 0.5 m in front of it,
  camera level with the box. No floor.
* ``box on the floor``: the same wall and box, the box standing on a floor (ρ 0.5, σ 0.5) 0.5 m in front
  of the wall, the camera 1 m high, 2 m from the wall, looking down 14° — closer to the thesis's set-up
  (Abbildung 6.1), where the floor and the region below the box showed the largest deviations.

Difference = depth(with box) − depth(without box) on the pixels whose first surface is not the box
(box pixels masked). Pixels hidden from the LED by the box (its "shadow") are found geometrically.

    .venv/bin/python studies/box_wall_error_map.py --out out/studies      # ~2 min on 2 cores
"""

from __future__ import annotations

import time

import numpy as np

import _common as C
import tofcore
from tofcore import Material


def box_on_floor() -> tuple[tofcore.Scene, tuple, tuple]:
    """Wall at y = 0, floor at z = 0, a 0.3 m box standing on the floor 0.5 m in front of the wall."""
    wall = Material(name="wall", reflectance=0.9, roughness=0.5)
    box = Material(name="box", reflectance=0.5, roughness=0.5)
    floor = Material(name="floor", reflectance=0.5, roughness=0.5)
    v, t, m, o = [], [], [], []

    def quad(corner, eu, ev, mat, obj, n=4):
        s = np.linspace(0, 1, n + 1)
        uu, vv = np.meshgrid(s, s)
        pts = np.asarray(corner) + uu.reshape(-1, 1) * np.asarray(eu) + vv.reshape(-1, 1) * np.asarray(ev)
        i = (np.arange(n)[None, :] + (n + 1) * np.arange(n)[:, None]).ravel()
        tri = np.concatenate([np.stack([i, i + 1, i + n + 2], 1), np.stack([i, i + n + 2, i + n + 1], 1)])
        base = sum(len(x) for x in v)
        v.append(pts); t.append(tri + base); m.append(np.full(len(tri), mat)); o.append(np.full(len(tri), obj))

    quad((-2.0, 0.0, 0.0), (4.0, 0, 0), (0, 0, 3.0), 0, 0)        # wall, normal −y
    quad((-2.0, -3.0, 0.0), (0, 3.0, 0), (4.0, 0, 0), 2, 1)       # floor, normal +z
    lo, hi = (-0.15, -0.8, 0.0), (0.15, -0.5, 0.3)
    ex, ey, ez = np.diag(np.subtract(hi, lo))
    lo_a = np.asarray(lo, float)
    for corner, eu, ev in ((lo_a + ez, ex, ey), (lo_a, ex, ez), (lo_a + ey, ez, ex), (lo_a, ez, ey),
                           (lo_a + ex, ey, ez)):                   # box without its bottom face
        quad(corner, eu, ev, 1, 2)
    scene = tofcore.Scene.from_arrays(np.concatenate(v), np.concatenate(t), np.concatenate(m), [wall, box, floor],
                                      object_ids=np.concatenate(o), object_names=["wall", "floor", "box"],
                                      name="box on the floor",
                                      metadata={"world_from_sensor": tofcore.look_at((0, -2.0, 1.0), (0, 0, 0.5)).tolist()})
    return scene, lo, hi


def reasons(frame, mask) -> dict:
    """Invalid pixels under ``mask`` by reason (tofcore.Reason names)."""
    r = frame.reason[mask]
    return {tofcore.Reason(int(k)).name: int(np.sum(r == k)) for k in np.unique(r) if k}


def run_case(label, scene, lo, hi, sensor, args):
    without = C.remove_object(scene, "box")
    f1 = tofcore.render(scene, sensor, spp=args.spp, max_depth=args.max_depth, seed=args.seed)
    f0 = tofcore.render(without, sensor, spp=args.spp, max_depth=args.max_depth, seed=args.seed)
    box_id = scene.object_names.index("box")
    box = f1.object_id == box_id
    background = (f1.object_id >= 0) & ~box
    diff = np.where(background, (f1.depth - f0.depth).astype(np.float64), np.nan)
    noise_free = np.where(background, (f1.distance_per_k[-1] - f0.distance_per_k[-1]).astype(np.float64), np.nan)
    shadow = C.led_shadow(f1, sensor, lo, hi) & background
    valid1 = np.isfinite(f1.depth)
    # Chebyshev distance (px) of every pixel from the box, by repeated dilation.
    near = np.full(box.shape, np.inf)
    grow = box.copy()
    for r in range(1, 61):
        g = grow.copy()
        g[1:] |= grow[:-1]; g[:-1] |= grow[1:]; g[:, 1:] |= grow[:, :-1]; g[:, :-1] |= grow[:, 1:]
        near[g & ~grow] = r
        grow = g
    lit = background & ~shadow & valid1
    edge = lit & (near <= 2)
    halo = lit & (near > 2) & (near <= 30)
    far = lit & (near > 60)

    def stats(mask, values):
        v = values[mask & np.isfinite(values)]
        return {"pixels": int(mask.sum()), "finite": int(v.size),
                "median_mm": float(np.median(v) * C.MM) if v.size else None,
                "mean_mm": float(np.mean(v) * C.MM) if v.size else None,
                "p95_abs_mm": float(np.percentile(np.abs(v), 95) * C.MM) if v.size else None,
                "max_mm": float(np.max(v) * C.MM) if v.size else None,
                "min_mm": float(np.min(v) * C.MM) if v.size else None}

    finite = diff[np.isfinite(diff)]
    res = {
        "background_pixels_changed": {f">{t} mm": int(np.sum(np.abs(finite) > t / C.MM)) for t in (2, 5, 10, 50)},
        "background_pixels_invalid_with_box": int(np.sum(background & ~valid1)),
        "background_pixels_invalid_without_box": int(np.sum(background & ~np.isfinite(f0.depth))),
        "invalid_reasons_with_box": reasons(f1, background),
        "invalid_reasons_without_box": reasons(f0, background),
        "shadow": {**stats(shadow, diff), "invalid": int(np.sum(shadow & ~valid1)),
                   "noise_free_decode_change": stats(shadow, noise_free)},
        "edge_ring_1_2px": stats(edge, diff),
        "halo_3_30px": {**stats(halo, diff), "noise_free_decode_change": stats(halo, noise_free)},
        "beyond_60px": stats(far, diff),
        "runtime": [C.runtime(f1, f"{label}, with box"), C.runtime(f0, f"{label}, without box")],
    }
    if "floor" in scene.object_names:
        floor = f1.object_id == scene.object_names.index("floor")
        in_front = floor & (near <= 60) & lit
        res["floor_in_front_of_box_within_60px"] = {**stats(in_front, diff),
                                                    "noise_free_decode_change": stats(in_front, noise_free)}
        fl0 = f0.object_id == scene.object_names.index("floor")
        err0 = (f0.distance_per_k[-1] - f0.gt_distance).astype(np.float64)
        res["floor_error_without_box_vs_ground_truth"] = stats(fl0, err0)
        res["wall_error_without_box_vs_ground_truth"] = stats(f0.object_id == scene.object_names.index("wall"), err0)
        rows, cols = np.nonzero(box)
        above = np.zeros_like(box)
        above[:rows.min(), max(0, cols.min() - 60):cols.max() + 61] = True
        wall_above = above & (f1.object_id == scene.object_names.index("wall")) & lit
        res["wall_above_box_within_60px_columns"] = {**stats(wall_above, diff),
                                                     "noise_free_decode_change": stats(wall_above, noise_free)}
    return f1, f0, diff, noise_free, shadow, valid1, background, res


def main() -> None:
    args = C.parser(__doc__, spp=16, max_depth=4).parse_args()
    started = time.perf_counter()
    sensor = C.kinect(scattering=True)
    demo = tofcore.demo_scene("box_on_wall")
    bv = demo.vertices[demo.triangles[demo.object_ids == demo.object_names.index("box")]].reshape(-1, 3)
    floor_scene, flo, fhi = box_on_floor()
    cases = [("box_on_wall", demo, bv.min(0), bv.max(0), "row"), ("box on the floor", floor_scene, flo, fhi, "column")]
    numbers = {"experiment": "SPEC §6.1 / thesis §6.1, §6.2: box in front of a bright wall, error map against the "
                             "scene without the box",
               "sensor": "kinect_v2 (512×424, LED 2.5 cm left, Airy scattering on), noise none", "cases": {}}
    fig, ax = C.plt.subplots(2, 3, figsize=(16, 9.2))
    lim = 20.0
    records = []
    for i, (label, scene, lo, hi, profile) in enumerate(cases):
        f1, f0, diff, noise_free, shadow, valid1, background, res = run_case(label, scene, lo, hi, sensor, args)
        numbers["cases"][label] = res
        records += res["runtime"]
        print(label, {k: v for k, v in res.items() if k != "runtime"})
        im = ax[i, 0].imshow(f1.depth, cmap="viridis")
        ax[i, 0].set_title(f"{label}: depth with the box (m)", fontsize=10)
        fig.colorbar(im, ax=ax[i, 0], fraction=0.04)
        cmap = C.plt.cm.RdBu_r.copy()
        cmap.set_bad("0.6")
        im = ax[i, 1].imshow(np.ma.masked_invalid(diff * C.MM), cmap=cmap, vmin=-lim, vmax=lim)
        inv = background & ~valid1
        ax[i, 1].imshow(np.ma.masked_where(~inv, np.ones(diff.shape)), cmap="gray_r", vmin=0, vmax=1)
        ax[i, 1].contour(shadow, levels=[0.5], colors="k", linewidths=0.6)
        ax[i, 1].set_title("depth(with box) − depth(without) (mm); grey: box,\nblack: invalid, contour: LED shadow",
                           fontsize=9)
        fig.colorbar(im, ax=ax[i, 1], fraction=0.04)
        if profile == "row":
            idx = int(round(sensor.camera.cy))
            cut = lambda a: a[idx]  # noqa: E731
            ax[i, 2].set_xlabel(f"pixel column (row {idx})")
        else:
            idx = int(np.median(np.nonzero(f1.object_id == scene.object_names.index("box"))[1]))
            cut = lambda a: a[:, idx]  # noqa: E731
            ax[i, 2].set_xlabel(f"pixel row (column {idx}, through the box; floor at the bottom)")
        x = np.arange(len(cut(diff)))
        ax[i, 2].plot(x, cut(diff) * C.MM, "-", lw=1, label="camera output (scattering on)")
        ax[i, 2].plot(x, cut(noise_free) * C.MM, "-", lw=0.8, label="noise- and scatter-free decode")
        ax[i, 2].plot(x, np.where(cut(shadow), 0.0, np.nan), "k-", lw=4, label="LED shadow")
        ax[i, 2].set_ylim(-lim, 3 * lim)
        ax[i, 2].set_ylabel("change of the background depth (mm)")
        ax[i, 2].legend(fontsize=7)
        ax[i, 2].grid(alpha=0.3)
    numbers["runtime"] = records
    total = sum(r["seconds"] for r in records)
    fig.suptitle(f"Box in front of a bright wall, Kinect v2 (scattering on, noise off): 4 renders of 512×424, "
                 f"{args.spp} spp, max path {args.max_depth}, {total:.0f} s")
    fig.tight_layout()
    print(C.runtime_line(records))
    C.write_outputs(args.out, "box_wall_error_map", fig, numbers, started, dpi=75, colors=64)


if __name__ == "__main__":
    main()
