"""Preview denoising: its error on flat regions and its bias at depth edges, against a converged reference.

The demo room (Kinect v2 preset, sensor noise off, render noise only) at a preview's resolution
(``--scale`` 0.25: 128 × 106): a reference of ``--ref-spp`` samples per pixel, then previews of ``--spp``
samples (the add-on's live-preview default, 8) with ``--seeds`` seeds, each with and without the
preview filter (:mod:`tofcore.sensor.denoise`). Pixels are split by the reference depth: **edge**
pixels lie within the filter's radius of a depth step larger than ``--step`` (5 cm) between
neighbours, **flat** pixels are the other valid ones. Printed per region: the RMS error against the
reference (all seeds), the RMS over pixels of the error averaged over the seeds (the seeds' noise
averages down by √seeds), and from the two the systematic part — the bias the filter adds (and the
reference's own noise, 0.5 mm at 512 spp).
Also the filter's time at 128 × 106 and 512 × 424.

    .venv/bin/python studies/preview_denoise.py --out out/studies

Writes ``<out>/preview_denoise.json`` and ``<out>/preview_denoise.png``; the reference is kept as
``<out>/preview_denoise_reference.npy`` (reused when its settings match).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

import tofcore
from _common import MM, kinect, parser, runtime, scaled_camera, write_outputs
from tofcore.sensor.denoise import RADIUS_PX, preview_denoise


def regions(reference: np.ndarray, step_m: float, radius_px: int) -> tuple[np.ndarray, np.ndarray]:
    """(flat, edge) masks: edge = valid pixels within ``radius_px`` of a neighbour pair differing by > step_m."""
    valid = np.isfinite(reference)
    filled = np.where(valid, reference, 0.0)
    jump = np.zeros(reference.shape, bool)
    for axis in (0, 1):
        diff = np.abs(np.diff(filled, axis=axis)) > step_m
        both = np.diff(valid.astype(np.int8), axis=axis) == 0
        pair = diff & both & np.delete(valid, 0, axis=axis)
        lead = [(0, 1) if a == axis else (0, 0) for a in (0, 1)]
        trail = [(1, 0) if a == axis else (0, 0) for a in (0, 1)]
        jump |= np.pad(pair, lead) | np.pad(pair, trail)
    near = np.zeros_like(jump)
    h, w = jump.shape
    padded = np.pad(jump, radius_px)
    for dy in range(2 * radius_px + 1):
        for dx in range(2 * radius_px + 1):
            near |= padded[dy:dy + h, dx:dx + w]
    return valid & ~near, valid & near


def _errors(errors: np.ndarray, pixels: int) -> dict:
    """RMS error, RMS of the seed-mean error, and the systematic part: with n seeds the mean's square is
    s² + v/n and the RMS's square s² + v (v the noise variance), so s² = (n·mean² − rms²)/(n − 1)."""
    n = errors.shape[0]
    rms, mean = _rms(errors), _rms(errors.mean(axis=0))
    systematic = np.sqrt(max(0.0, (n * mean**2 - rms**2) / (n - 1))) if n > 1 else float("nan")
    return {"rms_mm": rms * MM, "bias_rms_mm": mean * MM, "systematic_mm": systematic * MM, "pixels": int(pixels)}


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.nanmean(np.square(x))))


