"""Corner: depth along the middle scan line for max path length 1, 2, 3, 4, 5 and 16, from one render.

Thesis §6.3.1 (Abbildung 6.8): two perpendicular walls, σ = 0.5, η = 1.52; the multipath error grows with
the maximum path length and does not change any more beyond 5 (Meister et al. 2013: 8).

One render of the ``corner`` demo scene with the Kinect v2 preset (noise and lens scattering off) at
max_depth 16; ``frame.distance_per_k[k-1]`` is the decoded distance with bounces ≤ k, all from the same
paths. The multipath error of path length k is distance_k − distance_1 (radial, noise-free).

    .venv/bin/python studies/corner_path_length.py --out out/studies      # ~1.5 min on 2 cores
"""

from __future__ import annotations

import time

import numpy as np

import _common as C
import tofcore

KS = (1, 2, 3, 4, 5, 16)


def main() -> None:
    args = C.parser(__doc__, spp=256, max_depth=16, scale=0.5).parse_args()
    started = time.perf_counter()
    base = tofcore.load_preset("kinect_v2").camera
    cam = C.scaled_camera(base, args.scale)
    sensor = C.kinect(camera=cam)
    scene = tofcore.demo_scene("corner")
    frame = tofcore.render(scene, sensor, spp=args.spp, max_depth=args.max_depth, seed=args.seed)
    K = frame.distance_per_k.shape[0]
    row = int(round(cam.cy))
    per_k = frame.distance_per_k.astype(np.float64)
    seen = np.isfinite(frame.gt_distance) & np.isfinite(per_k).all(axis=0)
    mp = per_k - per_k[0]                                     # multipath error per k, (K, H, W)
    rms_image = [C.rms(mp[k][seen]) for k in range(K)]
    mean_image = [float(np.mean(mp[k][seen])) for k in range(K)]
    rms_line = [C.rms(mp[k, row][seen[row]]) for k in range(K)]
    # Convergence in k: the change from k to the deepest bucket, RMS over the image.
    to_last = [C.rms((per_k[k] - per_k[K - 1])[seen]) for k in range(K)]
    col = int(round(cam.cx))                                  # the corner's edge
    err_direct = (per_k[0] - frame.gt_distance)[seen]

    fig, ax = C.plt.subplots(1, 3, figsize=(15, 4.6))
    x_gt, z_gt = C.x_z(frame, frame.gt_distance.astype(np.float64), row)
    ax[0].plot(x_gt, z_gt, "k-", lw=2.5, label="ground truth (first hit)")
    colours = C.plt.cm.viridis(np.linspace(0, 0.9, len(KS)))
    for c, k in zip(colours, KS):
        if k > K:
            continue
        x, z = C.x_z(frame, per_k[k - 1], row)
        ax[0].plot(x, z, "-", color=c, lw=1, label=f"max path length {k}")
    ax[0].set_ylim(0.3, 1.55)
    inset = ax[0].inset_axes([0.62, 0.04, 0.35, 0.36])
    for line in ax[0].get_lines():
        inset.plot(*line.get_data(), "-", color=line.get_color(), lw=line.get_linewidth())
    inset.set_xlim(0.09, 0.15)
    inset.set_ylim(1.33, 1.43)
    inset.set_title("zoom", fontsize=7)
    inset.tick_params(labelsize=6)
    ax[0].indicate_inset_zoom(inset, edgecolor="0.4")
    ax[0].set_xlabel("x (m, sensor frame)")
    ax[0].set_ylabel("z (m, along the optical axis)")
    ax[0].set_title("top-down view of the middle scan line")
    ax[0].legend(fontsize=7, loc="lower left", ncol=1)
    ax[0].set_aspect("auto")
    u = np.arange(cam.width)
    for c, k in zip(colours, KS):
        if k > K:
            continue
        ax[1].plot(u, mp[k - 1, row] * C.MM, "-", color=c, lw=1, label=f"k ≤ {k}")
    ax[1].axvline(col, color="grey", lw=0.5, ls=":")
    ax[1].set_xlabel("pixel column (middle scan line)")
    ax[1].set_ylabel("multipath error d_k − d_1 (mm)")
    ax[1].set_title("multipath error along the scan line")
    ax[1].legend(fontsize=8)
    kk = np.arange(1, K + 1)
    ax[2].plot(kk, np.array(rms_image) * C.MM, "o-", label="RMS over the image")
    ax[2].plot(kk, np.array(rms_line) * C.MM, "s--", label="RMS over the scan line")
    tw = ax[2].twinx()
    tw.semilogy(kk[:-1], np.array(to_last[:-1]) * C.MM, "^:", color="C2", label=f"RMS d_k − d_{K} (image, right axis)")
    tw.set_ylabel(f"RMS d_k − d_{K} (mm, log)", color="C2")
    ax[2].set_xlabel("max path length k")
    ax[2].set_ylabel("RMS multipath error d_k − d_1 (mm)")
    ax[2].set_title("multipath error against path length")
    h1, l1 = ax[2].get_legend_handles_labels()
    h2, l2 = tw.get_legend_handles_labels()
    ax[2].legend(h1 + h2, l1 + l2, fontsize=8, loc="center right")
    ax[2].grid(alpha=0.3)
    rt = C.runtime(frame, f"corner {cam.width}×{cam.height}")
    fig.suptitle(f"Corner σ = 0.5, η = 1.52, Kinect v2 (noise, scattering off), one render: "
                 f"{rt['seconds']:.0f} s, {rt['spp']} spp, est. MC error {rt['est_depth_error_mm']:.2f} mm")
    fig.tight_layout()

    converged_k = next((k + 1 for k in range(K) if to_last[k] < 0.1e-3), None)
    numbers = {
        "experiment": "SPEC §6.2 / thesis §6.3.1: corner, depth against max path length, one render",
        "scene": "corner (σ = 0.5, η = 1.52, reflectance 0.8)", "sensor": "kinect_v2, noise none, scattering none",
        "resolution": [cam.width, cam.height], "middle_row": row,
        "rms_multipath_error_mm_image": {k: rms_image[k - 1] * C.MM for k in kk},
        "mean_multipath_error_mm_image": {k: mean_image[k - 1] * C.MM for k in kk},
        "rms_multipath_error_mm_scanline": {k: rms_line[k - 1] * C.MM for k in kk},
        "rms_change_to_k16_mm_image": {k: to_last[k - 1] * C.MM for k in kk},
        "first_k_within_0.1mm_of_k16": converged_k,
        "multipath_error_at_edge_column_mm": {k: float(mp[k - 1, row, col] * C.MM) for k in kk},
        "max_multipath_error_scanline_mm": {k: float(np.nanmax(mp[k - 1, row]) * C.MM) for k in kk},
        "direct_minus_ground_truth_rms_mm": C.rms(err_direct) * C.MM,
        "runtime": [rt],
    }
    print("k  RMS(d_k - d_1) image mm   scan line mm   RMS(d_k - d_16) mm")
    for k in kk:
        print(f"{k:2d} {rms_image[k - 1] * C.MM:10.3f} {rms_line[k - 1] * C.MM:14.3f} {to_last[k - 1] * C.MM:14.3f}")
    print(C.runtime_line([rt]))
    C.write_outputs(args.out, "corner_path_length", fig, numbers, started)


if __name__ == "__main__":
    main()
