"""Corner against surface roughness σ = 0, 0.25, 0.5, 0.75, 1.0 (η = 1.52): multipath error on the scan line.

Thesis §6.3.2 (Abbildung 6.9): for σ = 1.0 the multipath error is smallest and it grows for smoother
surfaces, "because rougher surfaces reflect more of the radiation back towards the source".

Five renders of the ``corner`` demo scene, identical except for the walls' roughness, with the Kinect v2
preset (noise and lens scattering off, full 512-pixel width, only a band of rows around the middle scan
line since nothing here needs the rest of the image). Multipath error = distance(max path length 16) −
distance(k = 1), radial, noise-free, from the same render. Also printed: the fraction of the returned LED
signal that is indirect (k ≥ 2) at the scan line, which is what the error follows.

    .venv/bin/python studies/corner_roughness.py --out out/studies      # ~1.5 min on 2 cores
"""

from __future__ import annotations

import time

import numpy as np

import _common as C
import tofcore

SIGMAS = (0.0, 0.25, 0.5, 0.75, 1.0)
BAND_ROWS = 16


def signal_shares(scene, sensor, pose, row: int, spp: int = 32) -> dict:
    """Direct and indirect LED radiance on the scan line and the mean extra path of the indirect light.

    A short extra trace (not part of the render above) with two "correlations": 1 and the path length
    L = c τ, so Σ w L / Σ w per bounce is the radiance-weighted mean path length of each bucket.
    """
    one = lambda tau: np.ones_like(tau)  # noqa: E731
    length = lambda tau: tau * tofcore.SPEED_OF_LIGHT_M_S  # noqa: E731
    tr = tofcore.trace(scene, sensor.camera, sensor.leds, world_from_sensor=pose,
                       correlations=[one, length], spp=spp, max_depth=16, seed=1)
    s = tr.signal_per_bounce()[:, row].astype(np.float64)               # (K, W)
    wl = tr.correlation_per_bounce()[:, 1, row].astype(np.float64)      # (K, W) Σ w L
    direct, indirect = s[0], s[1:].sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        extra = (wl[1:].sum(axis=0) / indirect - wl[0] / direct) / 2  # one-way metres, like a distance
    ok = np.isfinite(extra) & (direct > 0)
    return {"direct_radiance_scanline": float(np.mean(direct)),
            "indirect_radiance_scanline": float(np.mean(indirect)),
            "indirect_share_scanline": float(np.mean(indirect[ok] / (direct[ok] + indirect[ok]))),
            "indirect_extra_path_mm_scanline": float(np.mean(extra[ok]) * C.MM)}


