"""Render the demo: a furnished room seen by a Kinect-v2-like sensor (LED 2.5 cm beside the lens).

Writes PNG previews and a JSON summary to ``--out``:

* ``distance.png``    ground-truth radial distance (first hit through each pixel centre)
* ``direct.png``      direct (k = 1) LED radiance at the lens, log scale
* ``multipath.png``   share of the signal that arrived after two or more bounces
* ``mpi_error.png``   depth error caused by multipath for an 80 MHz sine sensor (full − direct only):
                      red = measured too far, blue = too near (multipath beyond the 1.87 m ambiguity
                      range wraps around and can pull the phase nearer)
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


def diverging(values: np.ndarray, limit: float) -> np.ndarray:
    """8-bit BGR image: blue (−limit) → white (0) → red (+limit); NaN → black."""
    x = np.clip(np.nan_to_num(values) / limit, -1, 1)[..., None]
    white = np.array([255.0, 255.0, 255.0])
    red, blue = np.array([40.0, 40.0, 200.0]), np.array([200.0, 60.0, 40.0])  # BGR
    img = np.where(x > 0, white + x * (red - white), white - x * (blue - white))
    img[~np.isfinite(values)] = 0
    return img.astype(np.uint8)


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
    parser.add_argument("--scene", default="room", choices=tofcore.scene.demo.NAMES, help="demo scene (default: room)")
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

    # The correlations are the phasor cos/sin(ω L/c) of the round trip L: its angle is ω L/c and the
    # distance d = L/2 = angle · c / (4π f). The multipath error is the angle between the full and the
    # direct-only phasor, so it needs no phase unwrapping.
    full = t.correlation()
    direct = t.correlation(max_k=1)
    full_c, direct_c = full[0] + 1j * full[1], direct[0] + 1j * direct[1]
    mpi_mm = np.angle(full_c * np.conj(direct_c)) * tofcore.SPEED_OF_LIGHT_M_S / (4 * np.pi * F_MOD_HZ) * 1000.0
    signal, direct_signal = t.signal(), t.signal(max_k=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        multipath_share = 1.0 - direct_signal / signal

    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    dist = t.first_hit.distance_m
    write_png(out / "distance.png", colorize(dist, np.nanmin(dist), np.nanmax(dist)))
    log_direct = np.log10(np.where(direct_signal > 0, direct_signal, np.nan))
    write_png(out / "direct.png", colorize(log_direct, *np.nanpercentile(log_direct, [2, 98])))
    write_png(out / "multipath.png", colorize(multipath_share, 0.0, 1.0))
    write_png(out / "mpi_error.png", diverging(mpi_mm, max(1.0, float(np.nanpercentile(np.abs(mpi_mm), 98)))))
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
