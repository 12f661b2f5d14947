"""The render-error estimate with unwrap flips counted apart (issue 34, item 2).

A render at ``--spp`` against a converged reference at ``--ref-spp`` with a seed apart, sensor noise and lens
scattering off (the render's own error only), at ``--scale`` of the preset's resolution. Per render:

* ``est``: the RMS of ``frame.render_error`` over the pixels valid in both frames whose replicates agree on
  the unwrapping (``frame.unwrap_flip`` = 0);
* ``actual``: the RMS difference of the output depth against the reference over the same pixels, less the
  pixels whose depth differs from the reference by more than a flip (:data:`tofcore.render.FLIP_FRACTION` of the
  smallest ambiguity distance: a wrong wrap), the reference's own estimated variance subtracted;
* ``flips``: those wrong wraps, counted apart, and how many of them the frame flagged.

    .venv/bin/python bench/bench_flips.py --preset kinect_v2 --scene room --spp 16 --ref-spp 1024 --seeds 3
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

import tofcore
from tofcore.render import FLIP_FRACTION

AMBIENT = {"xtion2": 0.05}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="kinect_v2")
    ap.add_argument("--scene", default="room")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--max-depth", type=int, default=4)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    sensor = tofcore.load_preset(args.preset).scaled(args.scale).replace(
        **{"noise.model": "none", "scattering.model": "none"})
    scene = tofcore.demo_scene(args.scene)
    ambient = tofcore.Ambient(radiance_w_m2_sr=AMBIENT[args.preset]) if args.preset in AMBIENT else None
    t0 = time.perf_counter()
    ref = tofcore.render(scene, sensor, spp=args.ref_spp, seed=10_000, max_depth=args.max_depth, ambient=ambient)
    ref_s = time.perf_counter() - t0
    flip_m = FLIP_FRACTION * float(np.min(sensor.modulation.ambiguity_distances_m())) if sensor.modulation.is_cw \
        else np.inf
    rows = []
    for seed in range(args.seeds):
        t0 = time.perf_counter()
        f = tofcore.render(scene, sensor, spp=args.spp, seed=seed, max_depth=args.max_depth, ambient=ambient)
        secs = time.perf_counter() - t0
        both = f.valid & ref.valid
        diff = (f.depth - ref.depth).astype(np.float64)
        flagged = f.unwrap_flip.astype(bool)
        wrong = both & (np.abs(diff) > flip_m)
        keep = both & ~flagged & ~wrong
        ref_var = float(np.nanmean(ref.render_error[keep].astype(np.float64) ** 2))
        actual = float(np.sqrt(max(np.mean(diff[keep] ** 2) - ref_var, 0.0)))
        actual_all = float(np.sqrt(max(np.mean(diff[both] ** 2) - ref_var, 0.0)))
        est = float(np.sqrt(np.nanmean(f.render_error[keep].astype(np.float64) ** 2)))
        row = {"seed": seed, "seconds": round(secs, 2), "valid_both": int(both.sum()), "est_mm": est * 1e3,
               "actual_mm": actual * 1e3, "est_over_actual": est / actual if actual else None,
               "actual_with_flips_mm": actual_all * 1e3, "wrong_wraps": int(wrong.sum()),
               "wrong_wraps_flagged": int((wrong & flagged).sum()), "flagged_valid": int((both & flagged).sum()),
               "flagged_share_log": f.stats["convergence"][-1]["unwrap_flip_share"],
               "est_log_mm": f.stats["convergence"][-1]["est_depth_error_m"] * 1e3,
               "wrong_wrap_sizes_m": sorted(np.round(np.abs(diff[wrong]), 3).tolist())}
        rows.append(row)
        print(json.dumps(row), flush=True)
    ratio = [r["est_over_actual"] for r in rows]
    summary = {"preset": args.preset, "scene": args.scene, "spp": args.spp, "ref_spp": args.ref_spp,
               "scale": args.scale, "pixels": int(ref.valid.size), "ref_seconds": round(ref_s, 1),
               "est_over_actual": ratio, "wrong_wraps": sum(r["wrong_wraps"] for r in rows),
               "wrong_wraps_flagged": sum(r["wrong_wraps_flagged"] for r in rows), "rows": rows}
    print(f"{args.preset} {args.scene}: est/actual {', '.join(f'{x:.2f}' for x in ratio)}; wrong wraps "
          f"{summary['wrong_wraps']} ({summary['wrong_wraps_flagged']} flagged) in {args.seeds} renders; "
          f"reference {ref_s:.0f} s")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(summary, fh, indent=1)


if __name__ == "__main__":
    main()
