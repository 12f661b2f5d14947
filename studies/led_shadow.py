"""Shadow of an object under the offset LED: amplitude and depth error along the scan line.

Thesis §4.0.8 (Abbildung 4.21, 4.22) and §6.2 (Abbildung 6.6): the Kinect v2's and Xtion 2's LEDs sit on
one side of the lens, so part of the background behind an object is in the LEDs' shadow: the camera sees
it, but it is lit only indirectly, and its depth is estimated too far. (The O3D303, with LEDs all around
the lens, does not show it.) The thesis's simulation with the LED 2.5 cm to the side reproduced the
falsified background right of the box.

Renders of the middle scan line (a 512 × 16 band of the Kinect v2 image, full horizontal resolution; no
lens scattering, so the band needs nothing else of the image), noise off:

* ``box_on_wall`` with the preset's LED 2.5 cm left of the lens (box front 1.2 m, wall 2 m);
* the same with the LED at the centre of the lens (no shadow can be seen) as the reference;
* the box moved to 0.6 m from the camera (1.4 m in front of the wall), LED 2.5 cm left: a wider shadow.

The depth error is the noise-free decoded distance (all bounces) minus the ground-truth distance along the
pixel ray; pixels the sensor reports invalid (amplitude below its threshold) are marked.

    .venv/bin/python studies/led_shadow.py --out out/studies      # ~1.5 min on 2 cores
"""

from __future__ import annotations

import time

import numpy as np

import _common as C
import tofcore

BAND_ROWS = 16


def moved_box(scene: tofcore.Scene, dy: float) -> tofcore.Scene:
    """The scene with the box moved by dy along y (towards the camera for dy < 0)."""
    box_id = scene.object_names.index("box")
    v = scene.vertices.astype(np.float64).copy()
    verts = np.unique(scene.triangles[scene.object_ids == box_id])
    v[verts, 1] += dy
    return tofcore.Scene.from_arrays(v, scene.triangles, scene.material_ids, scene.materials,
                                     object_ids=scene.object_ids, object_names=scene.object_names,
                                     name=f"{scene.name}, box moved {dy:+.2f} m", metadata=scene.metadata)


def shadow_width_prediction(b: float, z_box_front: float, z_wall: float, fx: float) -> float:
    """Width (px) of the visible shadow band beside a box edge: b (z_wall − z_front)/z_front on the wall."""
    return b * (z_wall - z_box_front) / z_box_front / z_wall * fx


