"""Flying pixels with and without lens scattering: a near box edge in front of a far wall.

Thesis §6.2 (Abbildung 6.4, 6.5) and §4.0.6–4.0.7: supersampling each pixel (several rays per pixel) makes
mixed pixels, but "that is not enough" to match the Kinect v2's flying pixels; with lens scattering the
simulation agrees with the measured point cloud. §4.0.7 even concluded that the flying pixels of the real
cameras come from lens scattering alone. Lens scattering also lets a bright foreground falsify the
background depth next to it.

Two renders of ``box_on_wall`` (box front at z = 1.2 m, wall at z = 2.0 m) with the Kinect v2 preset at
512 × 424, noise off, the same seed (so the traced light is identical), lens scattering off (only the
pixel-footprint mixing of the supersampled rays) and on (the preset's Airy PSF: 2 % scattered, first dark
ring at 2 px, 5 % negative ring). A flying pixel is a valid pixel within 3 px of the box's outline whose
depth lies between the foreground and the background by more than X from both (X = 5 cm, which no
decoder's wiggling error reaches; 1 and 2 cm in the JSON).

Because the Kinect v2 decoder invalidates pixels whose three frequencies disagree, the same raw images are
also decoded from the 16 MHz images alone (what a one-frequency sensor would report), and the scattering
strength is varied (0.05, 0.1, 0.2) and a dark wall (ρ 0.05, the thesis's §4.0.6 set-up: bright
foreground, dark background) tried, by applying the PSF to the scattering-free raw images exactly as the
renderer does (checked against the render with scattering on).

    .venv/bin/python studies/flying_pixels.py --out out/studies      # ~2.5 min on 2 cores
"""

from __future__ import annotations

import time

import numpy as np

import _common as C
import tofcore
from tofcore.sensor import decode, optics

Z_FG, Z_BG = 1.2, 2.0   # box front face and wall, z along the optical axis (m)
EDGE_PX = 3             # the edge zone: pixels within 3 px of the box's outline, on either side


def flying(depth: np.ndarray, x_m: float) -> np.ndarray:
    return np.isfinite(depth) & (depth > Z_FG + x_m) & (depth < Z_BG - x_m)


def rescatter(frame: tofcore.Frame, sensor: tofcore.Sensor, strength: float, modulation=None,
              raw_slice=slice(None), radius_px: float | None = None) -> np.ndarray:
    """z-depth after applying the sensor's Airy PSF with another strength to the raw images of a
    scattering-free, noise-free frame and decoding with the sensor's rules — the same steps as
    ``tofcore.render`` (scattering, full-well clip, decode, radial → z). Optionally decode only some raw
    images with another modulation (e.g. one frequency of the three)."""
    s = sensor.scattering
    raw = frame.raw[raw_slice].astype(np.float64)
    if strength > 0:
        kernel = optics.psf_kernel(s.model, strength=strength, radius_px=radius_px or s.radius_px,
                                   negative_lobe=s.negative_lobe)
        raw = optics.apply_scattering(raw, kernel)
    raw = np.minimum(raw, sensor.readout.full_well_e)
    dec = decode.decode(raw, modulation or sensor.modulation, decode.DecodeSettings(
        min_amplitude_e=sensor.invalid.min_amplitude_e, saturation_e=sensor.readout.full_well_e,
        range_m=tuple(sensor.range_m), unwrap_tolerance_m=sensor.invalid.unwrap_tolerance_m))
    return decode.radial_to_z(dec.distance, frame.ray_directions).astype(np.float64)


def rings(box: np.ndarray, n: int) -> np.ndarray:
    """Chebyshev distance (px) of every pixel from the box mask, up to n (inf beyond)."""
    near = np.full(box.shape, np.inf)
    grow = box.copy()
    for r in range(1, n + 1):
        g = grow.copy()
        g[1:] |= grow[:-1]; g[:-1] |= grow[1:]; g[:, 1:] |= grow[:, :-1]; g[:, :-1] |= grow[:, 1:]
        near[g & ~grow] = r
        grow = g
    return near


