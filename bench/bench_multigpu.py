"""Dataset throughput on 1 GPU against 2 GPUs, kernel caches cold and warm (issue 26).

Renders the same Kinect v2 room set (``--frames`` random poses of the demo room, ``--spp``, PNG + JSON,
``tofcore-batch run --device gpu``) into a fresh dataset per run, as ``python -m batch run`` in a fresh
process with ``CUDA_VISIBLE_DEVICES`` naming the first GPU, then the first two:

* **cold**: ``CUPY_CACHE_DIR`` and ``NUMBA_CACHE_DIR`` point at new empty folders (every worker compiles
  the kernels it meets, as on a fresh machine);
* **warm**: both point at ``--warm-cache`` (filled by a 2-frame warm-up run when it is empty).

Frames per minute are the set's frames over the wall time of the whole command (process start, GPU
discovery, workers, index and card included); scaling is 2-GPU frames/min over 1-GPU frames/min of the
same cache state and round. Per worker, the records' ``timing`` (:mod:`batch.timing`) says where the
time went. The PNGs of the 1-GPU and 2-GPU datasets (``depth_mm.png`` and every other but
``convergence.png``, whose x axis is the render time) are compared byte for byte. A round runs 1 GPU then 2, warm then cold; a pair is started only while
``--budget`` seconds allow it (estimated from the last pair of the same cache state).

    PYTHONPATH=. python3 bench/bench_multigpu.py --out-dir $OUT/multigpu        # a machine with >= 2 GPUs
    .venv/bin/python bench/bench_multigpu.py --device cpu --out-dir out/mgpu    # smoke test: 2 fake GPUs

``--device cpu`` runs the same commands with ``TOF_BATCH_FAKE_GPU=1`` (two pinned workers rendering on
the CPU) and tiny defaults (4 frames, 2 spp, 1/16 resolution): it checks the benchmark, not the GPUs.
Writes ``bench_multigpu.json``, ``bench_multigpu.md`` and one log per run into ``--out-dir``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from batch.timing import worker_timing  # noqa: E402

SET = """description = "bench_multigpu: demo room, Kinect v2, {frames} random poses"
seed = 0
presets = ["kinect_v2"]
resolution_scale = {scale}

[quality]
spp = {spp}
max_depth = {max_depth}

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


def write_set(folder: Path, frames: int, args) -> Path:
    path = folder / f"set-{frames}.toml"
    path.write_text(SET.format(frames=frames, spp=args.spp, max_depth=args.max_depth, scale=args.resolution_scale))
    return path


def run_batch(set_file: Path, dataset: Path, gpus: list[str], cache: Path, log: Path, args) -> tuple[float, float]:
    """(wall seconds, epoch when started) of one ``python -m batch run``; raises when it fails."""
    env = dict(os.environ, CUDA_VISIBLE_DEVICES=",".join(gpus), CUPY_CACHE_DIR=str(cache / "cupy"),
               NUMBA_CACHE_DIR=str(cache / "numba"),
               PYTHONPATH=os.pathsep.join([str(REPO)] + ([os.environ["PYTHONPATH"]] if "PYTHONPATH" in os.environ
                                                        else [])))
    env.pop("TOF_BATCH_FAIL", None)
    if args.device == "cpu":
        env["TOF_BATCH_FAKE_GPU"] = "1"
    cmd = [sys.executable, "-m", "batch", "run", str(set_file), "--out", str(dataset), "--device", "gpu", "--quiet"]
    launched, started = time.time(), time.perf_counter()
    with log.open("w") as out:
        proc = subprocess.run(cmd, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)
    seconds = time.perf_counter() - started
    if proc.returncode != 0:
        raise SystemExit(f"bench_multigpu: {' '.join(cmd)} failed (exit {proc.returncode}); see {log}:\n"
                         + "\n".join(log.read_text().splitlines()[-15:]))
    return seconds, launched


def records(dataset: Path) -> list[dict]:
    return [json.loads(line) for line in (dataset / "index.jsonl").read_text().splitlines()]


def tracer(dataset: Path, record: dict) -> str:
    """The tracer that rendered a frame (``frame.json``: stats.transport.tracer)."""
    stats = json.loads((dataset / record["dir"] / "frame.json").read_text())["stats"]
    return stats.get("transport", {}).get("tracer") or "?"


def png_digests(dataset: Path) -> dict[str, str]:
    """SHA-256 of every PNG of the dataset but ``convergence.png`` (its x axis is the render time), by
    ``job_id/name``."""
    return {f"{p.parent.name}/{p.name}": hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted((dataset / "frames").glob("*/*.png")) if p.name != "convergence.png"}