def filter_seconds(shape: tuple[int, int], repeats: int = 5) -> float:
    """Median seconds of one :func:`preview_denoise` call on an image of ``shape`` (a noisy slope)."""
    rng = np.random.default_rng(0)
    h, w = shape
    depth = 2.0 + 0.002 * np.arange(w)[None, :] + rng.normal(0.0, 0.01, (h, w))
    amplitude = 300.0 + rng.normal(0.0, 10.0, (h, w))
    sigma = np.full((h, w), 0.01)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        preview_denoise(depth.astype(np.float32), amplitude.astype(np.float32), sigma.astype(np.float32))
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> None:
    p = parser(__doc__, spp=8, max_depth=5, scale=0.25)
    p.add_argument("--ref-spp", type=int, default=1024, help="samples per pixel of the reference (default 1024)")
    p.add_argument("--seeds", type=int, default=4, help="previews per setting (default 4)")
    p.add_argument("--step", type=float, default=0.05, help="depth step of an edge, m (default 0.05)")
    args = p.parse_args()
    started = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sensor = kinect(camera=scaled_camera(tofcore.load_preset("kinect_v2").camera, args.scale))
    scene = tofcore.demo_scene("room")

    ref_file = out / "preview_denoise_reference.npy"
    key = f"room kinect_v2 scale {args.scale} ref_spp {args.ref_spp} max_depth {args.max_depth} seed 1000"
    meta_file = ref_file.with_suffix(".json")
    if ref_file.exists() and meta_file.exists() and json.loads(meta_file.read_text()).get("key") == key:
        reference = np.load(ref_file)
        ref_record = json.loads(meta_file.read_text())["record"]
    else:
        frame = tofcore.render(scene, sensor, spp=args.ref_spp, max_depth=args.max_depth, seed=1000)
        reference = frame.depth.astype(np.float64)
        ref_record = runtime(frame, "reference")
        np.save(ref_file, reference)
        meta_file.write_text(json.dumps({"key": key, "record": ref_record}))
    flat, edge = regions(reference, args.step, RADIUS_PX)

    errors = {"plain": [], "denoised": []}
    records, last = [], None
    for seed in range(args.seeds):
        frame = tofcore.render(scene, sensor, spp=args.spp, max_depth=args.max_depth, seed=args.seed + seed)
        records.append(runtime(frame, f"preview seed {args.seed + seed}"))
        smooth = preview_denoise(frame.depth, frame.amplitude, frame.render_error)
        errors["plain"].append(frame.depth - reference)
        errors["denoised"].append(smooth - reference)
        last = (frame.depth, smooth)
    rows = {}
    for name, errs in errors.items():
        stack = np.stack(errs)
        mean = stack.mean(axis=0)
        rows[name] = {region: _errors(stack[:, mask], mask.sum()) for region, mask in (("flat", flat), ("edge", edge))}
    timing = {f"{w}x{h}": filter_seconds((h, w)) for w, h in ((sensor.camera.width, sensor.camera.height),
                                                             (512, 424))}
    h, w = reference.shape
    print(f"demo room, Kinect v2 (sensor noise off), {w} x {h}, max path length {args.max_depth}; reference "
          f"{args.ref_spp} spp (est. render noise {ref_record['est_depth_error_mm']} mm RMS, "
          f"{ref_record['seconds']:.0f} s); previews {args.spp} spp x {args.seeds} seeds")
    print(f"edges: within {RADIUS_PX} px of a > {args.step * 100:.0f} cm step "
          f"({rows['plain']['edge']['pixels']} px); flat: the other valid pixels ({rows['plain']['flat']['pixels']} px)")
    print("| preview | flat RMS mm | flat seed-mean RMS mm | flat systematic mm | edge RMS mm | "
          "edge seed-mean RMS mm | edge systematic mm |")
    print("|---|---|---|---|---|---|---|")
    for name in ("plain", "denoised"):
        f, e = rows[name]["flat"], rows[name]["edge"]
        print(f"| {name} | {f['rms_mm']:.2f} | {f['bias_rms_mm']:.2f} | {f['systematic_mm']:.2f} | "
              f"{e['rms_mm']:.2f} | {e['bias_rms_mm']:.2f} | {e['systematic_mm']:.2f} |")
    print("filter time (median of 5): " + ", ".join(f"{k}: {1e3 * v:.1f} ms" for k, v in timing.items()))
    numbers = {"settings": vars(args), "reference": ref_record, "previews": records, "errors": rows,
               "filter_seconds": timing}
    write_outputs(out, "preview_denoise", _figure(reference, *last, edge), numbers, started)


def _figure(reference, plain, smooth, edge):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(16, 3.4))
    lo, hi = np.nanpercentile(reference, [2, 98])
    for ax, image, title in zip(axes[:3], (reference, plain, smooth), ("reference", "preview", "preview, denoised")):
        ax.imshow(image, vmin=lo, vmax=hi, cmap="viridis")
        ax.set_title(title)
    axes[3].imshow(np.abs(smooth - reference) * MM, vmin=0, vmax=30, cmap="magma")
    axes[3].contour(edge, levels=[0.5], colors="cyan", linewidths=0.5)
    axes[3].set_title("|denoised - reference| mm (edges outlined)")
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    return fig


if __name__ == "__main__":
    main()
