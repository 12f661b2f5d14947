"""Per-bounce radiance of tofcore and mitransient: a sharper test of the multipath radiometry.

One command (bench venv)::

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 \\
        .venv-bench/bin/python studies/crosscheck/bounce_check.py [--spp 256] [--seeds 16]

Same set-up as ``crosscheck.py``. For every seed, the image mean of the radiance carried by paths
with exactly k surface vertices, k = 1..5: tofcore's bounce buckets; mitransient's steady image of
a ``max_depth = k + 1`` render minus that of ``max_depth = k`` with the same seed (the same camera
rays and the same random numbers for the first k vertices, so the difference is exactly bucket k
of one render). Ratio mitransient / tofcore per k with its standard error from the spread over
seeds, and z. Seeds differ from ``crosscheck.py``'s, so this is also an independent replication
of its indirect-radiance test. Writes ``bounce_check.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common as cc  # noqa: E402

import tofcore  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--seeds", type=int, default=16)
    ap.add_argument("--max-depth", type=int, default=5)
    ap.add_argument("--scenes", default="corner,box_on_wall")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"))
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    K = args.max_depth
    cc.mitsuba_setup()
    results = {}
    path = out / "bounce_check.json"
    if path.exists():   # keep the other scenes of an earlier run
        with open(path) as fh:
            results = json.load(fh).get("scenes", {})
    for name in args.scenes.split(","):
        s = cc.make_setup(name)
        tb = np.zeros((args.seeds, K))
        for i in range(args.seeds):
            t = tofcore.trace(s.scene, s.camera, [s.led], world_from_sensor=s.pose, spp=args.spp,
                              max_depth=K, seed=5000 + i)
            tb[i] = t.signal_per_bounce().reshape(K, -1).mean(axis=1)
            print(f"[{time.perf_counter() - t0:6.0f} s] {name} tofcore seed {i}", file=sys.stderr, flush=True)
        r = cc.MitransientRenderer(s, (16e6,), args.spp, cc.WORK / "ply", max_depth=K)
        mb = np.zeros((args.seeds, K))
        for i in range(args.seeds):
            prev = 0.0
            for k in range(1, K + 1):
                _, steady, _ = r.render(seed=6000 + i, max_depth=k)
                m = float(steady.mean())
                mb[i, k - 1] = m - prev
                prev = m
        rows = []
        for k in range(K):
            a, b = tb[:, k], mb[:, k]
            se = np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
            rows.append({"k": k + 1, "tofcore": float(a.mean()), "mitransient": float(b.mean()),
                         "ratio": float(b.mean() / a.mean()) if a.mean() > 0 else None,
                         "ratio_se": float(se / a.mean()) if a.mean() > 0 else None,
                         "z": float((a.mean() - b.mean()) / se) if se > 0 else None})
        ind_t, ind_m = tb[:, 1:].sum(axis=1), mb[:, 1:].sum(axis=1)
        se = np.sqrt(ind_t.var(ddof=1) / len(ind_t) + ind_m.var(ddof=1) / len(ind_m))
        results[name] = {"per_bounce": rows, "indirect": {
            "ratio": float(ind_m.mean() / ind_t.mean()), "ratio_se": float(se / ind_t.mean()),
            "z": float((ind_t.mean() - ind_m.mean()) / se)}, "spp": args.spp, "seeds": args.seeds}
        print(f"\n{name}: image-mean radiance per bounce count k, {args.seeds} seeds × {args.spp} spp")
        print("| k | tofcore | mitransient | ratio m/t | ± SE | z (t − m) |")
        print("|---|---|---|---|---|---|")
        def fmt(x, spec):
            return "–" if x is None else format(x, spec)

        for q in rows:
            print(f"| {q['k']} | {q['tofcore']:.6g} | {q['mitransient']:.6g} | {fmt(q['ratio'], '.5f')} "
                  f"| {fmt(q['ratio_se'], '.5f')} | {fmt(q['z'], '+.2f')} |")
        ind = results[name]["indirect"]
        print(f"| 2–{K} | | | {ind['ratio']:.5f} | {ind['ratio_se']:.5f} | {ind['z']:+.2f} |")
        with open(path, "w") as fh:
            json.dump({"command": " ".join([Path(sys.executable).name] + sys.argv), "scenes": results,
                       "seconds": time.perf_counter() - t0}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