def main() -> None:
    p = C.parser(__doc__, spp=256, max_depth=16)
    args = p.parse_args()
    started = time.perf_counter()
    cam, row = C.band_camera(tofcore.load_preset("kinect_v2").camera, BAND_ROWS)
    sensor = C.kinect(camera=cam)
    base = tofcore.demo_scene("corner")
    col = int(round(cam.cx))
    results, records, curves = {}, [], {}
    for sigma in SIGMAS:
        wall = tofcore.Material(name="wall", reflectance=0.8, roughness=sigma, ior=1.52)
        scene = C.with_materials(base, [wall])
        frame = tofcore.render(scene, sensor, spp=args.spp, max_depth=args.max_depth, seed=args.seed)
        per_k = frame.distance_per_k.astype(np.float64)
        mp = per_k[-1] - per_k[0]
        seen = np.isfinite(frame.gt_distance) & np.isfinite(mp)
        line = mp[row]
        profile = np.nanmean(mp, axis=0)  # the band's rows averaged: the scan line with 16× the samples
        curves[sigma] = profile
        share = signal_shares(scene, sensor, frame.world_from_sensor, row)
        results[sigma] = {
            "mean_multipath_error_mm_band": float(np.mean(mp[seen]) * C.MM),
            "rms_multipath_error_mm_band": C.rms(mp[seen]) * C.MM,
            "mean_multipath_error_mm_scanline": float(np.nanmean(line) * C.MM),
            "peak_multipath_error_mm_profile": float(np.nanmax(profile) * C.MM),
            "multipath_error_mm_profile_every_16th_px": profile[::16] * C.MM,
            "multipath_error_mm_at_edge_profile": float(profile[col] * C.MM),
            **share,
            "mean_direct_error_mm_scanline": float(np.nanmean(per_k[0, row] - frame.gt_distance[row]) * C.MM),
        }
        records.append(C.runtime(frame, f"σ = {sigma}"))
        print(f"σ = {sigma:4.2f}: mean multipath error {results[sigma]['mean_multipath_error_mm_band']:.2f} mm "
              f"(scan line {results[sigma]['mean_multipath_error_mm_scanline']:.2f} mm, "
              f"peak {results[sigma]['peak_multipath_error_mm_profile']:.2f} mm), direct {share['direct_radiance_scanline']:.4f}, "
              f"indirect {share['indirect_radiance_scanline']:.4f} W/m²/sr, indirect share {share['indirect_share_scanline']:.3f}, "
              f"extra path {share['indirect_extra_path_mm_scanline']:.0f} mm, {records[-1]['seconds']:.1f} s")

    # Is it the specular lobe? The same light budget with η = 1 (no Fresnel reflection: pure Oren–Nayar).
    no_fresnel = {}
    for sigma in (0.0, 1.0):
        scene = C.with_materials(base, [tofcore.Material(name="wall", reflectance=0.8, roughness=sigma, ior=1.0)])
        no_fresnel[sigma] = signal_shares(scene, sensor, tofcore.suggested_pose(base), row, spp=64)
        print(f"η = 1 (no specular), σ = {sigma}: indirect share {no_fresnel[sigma]['indirect_share_scanline']:.3f}")

    fig, ax = C.plt.subplots(1, 3, figsize=(16, 4.6), gridspec_kw={"width_ratios": [2.2, 1, 1]})
    colours = C.plt.cm.plasma(np.linspace(0, 0.85, len(SIGMAS)))
    u = np.arange(cam.width)
    for c, sigma in zip(colours, SIGMAS):
        ax[0].plot(u, curves[sigma] * C.MM, "-", color=c, lw=1, label=f"σ = {sigma}")
    ax[0].axvline(col, color="grey", lw=0.5, ls=":")
    ax[0].set_xlabel("pixel column (middle scan line, 512 px)")
    ax[0].set_ylabel("multipath error d_16 − d_1 (mm)")
    ax[0].set_title(f"multipath error along the middle scan line (mean of the {BAND_ROWS} rows around it)")
    ax[0].legend(fontsize=8)
    s = np.array(SIGMAS)
    ax[1].plot(s, [results[x]["mean_multipath_error_mm_band"] for x in SIGMAS], "o-", label="mean (band)")
    ax[1].plot(s, [results[x]["peak_multipath_error_mm_profile"] for x in SIGMAS], "s--", label="peak of the profile")
    ax[1].set_xlabel("roughness σ (rad)")
    ax[1].set_ylabel("mm")
    ax[1].set_title("multipath error against roughness")
    ax[1].grid(alpha=0.3)
    ax[1].legend(fontsize=8)
    for key, label, mark in (("direct_radiance_scanline", "direct (k = 1)", "o-"),
                             ("indirect_radiance_scanline", "indirect (k ≥ 2)", "s--")):
        v = np.array([results[x][key] for x in SIGMAS])
        ax[2].plot(s, v / v[0], mark, label=label)
    ax[2].set_xlabel("roughness σ (rad)")
    ax[2].set_ylabel("LED radiance at the lens, relative to σ = 0")
    ax[2].set_title("direct and indirect light (scan line)")
    ax[2].grid(alpha=0.3)
    ax[2].legend(fontsize=8)
    total = sum(r["seconds"] for r in records)
    fig.suptitle(f"Corner η = 1.52, Kinect v2 (noise, scattering off), 512×{BAND_ROWS} band, "
                 f"{args.spp} spp, max path 16: 5 renders in {total:.0f} s")
    fig.tight_layout()
    numbers = {
        "experiment": "SPEC §6.3 / thesis §6.3.2: corner against roughness",
        "scene": "corner geometry, walls reflectance 0.8, η = 1.52, σ varied",
        "sensor": "kinect_v2, noise none, scattering none", "band": [cam.width, cam.height], "scan_row_in_band": row,
        "per_sigma": results, "eta_1_no_specular_signal_shares": no_fresnel, "runtime": records,
    }
    print(C.runtime_line(records))
    C.write_outputs(args.out, "corner_roughness", fig, numbers, started)


if __name__ == "__main__":
    main()
