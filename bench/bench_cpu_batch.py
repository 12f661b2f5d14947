"""A CPU batch on a many-core machine: frames × tracer threads, side by side.

Writes a set of ``--frames`` random views of the demo room (Kinect v2 at ``--scale`` of its resolution,
``--spp`` samples, JSON + PNG output) and renders it with ``python -m batch run`` once per configuration
(``--configs``, "workers×threads", "auto" for the batch's own choice), each into a fresh dataset, one after
the other, after one warm-up run that fills numba's cache. Prints wall seconds, frames per minute and the
speed-up over the first configuration.

Run ``python bench/bench_cpu_batch.py --configs 1x16 4x4 8x2 16x1 auto`` on the machine to measure
(docs/benchmarks.md, "Batch").
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SET = """description = "bench_cpu_batch: random views of the demo room"
seed = 0
presets = ["kinect_v2"]
resolution_scale = {scale}
[quality]
spp = {spp}
[output]
formats = ["png", "json"]
[[scenes]]
demo = "room"
[[scenes.poses]]
count = {frames}
box_min = [-1.5, -1.8, 1.2]
box_max = [1.5, -1.2, 1.9]
target = [0.0, 1.0, 0.8]
seed = 1
"""


def run(set_file: Path, out: Path, config: str) -> float:
    """Wall seconds of one batch run with ``config`` ("WxT" or "auto")."""
    cmd = [sys.executable, "-m", "batch", "run", str(set_file), "--out", str(out), "--quiet"]
    if config != "auto":
        workers, threads = config.split("x")
        cmd += ["--workers", workers, "--threads-per-worker", threads]
    start = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stderr[-2000:]}")
    chosen = [line for line in proc.stderr.splitlines() if "at once" in line]
    if chosen:
        print(f"  auto: {chosen[0].strip()}", flush=True)
    return seconds


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--scale", type=float, default=0.5, help="resolution scale of the Kinect v2 (default 0.5)")
    ap.add_argument("--configs", nargs="+", default=["1x2", "auto"], help='"WORKERSxTHREADS" or "auto"')
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench-cpu-batch-") as tmp:
        set_file = Path(tmp) / "set.toml"
        set_file.write_text(SET.format(scale=args.scale, spp=args.spp, frames=args.frames))
        warm = Path(tmp) / "warm.toml"
        warm.write_text(SET.format(scale=0.1, spp=1, frames=1))
        run(warm, Path(tmp) / "warm", "1x1")
        print(f"{args.frames} frames, Kinect v2 × {args.scale}, {args.spp} spp, {os.cpu_count()} CPUs")
        print("| frames × threads | wall s | frames/min | speed-up |")
        print("|---|---|---|---|")
        first = None
        for config in args.configs:
            seconds = run(set_file, Path(tmp) / f"out-{config}", config)
            first = first or seconds
            print(f"| {config} | {seconds:.1f} | {60 * args.frames / seconds:.1f} | {first / seconds:.2f}× |",
                  flush=True)


if __name__ == "__main__":
    main()