def counts(depth: np.ndarray, gt: np.ndarray, zone: np.ndarray, lit_wall: np.ndarray, near: np.ndarray) -> dict:
    """Flying and invalid pixels in the edge zone; mean error of the directly lit wall by distance from the box."""
    err = depth - gt
    return {"flying_pixels_in_edge_zone": {f"X = {x} cm": int((flying(depth, x / 100) & zone).sum()) for x in (1, 2, 5)},
            "flying_pixels_whole_image_X5cm": int(flying(depth, 0.05).sum()),
            "invalid_pixels_in_edge_zone": int((~np.isfinite(depth) & zone).sum()),
            "edge_zone_pixels": int(zone.sum()),
            "invalid_pixels": int((~np.isfinite(depth)).sum()),
            "lit_wall_mean_error_mm_by_ring_px": {int(r): float(np.nanmean(err[lit_wall & (near == r)]) * C.MM)
                                                  for r in (1, 2, 3, 4, 6, 8, 10)},
            "lit_wall_mean_error_mm_beyond_10px": float(np.nanmean(err[lit_wall & ~(near <= 10)]) * C.MM)}


def main() -> None:
    args = C.parser(__doc__, spp=32, max_depth=3).parse_args()
    started = time.perf_counter()
    bright = tofcore.demo_scene("box_on_wall")
    dark = C.with_materials(bright, [tofcore.Material(name="black paper", reflectance=0.05, roughness=0.5),
                                     bright.materials[1]])
    off_sensor, on_sensor = C.kinect(scattering=False), C.kinect(scattering=True)
    preset_strength = on_sensor.scattering.strength
    frames = {
        "scattering off": tofcore.render(bright, off_sensor, spp=args.spp, max_depth=args.max_depth, seed=args.seed),
        "scattering on": tofcore.render(bright, on_sensor, spp=args.spp, max_depth=args.max_depth, seed=args.seed),
        "dark wall, scattering off": tofcore.render(dark, off_sensor, spp=args.spp, max_depth=args.max_depth,
                                                    seed=args.seed),
    }
    f_off, f_on, f_dark = frames.values()
    row = int(round(on_sensor.camera.cy))
    box = f_off.object_id == bright.object_names.index("box")
    wall = ~box & (f_off.object_id >= 0)
    near = rings(box, 12)
    zone = (near <= EDGE_PX) | (box & (rings(~box & (f_off.object_id >= 0), EDGE_PX) <= EDGE_PX))
    lit_wall = wall & ~C.led_shadow(f_off, off_sensor, *C.box_bounds(bright))   # not in the box's LED shadow
    cols = np.nonzero(box[row])[0]
    left, right = int(cols.min()), int(cols.max())
    gt = f_off.gt_depth.astype(np.float64)
    # The post-processed preset strength must reproduce the render with scattering on exactly.
    same = rescatter(f_off, on_sensor, preset_strength)
    on_depth = f_on.depth.astype(np.float64)
    check = float(np.nanmax(np.abs(same - on_depth))) if np.isfinite(same).any() else None
    assert np.array_equal(np.isfinite(same), np.isfinite(on_depth)) and check < 1e-5, check
    depths = {"bright wall, scattering off (render)": f_off.depth.astype(np.float64),
              f"bright wall, scattering on, preset strength {preset_strength} (render)": on_depth}
    for k in (0.05, 0.1, 0.2):
        depths[f"bright wall, Airy strength {k} (post-processed)"] = rescatter(f_off, on_sensor, k)
    depths["bright wall, Airy strength 0.1, radius 6 px (post-processed)"] = rescatter(f_off, on_sensor, 0.1,
                                                                                       radius_px=6.0)
    depths["dark wall ρ 0.05, scattering off (render)"] = f_dark.depth.astype(np.float64)
    depths[f"dark wall ρ 0.05, scattering on, preset strength {preset_strength} (post-processed)"] = \
        rescatter(f_dark, on_sensor, preset_strength)
    sixteen = tofcore.Modulation(kind="cw_square", frequencies_hz=(16e6,), phase_steps=(3,), exposure_s=(4e-3,))
    one_f = on_sensor.replace(**{"range_m": [0.5, 4.5]})
    depths["bright wall, scattering off, 16 MHz raw images only"] = rescatter(f_off, one_f, 0.0, sixteen, slice(3, 6))
    depths[f"bright wall, scattering on ({preset_strength}), 16 MHz raw images only"] = \
        rescatter(f_off, one_f, preset_strength, sixteen, slice(3, 6))
    depths["bright wall, Airy 0.1, radius 6 px, 16 MHz raw images only"] = \
        rescatter(f_off, one_f, 0.1, sixteen, slice(3, 6), radius_px=6.0)
    results = {}
    for label, d in depths.items():
        results[label] = r = counts(d, gt, zone, lit_wall, near)
        ring = r["lit_wall_mean_error_mm_by_ring_px"]
        print(f"{label:72s} flying X=2/5 cm {r['flying_pixels_in_edge_zone']['X = 2 cm']:4d} "
              f"{r['flying_pixels_in_edge_zone']['X = 5 cm']:4d}  invalid in edge zone "
              f"{r['invalid_pixels_in_edge_zone']:4d}/{r['edge_zone_pixels']}  lit wall error 1/2/3 px from box "
              f"{ring[1]:.1f} / {ring[2]:.1f} / {ring[3]:.1f} mm")

    fig, ax = C.plt.subplots(1, 3, figsize=(16, 4.8))
    show = [("bright wall, scattering off (render)", "C0", "scattering off"),
            (f"bright wall, scattering on, preset strength {preset_strength} (render)", "C3", "scattering on (preset)"),
            ("bright wall, Airy strength 0.1, radius 6 px (post-processed)", "C1", "Airy 0.1, radius 6 px"),
            ("bright wall, scattering on (0.02), 16 MHz raw images only", "C2", "scattering on, 16 MHz only"),
            ("bright wall, Airy 0.1, radius 6 px, 16 MHz raw images only", "C4", "Airy 0.1, r 6 px, 16 MHz only")]
    for a, (c0, c1, title) in zip(ax[:2], ((left - 10, left + 6, "left box edge"),
                                          (right - 5, right + 11, "right box edge (LED shadow beside it)"))):
        u = np.arange(c0, c1)
        a.plot(u, gt[row, c0:c1], "k--", lw=1, label="ground truth")
        for key, colour, short in show:
            a.plot(u, depths[key][row, c0:c1], "o-", color=colour, ms=3.5, lw=0.8, label=short)
        a.axhspan(Z_FG + 0.05, Z_BG - 0.05, color="0.92", zorder=0, label="flying (X = 5 cm)")
        a.set_xlabel(f"pixel column (row {row}); gaps: invalid")
        a.set_ylabel("depth z (m)")
        a.set_title(title)
        a.legend(fontsize=7)
    labels = list(results)
    short = ["off", f"on {preset_strength}", "0.05", "0.1", "0.2", "0.1, r 6 px", "dark, off",
             f"dark, on {preset_strength}", "16 MHz, off", f"16 MHz, on {preset_strength}", "16 MHz, 0.1, r 6 px"]
    y = np.arange(len(labels))
    ax[2].barh(y - 0.2, [results[k]["flying_pixels_in_edge_zone"]["X = 5 cm"] for k in labels], 0.4,
               label="flying (X = 5 cm)")
    ax[2].barh(y + 0.2, [results[k]["invalid_pixels_in_edge_zone"] for k in labels], 0.4, label="invalid")
    ax[2].set_xlabel(f"pixels within {EDGE_PX} px of the box outline ({int(zone.sum())} in all)")
    ax[2].set_yticks(y, short, fontsize=8)
    ax[2].invert_yaxis()
    ax[2].set_title("flying vs invalidated edge pixels")
    ax[2].legend(fontsize=7)
    rt = [C.runtime(f, k) for k, f in frames.items()]
    fig.suptitle(f"Flying pixels at the box edge, Kinect v2 512×424, noise off, {args.spp} spp, max path "
                 f"{args.max_depth} ({' + '.join(str(round(r['seconds'])) for r in rt)} s)")
    fig.tight_layout()
    numbers = {"experiment": "SPEC §6.5 / thesis §6.2: flying pixels with and without lens scattering",
               "scene": "box_on_wall (box front z 1.2 m ρ 0.5, wall z 2.0 m ρ 0.9; dark variant wall ρ 0.05)",
               "sensor": "kinect_v2 512×424, noise none; Airy PSF radius 2 px, negative ring 0.05",
               "foreground_background_z_m": [Z_FG, Z_BG], "middle_row": row, "box_columns": [left, right],
               "post_processing_reproduces_render_max_abs_m": check,
               "results": results, "runtime": rt}
    print(C.runtime_line(rt))
    C.write_outputs(args.out, "flying_pixels", fig, numbers, started)


if __name__ == "__main__":
    main()
