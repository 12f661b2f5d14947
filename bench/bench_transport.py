"""Benchmark of the path tracer: rays/s, time and peak memory per frame.

Renders the demo room at three triangle counts (~10 k, ~500 k, ~1 M) at
512×424, 16 spp, max_depth 5, with one LED 2.5 cm beside the lens and two
correlation functions (an 80 MHz phasor), each scene in a fresh subprocess so
peak memory (max RSS) is per frame. Prints a Markdown table for
``docs/benchmarks.md``.

Usage::

    .venv/bin/python bench/bench_transport.py                 # all three scenes
    .venv/bin/python bench/bench_transport.py --sizes 10k --spp 4
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

# Room detail → triangles: 49 quads × 2·detail².
SIZES = {"10k": 10, "500k": 71, "1M": 101}


def run_one(detail: int, spp: int, max_depth: int, width: int, height: int, workers: int | None = None,
            progressive: bool = False, chunk_size: int | None = None) -> dict:
    import tofcore
    from tofcore.sensor.modulation import phasor_correlations
    from tofcore.limits import usable_cpus

    t0 = time.perf_counter()
    scene = tofcore.demo_scene("room", detail=detail)
    bvh = scene.bvh
    build_s = time.perf_counter() - t0
    camera = tofcore.Camera.from_fov(width, height, 70.6, 60.0)
    t = tofcore.trace(scene, camera, [tofcore.LED(position_m=(0.025, 0.0, 0.0))],
                      world_from_sensor=tofcore.suggested_pose(scene),
                      correlations=phasor_correlations([80e6]), spp=spp, max_depth=max_depth, seed=0,
                      workers=workers, progressive=progressive, chunk_size=chunk_size)
    s = t.stats
    n_workers = workers or usable_cpus()
    return {
        "triangles": scene.triangle_count, "build_s": build_s, "bvh": {k: v for k, v in bvh.stats.items()
                                                                        if isinstance(v, (int, float))},
        "frame_s": s.seconds, "rays": s.rays, "camera_rays": s.camera_rays, "bounce_rays": s.bounce_rays,
        "shadow_rays": s.shadow_rays, "skipped_shadow_rays": s.skipped_shadow_rays,
        "rays_per_s": s.rays / s.seconds,
        "camera_rays_per_s": s.camera_rays / max(s.camera_seconds, 1e-9),
        "bounce_rays_per_s": s.bounce_rays / max(s.bounce_seconds, 1e-9),
        "shadow_rays_per_s": s.shadow_rays / max(s.shadow_seconds, 1e-9),
        "workers": n_workers, "parallel": s.parallel, "setup_s": s.setup_seconds, "chunk_s": s.chunk_seconds,
        "busy": s.chunk_seconds / (n_workers * max(s.seconds - s.setup_seconds, 1e-9)),
        "bvh_share": (s.camera_seconds + s.bounce_seconds + s.shadow_seconds) / (s.seconds * n_workers),
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "worker_memory_mib": _worker_memory(),
    }


def _worker_memory() -> list[dict]:
    """Resident memory of each tracer worker process (Linux /proc): private (RssAnon) and shared (RssShmem), MiB."""
    from tofcore.tracer import workers
    if workers._POOL is None:
        return []
    out = []
    for proc in workers._POOL.pool._pool:
        fields = {}
        try:
            for line in open(f"/proc/{proc.pid}/status"):
                key, _, value = line.partition(":")
                if key in ("VmRSS", "RssAnon", "RssShmem", "VmHWM"):
                    fields[key] = int(value.split()[0]) / 1024
        except OSError:
            continue
        out.append(fields)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="10k,500k,1M", help="comma list of 10k, 500k, 1M (default: all)")
    parser.add_argument("--spp", type=int, default=16, help="samples per pixel (default: 16)")
    parser.add_argument("--max-depth", type=int, default=5, help="path length (default: 5)")
    parser.add_argument("--resolution", default="512x424", help="WxH (default: 512x424)")
    parser.add_argument("--workers", type=int, default=None, help="tracer worker processes (default: usable CPUs)")
    parser.add_argument("--progressive", action="store_true",
                        help="passes of 1, 1, 2, 4, 8, 16 spp (previews) instead of 16")
    parser.add_argument("--chunk-size", type=int, default=None, help="paths per chunk (default: the tracer's)")
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # internal: run one detail level, print JSON
    args = parser.parse_args()
    width, height = (int(x) for x in args.resolution.split("x"))
    if args.one is not None:
        print(json.dumps(run_one(args.one, args.spp, args.max_depth, width, height, args.workers,
                                    args.progressive, args.chunk_size)))
        return 0
    rows = []
    for size in args.sizes.split(","):
        cmd = [sys.executable, __file__, "--one", str(SIZES[size]), "--spp", str(args.spp),
               "--max-depth", str(args.max_depth), "--resolution", args.resolution]
        cmd += ["--workers", str(args.workers)] if args.workers else []
        out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=os.environ).stdout
        r = json.loads(out.strip().splitlines()[-1])
        rows.append(r)
        print(f"# {size}: {json.dumps(r)}", file=sys.stderr, flush=True)
    print(f"{args.resolution}, {args.spp} spp, max_depth {args.max_depth}, room scene, 1 LED 2.5 cm beside the lens\n")
    print("| triangles | BVH build s | frame s | M rays | M rays/s total | camera | bounce | shadow "
          "| BVH share | peak RSS MiB |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['triangles']:,} | {r['build_s']:.1f} | {r['frame_s']:.1f} | {r['rays'] / 1e6:.1f} "
              f"| {r['rays_per_s'] / 1e6:.2f} | {r['camera_rays_per_s'] / 1e6:.2f} "
              f"| {r['bounce_rays_per_s'] / 1e6:.2f} | {r['shadow_rays_per_s'] / 1e6:.2f} "
              f"| {r['bvh_share']:.0%} | {r['peak_rss_mib']:.0f} |")
    print("\ncamera/bounce/shadow: rays per thread-second spent inside the BVH for that kind of ray "
          "(per core); total: all rays over the wall-clock frame time (BVH + shading + sampling, "
          f"{rows[0]['workers']} worker threads); BVH share: BVH thread-time over workers × frame time.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
