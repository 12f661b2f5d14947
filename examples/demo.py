"""Render the demo: a box in front of a bright wall, seen by a Kinect-v2-like sensor.

Writes PNG previews and a JSON summary to ``--out``:

* ``distance.png``    ground-truth radial distance (first hit through each pixel centre)
* ``direct.png``      direct (k = 1) LED radiance at the lens, log scale
* ``multipath.png``   share of the signal that arrived after two or more bounces
* ``mpi_error.png``   depth error caused by multipath for a 80 MHz sine sensor (full − direct only), mm
* ``summary.json``    settings, rays, time, rays/s

Usage: ``python examples/demo.py --out out/demo [--spp 16] [--max-depth 4]``
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

import tofcore

F_MOD_HZ = 80e6


def colorize(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """8-bit BGR image of ``values`` with OpenCV's turbo colour map; NaN → black."""
    import cv2

    scaled = np.clip((values - lo) / (hi - lo), 0, 1)
    img = cv2.applyColorMap(np.nan_to_num(scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    img[~np.isfinite(values)] = 0
    return img


def write_png(path: Path, image: np.ndarray) -> None:
    import cv2

    tmp = path.with_name(f".{path.name}.tmp.png")
    if not cv2.imwrite(str(tmp), image):
        raise OSError(f"{path}: could not write PNG")
    os.replace(tmp, path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default: out/demo)")
    parser.add_argument("--spp", type=int, default=16, help="samples per pixel (default: 16)")
    parser.add_argument("--max-depth", type=int, default=4, help="surface vertices per path (default: 4)")
    parser.add_argument("--scene", default="box_on_wall", choices=tofcore.demo.NAMES, help="demo scene")
    args = parser.parse_args(argv)

    scene = tofcore.demo_scene(args.scene)
    camera = tofcore.Camera.from_fov(512, 424, 70.6, 60.0)
    leds = [tofcore.LED(position_m=(0.025, 0.0, 0.0), intensity_w_sr=1.0)]
    omega = 2 * np.pi * F_MOD_HZ
    correlations = [lambda tau: np.cos(omega * tau), lambda tau: np.sin(omega * tau)]
    print(f"scene {args.scene}: {scene.triangle_count} triangles; 512x424, {args.spp} spp, max_depth {args.max_depth}")
    start = time.perf_counter()
    for t in tofcore.trace_progressive(scene, camera, leds, world_from_sensor=tofcore.suggested_pose(scene),
                                       correlations=correlations, spp=args.spp, max_depth=args.max_depth, seed=0):
        print(f"  pass {t.stats.passes}: {int(t.sample_count[0])} spp, {t.stats.seconds:.1f} s", flush=True)
    elapsed = time.perf_counter() - start

    def distance_from_phasor(re, im):
        phase = np.mod(np.arctan2(im, re), 2 * np.pi)
        return phase * tofcore.SPEED_OF_LIGHT_M_S / (4 * np.pi * F_MOD_HZ)

    # The phasor's phase is the round trip: cos/sin of ω L/c, so the phase is ω L / c.
    full = distance_from_phasor(*t.correlation())
    direct = distance_from_phasor(*t.correlation(max_k=1))
    mpi_mm = (full - direct) * 1000.0
    signal, direct_signal = t.signal(), t.signal(max_k=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        multipath_share = 1.0 - direct_signal / signal

    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    dist = t.first_hit.distance_m
    write_png(out / "distance.png", colorize(dist, np.nanmin(dist), np.nanmax(dist)))
    log_direct = np.log10(np.where(direct_signal > 0, direct_signal, np.nan))
    write_png(out / "direct.png", colorize(log_direct, np.nanpercentile(log_direct, 1), np.nanmax(log_direct)))
    write_png(out / "multipath.png", colorize(multipath_share, 0.0, 0.5))
    write_png(out / "mpi_error.png", colorize(mpi_mm, 0.0, max(1.0, np.nanpercentile(mpi_mm, 99))))
    summary = {
        "scene": args.scene, "triangles": scene.triangle_count, "resolution": [512, 424], "spp": args.spp,
        "max_depth": args.max_depth, "seconds": elapsed, **t.stats.as_dict(),
        "median_multipath_error_mm": float(np.nanmedian(mpi_mm)),
        "median_multipath_share": float(np.nanmedian(multipath_share)),
    }
    tmp = out / ".summary.json.tmp"
    tmp.write_text(json.dumps(summary, indent=2))
    os.replace(tmp, out / "summary.json")
    print(f"done in {elapsed:.1f} s: {t.stats.rays / elapsed / 1e6:.2f} M rays/s; "
          f"median multipath error {summary['median_multipath_error_mm']:.1f} mm; wrote {out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
