"""Scaling of one frame with CPU workers: processes (the default) against threads, side by side.

Renders the ``bench_peers`` frame (demo room, 9,800 triangles, 512 × 424, 16 spp, path length 5, one LED
2.5 cm beside the lens) with 1, 2, 4, … workers up to the usable CPUs, as processes and as threads
(``TOFCORE_PARALLEL=threads``), each in a fresh subprocess, rounds alternating; prints frame time,
speed-up over one worker, parallel efficiency and the worker processes' memory (private / shared).

Where the efficiency goes: *setup* is the wall time before the first pass (first-hit buffers, shared
memory, worker start-up); *busy* is the share of the workers' time after it spent tracing chunks (the
rest waits at pass ends or in the parent); *work* is the CPU-seconds inside chunks relative to one
worker's (above 1: each core traces slower when all are busy — shared caches, memory bandwidth, SMT
siblings, lower turbo clocks). Efficiency ≈ (1 − setup share) × busy / work.

    .venv/bin/python bench/bench_scaling.py [--rounds 2] [--resolution 512x424] [--json out/bench_scaling.json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from tofcore.limits import usable_cpus  # noqa: E402

BENCH = Path(__file__).resolve().parent / "bench_transport.py"


def frame(mode: str, workers: int, args) -> dict:
    env = dict(os.environ, TOFCORE_PARALLEL=mode)
    cmd = [sys.executable, str(BENCH), "--one", "10", "--spp", str(args.spp), "--resolution", args.resolution,
           "--workers", str(workers)] + (["--progressive"] if args.progressive else []) \
        + (["--chunk-size", str(args.chunk_size)] if args.chunk_size else [])
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--resolution", default="512x424")
    ap.add_argument("--max-workers", type=int, default=usable_cpus())
    ap.add_argument("--modes", default="processes,threads", help="comma list of processes, threads")
    ap.add_argument("--progressive", action="store_true", help="passes of 1, 1, 2, 4, 8 spp (previews)")
    ap.add_argument("--chunk-size", type=int, help="paths per chunk (default: the tracer's)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    counts = sorted({1, args.max_workers} | {2 ** k for k in range(1, 8) if 2 ** k <= args.max_workers})
    runs: dict = {}
    for r in range(args.rounds):
        for mode in args.modes.split(","):
            for w in counts:
                result = frame(mode, w, args)
                runs.setdefault((mode, w), []).append(result)
                print(f"# round {r + 1} {mode} {w}: {result['frame_s']:.2f} s ({result['parallel']})",
                      file=sys.stderr, flush=True)
    base = statistics.median(x["frame_s"] for x in runs[("processes", 1)])
    print(f"{args.resolution}, {args.spp} spp, room 9,800 triangles, path length 5; {usable_cpus()} usable CPUs; "
          f"median of {args.rounds}\n")
    work1 = min(runs[("processes", 1)], key=lambda x: abs(x["frame_s"] - base))["chunk_s"]
    print("| workers | processes s | speed-up | efficiency | setup s | busy | work | threads s | speed-up "
          "| worker memory MiB (private / shared, each) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for w in counts:
        p = statistics.median(x["frame_s"] for x in runs[("processes", w)])
        t = statistics.median(x["frame_s"] for x in runs.get(("threads", w), [{"frame_s": float("nan")}]))
        mem = runs[("processes", w)][-1].get("worker_memory_mib") or []
        mem_text = ", ".join(f"{m.get('RssAnon', 0):.0f} / {m.get('RssShmem', 0):.0f}" for m in mem) or "–"
        one = min(runs[("processes", w)], key=lambda x: abs(x["frame_s"] - p))  # the run nearest the median
        print(f"| {w} | {p:.1f} | {base / p:.2f}× | {base / p / w:.0%} | {one['setup_s']:.2f} | {one['busy']:.0%} "
              f"| {one['chunk_s'] / work1:.2f} | {t:.1f} | {base / t:.2f}× | {mem_text} |")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({f"{m} {w}": v for (m, w), v in runs.items()}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