def one_run(n_gpus: int, cache_state: str, round_no: int, set_file: Path, work: Path, args) -> dict:
    name = f"{cache_state}-{n_gpus}gpu-r{round_no}"
    dataset = work / "datasets" / name
    cache = Path(tempfile.mkdtemp(prefix=f"cache-{name}-", dir=work)) if cache_state == "cold" else args.warm_cache
    try:
        seconds, launched = run_batch(set_file, dataset, args.gpus[:n_gpus], cache, args.out_dir / f"{name}.log",
                                      args)
    finally:
        if cache_state == "cold":
            shutil.rmtree(cache, ignore_errors=True)
    rows = records(dataset)
    bad = [r["job_id"] for r in rows if r["status"] != "ok"]
    if len(rows) != args.frames or bad:
        raise SystemExit(f"bench_multigpu: {name}: {len(rows)} records, not ok: {bad}")
    workers = worker_timing(rows)
    result = {"name": name, "gpus": n_gpus, "cache": cache_state, "round": round_no, "frames": len(rows),
              "wall_s": seconds, "frames_per_min": len(rows) / seconds * 60, "workers": workers,
              # the parent before its first worker: interpreter, imports, GPU discovery, set and index
              "parent_s": min(w["worker_started"] for w in workers) - launched,
              # the last worker's end to the command's: index rewrite, dataset card, exit
              "tail_s": launched + seconds - max(w["worker_started"] + w["span_s"] for w in workers),
              "frames_per_worker": [w["frames"] for w in workers],
              "devices": sorted({(r.get("device") or {}).get("description") or "?" for r in rows}),
              "tracers": sorted({tracer(dataset, r) for r in rows}),
              "png": png_digests(dataset)}
    print(f"{name}: {seconds:.1f} s, {result['frames_per_min']:.1f} frames/min, frames per worker "
          f"{result['frames_per_worker']}", flush=True)
    if not args.keep_datasets:
        shutil.rmtree(dataset, ignore_errors=True)
    return result


def warm_up(work: Path, args) -> None:
    """Fill an empty ``--warm-cache``: 2 frames on 1 GPU, then on 2 (the CPU stand-in compiles a tracer per
    thread count; on GPUs the second run finds everything cached)."""
    if any(args.warm_cache.rglob("*")):
        return
    args.warm_cache.mkdir(parents=True, exist_ok=True)
    set_file = write_set(work, 2, args)
    for n_gpus in gpu_counts(args):
        seconds, _ = run_batch(set_file, work / "datasets" / f"warm-up-{n_gpus}", args.gpus[:n_gpus], args.warm_cache,
                               args.out_dir / f"warm-up-{n_gpus}gpu.log", args)
        print(f"warm-up on {n_gpus} GPU(s) (2 frames, cache {args.warm_cache}): {seconds:.1f} s", flush=True)


def gpu_counts(args) -> tuple[int, ...]:
    """The GPU counts each round runs: 1 and 2, or 1 alone where ``--gpus`` names one GPU."""
    return (1, 2) if len(args.gpus) >= 2 else (1,)


def plan(args) -> list[tuple[str, int]]:
    """(cache, round) pairs in the order run (each pair: 1 GPU, then 2): per round warm, then cold."""
    return [(cache_state, round_no) for round_no in range(1, max(args.rounds, args.cold_rounds) + 1)
            for cache_state, rounds in (("warm", args.rounds), ("cold", args.cold_rounds)) if round_no <= rounds]


def _seconds(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f}"


