"""The estimator's ablation and the honesty of its error estimate (issue 10, items 4 and 7).

For each preset × scene: a converged reference (``--ref-spp``, seed apart), then renders at each ``--spp``
with several seeds for each variant

* ``independent``  — plain counter-based uniforms, every pixel the same spp (the estimator before issue 10),
* ``sobol``        — randomized QMC (Owen-scrambled Sobol' replicates, :mod:`tofcore.tracer.qmc`),
* ``sobol+adaptive`` — the same with adaptive sampling after a 16-spp pilot (:mod:`tofcore.tracer.adaptive`),
* ``…+light`` — with light vertices and MIS (:mod:`tofcore.tracer.light_paths`),

all with sensor noise off (the render's own noise only; lens scattering stays as the preset has it).
Per render: trace seconds, the **actual** RMS error of the output depth against the reference over the
pixels valid in both (the reference's own estimated variance subtracted, as in
``studies/crosscheck/error_vs_time.py``), the **estimated** RMS error (``frame.render_error`` over the
same pixels), their ratio, and the share of pixels invalid for "unwrapping failed" beyond the reference's.

    .venv/bin/python bench/bench_estimator.py --scale 0.25 --spp 16 64 --seeds 3 --json out/bench_estimator.json

Writes a JSON of every render and prints Markdown tables (docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import time
from pathlib import Path

import numpy as np

import tofcore
from tofcore.output.frame import Reason

VARIANTS = {"independent": dict(sampler="independent", adaptive=False, light_paths=False),
            "sobol": dict(sampler="sobol", adaptive=False, light_paths=False),
            "sobol+adaptive": dict(sampler="sobol", adaptive=True, light_paths=False),
            "sobol+light": dict(sampler="sobol", adaptive=False, light_paths=True),
            "sobol+adaptive+light": dict(sampler="sobol", adaptive=True, light_paths=True)}
AMBIENT = {"xtion2": 0.05}  # W m^-2 sr^-1: the pulsed sensor is judged under ambient light (SPEC §6.4)


def sensor_for(preset: str, scale: float):
    sensor = tofcore.load_preset(preset)
    cam = sensor.camera
    w, h = max(8, round(cam.width * scale)), max(8, round(cam.height * scale))
    small = dataclasses.replace(cam, width=w, height=h, fx=cam.fx * w / cam.width, fy=cam.fy * h / cam.height,
                                cx=cam.cx * w / cam.width, cy=cam.cy * h / cam.height)
    return sensor.replace(camera=small, **{"noise.model": "none"})


DEVICE = "cpu"


def render(scene, sensor, preset, spp, seed, variant, max_depth):
    ambient = tofcore.Ambient(radiance_w_m2_sr=AMBIENT[preset]) if preset in AMBIENT else None
    t0 = time.perf_counter()
    frame = tofcore.render(scene, sensor, spp=spp, seed=seed, max_depth=max_depth, ambient=ambient,
                           device=DEVICE, **VARIANTS[variant])
    return frame, time.perf_counter() - t0


def compare(frame, ref) -> dict:
    both = frame.valid & ref.valid
    diff = (frame.depth - ref.depth)[both].astype(np.float64)
    mse = float(np.mean(diff**2))
    ref_var = float(np.nanmean(ref.render_error[both].astype(np.float64) ** 2))
    actual = float(np.sqrt(max(mse - ref_var, 0.0)))
    est = float(np.sqrt(np.nanmean(frame.render_error[both].astype(np.float64) ** 2)))
    unwrap = float(np.mean(frame.reason == Reason.UNWRAPPING_FAILED))
    ref_unwrap = float(np.mean(ref.reason == Reason.UNWRAPPING_FAILED))
    return {"actual_rms_m": actual, "actual_rms_raw_m": float(np.sqrt(mse)), "est_rms_m": est,
            "est_over_actual": est / actual if actual > 0 else None,
            "unwrap_failed": unwrap, "unwrap_failed_ref": ref_unwrap, "valid_both": float(both.mean())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", nargs="+", default=["kinect_v2", "o3d303", "xtion2"])
    ap.add_argument("--scenes", nargs="+", default=["corner", "box_on_wall", "room"])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS))
    ap.add_argument("--scale", type=float, default=0.25, help="resolution factor of the presets' cameras")
    ap.add_argument("--spp", type=int, nargs="+", default=[16, 64])
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--max-depth", type=int, default=5)
    ap.add_argument("--json", type=Path, default=Path("out/bench_estimator.json"))
    ap.add_argument("--markdown", type=Path, help="also write the table to this file")
    ap.add_argument("--device", choices=("cpu", "gpu"), default="cpu")
    args = ap.parse_args()
    global DEVICE
    DEVICE = args.device
    rows = []
    for preset in args.presets:
        sensor = sensor_for(preset, args.scale)
        for name in args.scenes:
            scene = tofcore.demo_scene(name)
            ref, ref_s = render(scene, sensor, preset, args.ref_spp, 999_999, "sobol+light", args.max_depth)
            print(f"{preset} {name}: reference {args.ref_spp} spp in {ref_s:.0f} s, est "
                  f"{np.sqrt(np.nanmean(ref.render_error**2)) * 1e3:.2f} mm", flush=True)
            for variant in args.variants:
                for spp in args.spp:
                    for seed in range(args.seeds):
                        frame, seconds = render(scene, sensor, preset, spp, seed, variant, args.max_depth)
                        row = {"preset": preset, "scene": name, "variant": variant, "spp": spp, "seed": seed,
                               "seconds": seconds, **compare(frame, ref)}
                        rows.append(row)
                        print(f"  {variant:15s} {spp:5d} spp seed {seed}: {seconds:6.1f} s  actual "
                              f"{row['actual_rms_m'] * 1e3:7.2f} mm  est {row['est_rms_m'] * 1e3:7.2f} mm  "
                              f"unwrap {row['unwrap_failed'] * 100:.2f} % (ref {row['unwrap_failed_ref'] * 100:.2f})",
                              flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                     "machine": platform.platform(), "rows": rows}, indent=1))
    print(tables(rows))
    if args.markdown:
        args.markdown.write_text(tables(rows) + "\n")
    return 0


def tables(rows: list[dict]) -> str:
    """Markdown: per preset/scene/spp the variants' mean actual error (variance ratio to independent) and
    the estimate's accuracy (mean est/actual)."""
    out = ["| preset | scene | spp | variant | s | actual RMS mm | MSE gain vs independent | est/actual | "
           "unwrap failed % |", "|---|---|---|---|---|---|---|---|---|"]
    keys = sorted({(r["preset"], r["scene"], r["spp"]) for r in rows}, key=lambda k: (k[0], k[1], k[2]))
    for preset, scene, spp in keys:
        group = [r for r in rows if (r["preset"], r["scene"], r["spp"]) == (preset, scene, spp)]
        base = [r for r in group if r["variant"] == "independent"]
        base_mse = np.mean([r["actual_rms_m"] ** 2 for r in base]) if base else None
        for variant in VARIANTS:
            rs = [r for r in group if r["variant"] == variant]
            if not rs:
                continue
            mse = np.mean([r["actual_rms_m"] ** 2 for r in rs])
            ratio = [r["est_over_actual"] for r in rs if r["est_over_actual"]]
            gain = f"{base_mse / mse:.2f}×" if base_mse and mse > 0 else "–"
            out.append(f"| {preset} | {scene} | {spp} | {variant} | {np.mean([r['seconds'] for r in rs]):.1f} | "
                       f"{np.sqrt(mse) * 1e3:.2f} | {gain} | {np.mean(ratio):.2f} | "
                       f"{np.mean([r['unwrap_failed'] for r in rs]) * 100:.2f} |")
    return "\n".join(out)


if __name__ == "__main__":
    raise SystemExit(main())