def main() -> None:
    args = C.parser(__doc__, spp=512, max_depth=5).parse_args()
    started = time.perf_counter()
    preset = tofcore.load_preset("kinect_v2")
    cam, row = C.band_camera(preset.camera, BAND_ROWS)
    led = preset.leds[0]
    centred = tofcore.LED(position_m=(0.0, 0.0, 0.0), intensity_w_sr=led.intensity_w_sr, kind=led.kind)
    demo = tofcore.demo_scene("box_on_wall")
    near = moved_box(demo, -0.6)
    cases = [("box 1.2 m, LED 2.5 cm left", demo, C.kinect(camera=cam), 1.2),
             ("box 1.2 m, LED at the lens", demo, C.kinect(camera=cam, leds=(centred,)), 1.2),
             ("box 0.6 m, LED 2.5 cm left", near, C.kinect(camera=cam), 0.6)]
    b = -led.position_m[0]
    results, frames, records = {}, {}, []
    for label, scene, sensor, z_front in cases:
        f = tofcore.render(scene, sensor, spp=args.spp, max_depth=args.max_depth, seed=args.seed)
        frames[label] = f
        records.append(C.runtime(f, label))
        wall = f.object_id[row] == scene.object_names.index("wall")
        shadow = wall & C.led_shadow(f, sensor, *C.box_bounds(scene))[row]   # hidden from the LED by the box
        err = (f.distance_per_k[-1][row] - f.gt_distance[row]).astype(np.float64)
        amp = f.amplitude[row].astype(np.float64)
        lit = wall & ~shadow
        is_box = f.object_id[row] == scene.object_names.index("box")
        touches_box = np.convolve(is_box.astype(int), [1, 1, 1], mode="same") > 0
        core = shadow & ~touches_box        # shadow pixels whose footprint does not reach the box
        sh_cols = np.nonzero(shadow)[0]
        # neighbouring lit wall pixels right of the shadow, for the amplitude ratio
        right_lit = lit & (np.arange(len(lit)) > (sh_cols.max() if sh_cols.size else 0)) & \
            (np.arange(len(lit)) <= (sh_cols.max() + 10 if sh_cols.size else 0))
        results[label] = {
            "shadow_columns": sh_cols,
            "shadow_width_px": int(shadow.sum()),
            "shadow_width_px_predicted": shadow_width_prediction(-sensor.leds[0].position_m[0], z_front, 2.0, cam.fx),
            "shadow_depth_error_mm": err[shadow] * C.MM,
            "shadow_core_width_px (not next to a box pixel)": int(core.sum()),
            "shadow_core_mean_depth_error_mm": float(np.nanmean(err[core]) * C.MM) if core.any() else None,
            "shadow_core_mean_amplitude_e": float(np.mean(amp[core])) if core.any() else None,
            "shadow_core_pixels_without_any_decodable_return": int(np.sum(core & ~np.isfinite(err))),
            "shadow_mean_amplitude_e": float(np.mean(amp[shadow])) if shadow.any() else None,
            "lit_wall_next_to_shadow_mean_amplitude_e": float(np.mean(amp[right_lit])) if right_lit.any() else None,
            "shadow_pixels_invalid_by_sensor": int(np.sum(shadow & ~np.isfinite(f.depth[row]))),
            "shadow_invalid_reasons": [tofcore.Reason(int(r)).name for r in f.reason[row][shadow]],
            "lit_wall_median_depth_error_mm (not next to the box)": float(np.nanmedian(err[lit & ~touches_box]) * C.MM),
            "shadow_core_error_mm_by_max_path_length": {
                int(k + 1): float(np.nanmean((f.distance_per_k[k][row] - f.gt_distance[row])[core]) * C.MM)
                if core.any() and np.isfinite(f.distance_per_k[k][row][core]).any() else None
                for k in range(f.distance_per_k.shape[0])},
        }
        r = results[label]
        print(f"{label}: shadow {r['shadow_width_px']} px (predicted {r['shadow_width_px_predicted']:.1f}), "
              f"core {r['shadow_core_width_px (not next to a box pixel)']} px, per k {r['shadow_core_error_mm_by_max_path_length']}, "
              f"depth error there {r['shadow_core_mean_depth_error_mm']} mm, amplitude {r['shadow_core_mean_amplitude_e']} e "
              f"vs {r['lit_wall_next_to_shadow_mean_amplitude_e']} e lit, invalid {r['shadow_pixels_invalid_by_sensor']}, "
              f"{records[-1]['seconds']:.1f} s")

    fig, ax = C.plt.subplots(2, 2, figsize=(14, 7.5), sharex="col")
    colours = ["C3", "C0", "C2"]
    windows = []
    for label in (cases[0][0], cases[2][0]):
        right = int(np.nonzero(frames[label].object_id[row] == demo.object_names.index("box"))[0].max())
        windows.append((right - 12, right + 28))
    for j, (label, colour) in enumerate(zip(results, colours)):
        f = frames[label]
        col = 0 if label.startswith("box 1.2") else 1
        c0, c1 = windows[col]
        u = np.arange(c0, c1)
        err = (f.distance_per_k[-1][row] - f.gt_distance[row]) * C.MM
        inval = ~np.isfinite(f.depth[row])
        ax[0, col].semilogy(u, f.amplitude[row, c0:c1], "o-", color=colour, ms=3, lw=0.8, label=label)
        ax[1, col].plot(u, err[c0:c1], "o-", color=colour, ms=3, lw=0.8, label=label)
        iv = inval[c0:c1]
        ax[1, col].plot(u[iv], err[c0:c1][iv], "x", color="k", ms=7)
        sh = np.asarray(results[label]["shadow_columns"])
        if sh.size:
            for a in ax[:, col]:
                a.axvspan(sh.min() - 0.5, sh.max() + 0.5, color=colour, alpha=0.12)
    for col, title in enumerate(("box 1.2 m from the camera (demo scene)", "box moved to 0.6 m")):
        ax[0, col].set_title(title)
        ax[0, col].set_ylabel("amplitude (e⁻, 120 MHz)")
        ax[1, col].set_ylabel("decoded − true distance (mm)")
        ax[1, col].set_xlabel(f"pixel column (middle row); shaded: LED shadow; ×: invalid in the camera output")
        ax[1, col].set_yscale("symlog", linthresh=10)
        for a in ax[:, col]:
            a.grid(alpha=0.3)
            a.legend(fontsize=7)
    fig.suptitle(f"LED shadow beside a box, Kinect v2 (noise, scattering off), 512×{BAND_ROWS} band, {args.spp} spp, "
                 f"max path {args.max_depth}: " + ", ".join(f"{r['seconds']:.0f} s" for r in records))
    fig.tight_layout()
    numbers = {"experiment": "SPEC §6.6 / thesis §4.0.8, §6.2: shadow of an object under the offset LED",
               "sensor": "kinect_v2, noise none, scattering none, 512×16 band around the middle row",
               "led_offset_m": b, "results": results, "runtime": records}
    print(C.runtime_line(records))
    C.write_outputs(args.out, "led_shadow", fig, numbers, started)


if __name__ == "__main__":
    main()