def table(results: list[dict]) -> list[str]:
    by_key = {(r["cache"], r["round"], r["gpus"]): r for r in results}
    lines = ["| cache | round | GPUs | frames | wall s | frames/min | scaling | frames per worker | parent s "
             "(before workers / after) | per worker: start-up / first render / render median / render total / "
             "write total (overlapped with rendering) / render waited for the writer / idle s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        one = by_key.get((r["cache"], r["round"], 1))
        scaling = f"{r['frames_per_min'] / one['frames_per_min']:.2f}×" if one and r["gpus"] > 1 else "–"
        phases = "; ".join(f"{w['startup_s']:.1f} / {w['first_s']:.1f} / {_seconds(w['render_median_s'])} / "
                           f"{w['render_s']:.1f} / {w['write_s']:.1f} ({w.get('overlap_s', 0.0):.1f}) / "
                           f"{w.get('wait_s', 0.0):.1f} / {w['idle_s']:.1f}" for w in r["workers"])
        lines.append(f"| {r['cache']} | {r['round']} | {r['gpus']} | {r['frames']} | {r['wall_s']:.1f} | "
                     f"{r['frames_per_min']:.1f} | {scaling} | {r['frames_per_worker']} | {r['parent_s']:.1f} / "
                     f"{r['tail_s']:.1f} | {phases} |")
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", choices=["gpu", "cpu"], default="gpu",
                        help="gpu (default): the machine's GPUs; cpu: two fake GPUs rendering on the CPU (smoke)")
    parser.add_argument("--gpus", default="0,1", help="CUDA_VISIBLE_DEVICES ids; 1 GPU = the first (default 0,1); one id: "
                        "the 1-GPU runs alone")
    parser.add_argument("--frames", type=int, default=None, help="frames in the set (default 24; cpu: 4)")
    parser.add_argument("--spp", type=int, default=None, help="samples per pixel (default 64; cpu: 2)")
    parser.add_argument("--max-depth", type=int, default=None, help="path length (default 5; cpu: 2)")
    parser.add_argument("--resolution-scale", type=float, default=None, help="default 1 (512 × 424); cpu: 0.0625")
    parser.add_argument("--rounds", type=int, default=2, help="warm rounds (default 2)")
    parser.add_argument("--cold-rounds", type=int, default=2, help="cold rounds (default 2)")
    parser.add_argument("--budget", type=float, default=420.0,
                        help="seconds: a pair of runs that would end past them (by the last pair of its cache "
                             "state) is skipped (default 420)")
    parser.add_argument("--warm-cache", type=Path, default=None,
                        help="the warm kernel caches (CUPY_CACHE_DIR/NUMBA_CACHE_DIR below it; default: in the "
                             "work folder, filled by a warm-up run)")
    parser.add_argument("--out-dir", type=Path, required=True, help="JSON, markdown and logs go here")
    parser.add_argument("--keep-datasets", action="store_true", help="keep the datasets (in --out-dir/work)")
    args = parser.parse_args()
    tiny = args.device == "cpu"
    args.frames = args.frames or (4 if tiny else 24)
    args.spp = args.spp or (2 if tiny else 64)
    args.max_depth = args.max_depth or (2 if tiny else 5)
    args.resolution_scale = args.resolution_scale or (0.0625 if tiny else 1.0)
    args.gpus = [g.strip() for g in args.gpus.split(",") if g.strip()]
    if not args.gpus:
        parser.error("--gpus must name a GPU (one: the per-GPU rate alone, no scaling)")
    args.out_dir.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="bench-multigpu-")) if not args.keep_datasets else args.out_dir / "work"
    work.mkdir(parents=True, exist_ok=True)
    args.warm_cache = (args.warm_cache or work / "warm-cache").resolve()
    started = time.perf_counter()
    set_file = write_set(work, args.frames, args)
    warm_up(work, args)
    results, skipped, last, same = [], [], {}, None
    for cache_state, round_no in plan(args):
        expected = last.get(cache_state)  # the last pair of this cache state
        if expected is not None and time.perf_counter() - started + expected > args.budget:
            skipped.append(f"{cache_state} round {round_no}")
            continue
        pair = 0.0
        for n_gpus in gpu_counts(args):
            result = one_run(n_gpus, cache_state, round_no, set_file, work, args)
            pair += result["wall_s"]
            results.append(result)
            same = report(results, skipped, args, time.perf_counter() - started)  # after every run: kept if cut off
        last[cache_state] = pair
    print((args.out_dir / "bench_multigpu.md").read_text(), end="")
    if not args.keep_datasets:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if same is not False else 1


def report(results: list[dict], skipped: list[str], args, seconds: float) -> bool | None:
    """Write ``bench_multigpu.md`` and ``.json``; whether the PNGs of the 2-GPU runs equal the first 1-GPU run's."""
    one = next((o for o in results if o["gpus"] == 1), None)
    same_png = {r["name"]: one is not None and r["png"] == one["png"] for r in results if r["gpus"] > 1}
    same = all(same_png.values()) if same_png and one is not None else None
    scalings = {}
    for cache_state in ("warm", "cold"):
        pairs = [(r["frames_per_min"], o["frames_per_min"]) for r in results for o in results
                 if r["cache"] == o["cache"] == cache_state and r["round"] == o["round"] and r["gpus"] == 2
                 and o["gpus"] == 1]
        if pairs:
            scalings[cache_state] = [two / one for two, one in pairs]
    fake = " (fake GPUs on the CPU)" if args.device == "cpu" else ""
    lines = [f"bench_multigpu: {args.frames} frames, demo room, Kinect v2 × {args.resolution_scale:g}, "
             f"{args.spp} spp, path length {args.max_depth}, png+json, --device gpu{fake}; devices "
             f"{sorted({d for r in results for d in r['devices']})}; tracer "
             f"{sorted({t for r in results for t in r['tracers']})}", ""] + table(results) + [""]
    for cache_state, values in scalings.items():
        lines.append(f"{cache_state}: scaling 2 GPUs / 1 GPU = {', '.join(f'{v:.2f}×' for v in values)} "
                     f"(median {statistics.median(values):.2f}×)")
    lines.append(f"PNG files (depth_mm.png and the rest but convergence.png) identical between 1 and 2 GPUs: "
                 f"{same} ({len(results[0]['png'])} files per run)")
    if skipped:
        lines.append(f"skipped for the {args.budget:g} s budget: {', '.join(skipped)}")
    lines.append(f"total {seconds:.0f} s")
    (args.out_dir / "bench_multigpu.md").write_text("\n".join(lines) + "\n")
    runs = [{k: v for k, v in r.items() if k != "png"} for r in results]
    (args.out_dir / "bench_multigpu.json").write_text(json.dumps(
        {"settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
         "runs": runs, "scaling": scalings, "png_identical": same_png, "skipped": skipped}, indent=1))
    return same


if __name__ == "__main__":
    sys.exit(main())
