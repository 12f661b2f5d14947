"""Textured scenes, sky maps and transient histograms on the compiled tracer: their cost against the plain room.

Issue 31's target: the textured demo room under its sky map (``demo_scene("textured_room")`` with
``demo_ambient("textured_room")``) traces compiled on the CPU and the GPU in ≤ 1.2× the plain room's time
per sample. Scenes, each traced with the Kinect v2's correlation bank, one point LED 2.5 cm beside the
lens, 5 surface vertices, in one process after a warm-up frame of each:

* ``room``: the plain demo room (closed, untextured);
* ``room + textures``: the same closed room with the textured room's materials (textures only);
* ``textured_room + sky``: the textured room, open to its 32 × 64 sky map;
* ``textured_room + sky + transient``: the same with a transient histogram (5 cm bins to 12 m);
* with ``--numpy`` also the NumPy reference on the first and third.

Each frame is traced ``--repeat`` times; the table gives the median seconds per frame, per sample per pixel,
the rays, and the ratio to the plain room per sample and per ray (the open room's paths end earlier, so
per ray is the fairer measure of what a texture lookup costs).

Usage::

    .venv/bin/python bench/bench_textured.py --size 128x106 --spp 16 --repeat 3 [--numpy] [--json out.json]
    python3 bench/bench_textured.py --device gpu --size 512x424 --spp 16 --repeat 5 --json $OUT/textured.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def cases(detail: int) -> dict:
    """name → (scene, ambient, extra trace settings)."""
    import tofcore
    from tofcore.scene import demo

    room = tofcore.demo_scene("room", detail=detail)
    textured = tofcore.demo_scene("textured_room", detail=detail)
    closed_textured = demo._room(demo._Builder(detail), "room + textures", demo._textured_materials())
    sky = tofcore.demo_ambient("textured_room")
    return {"room": (room, None, {}), "room + textures": (closed_textured, None, {}),
            "textured_room + sky": (textured, sky, {}),
            "textured_room + sky + transient": (textured, sky, dict(transient_bin_m=0.05, transient_max_m=12.0))}


def run(name, scene, ambient, extra, args, tracer: str) -> dict:
    import tofcore

    os.environ["TOFCORE_TRACER"] = tracer
    sensor = tofcore.load_preset("kinect_v2")
    width, height = (int(x) for x in args.size.split("x"))
    camera = tofcore.Camera.from_fov(width, height, 70.6, 60.0)
    kwargs = dict(world_from_sensor=tofcore.suggested_pose(scene), correlations=sensor.modulation.correlation_bank(),
                  max_depth=5, seed=0, ambient=ambient, device=args.device, **extra)
    leds = [tofcore.LED(position_m=(0.025, 0.0, 0.0))]
    tofcore.trace(scene, camera, leds, spp=1, **kwargs)  # warm-up: compile or load, device arrays
    seconds, rays = [], 0
    for _ in range(args.repeat):
        start = time.perf_counter()
        t = tofcore.trace(scene, camera, leds, spp=args.spp, **kwargs)
        seconds.append(time.perf_counter() - start)
        rays = t.stats.rays
    assert t.stats.tracer == tracer, (t.stats.tracer, t.stats.tracer_reason)
    s = statistics.median(seconds)
    return {"case": name, "tracer": tracer, "device": args.device, "seconds": s, "all_seconds": seconds,
            "seconds_per_spp": s / args.spp, "rays": rays, "ns_per_ray": 1e9 * s / max(rays, 1)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", default="128x106")
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--detail", type=int, default=10, help="demo scene detail (10: 9.8k triangles, bench_peers')")
    p.add_argument("--device", default="cpu")
    p.add_argument("--numpy", action="store_true", help="also the NumPy reference (CPU)")
    p.add_argument("--json", type=Path)
    args = p.parse_args()
    rows = []
    for name, (scene, ambient, extra) in cases(args.detail).items():
        rows.append(run(name, scene, ambient, extra, args, "compiled"))
        if args.numpy and name in ("room", "textured_room + sky"):
            rows.append(run(name, scene, ambient, extra, args, "numpy"))
    base = {r["tracer"]: r for r in rows if r["case"] == "room"}
    print(f"{args.device}, {args.size}, {args.spp} spp, median of {args.repeat}")
    print(f"{'case':34s} {'tracer':9s} {'s/frame':>9s} {'ms/spp':>8s} {'rays':>11s} {'ns/ray':>7s} "
          f"{'×room/spp':>9s} {'×room/ray':>9s}")
    for r in rows:
        b = base[r["tracer"]]
        r["ratio_per_spp"] = r["seconds"] / b["seconds"]
        r["ratio_per_ray"] = r["ns_per_ray"] / b["ns_per_ray"]
        print(f"{r['case']:34s} {r['tracer']:9s} {r['seconds']:9.3f} {1e3 * r['seconds_per_spp']:8.2f} "
              f"{r['rays']:11,d} {r['ns_per_ray']:7.1f} {r['ratio_per_spp']:9.2f} {r['ratio_per_ray']:9.2f}")
    if args.json:
        args.json.write_text(json.dumps({"size": args.size, "spp": args.spp, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
