"""How much of a time budget a render uses: the demo room (Kinect v2, 512 × 424) with ``time_budget_s``.

Prints, per budget (after a warm-up render that loads the compiled tracer's kernels), the render's whole time (set-up to final frame), its tracing time, the samples per
pixel it reached and the pass sizes. Run the same command under two checkouts' interpreters to compare
(before/after), in one shell command so that both see the same load::

    /work/main/.venv/bin/python bench/bench_budget.py --budgets 20 50
    .venv/bin/python bench/bench_budget.py --budgets 20 50
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import tofcore


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--budgets", type=float, nargs="+", default=[20.0, 50.0], help="seconds (default 20 50)")
    parser.add_argument("--scene", default="room", help="demo scene (default room)")
    parser.add_argument("--preset", default="kinect_v2", help="sensor preset (default kinect_v2)")
    parser.add_argument("--scale", type=float, default=1.0, help="resolution scale (default 1: 512 x 424)")
    args = parser.parse_args()
    sensor = tofcore.load_preset(args.preset).scaled(args.scale)
    scene = tofcore.demo_scene(args.scene)
    # Warm-up outside the measurement: the compiled tracer's kernels load (or compile, after a change) once.
    tofcore.render(scene, tofcore.load_preset(args.preset).scaled(16 / 512), spp=1, seed=0)
    for budget in args.budgets:
        start = time.perf_counter()
        frame = tofcore.render(scene, sensor, spp=65536, seed=0, time_budget_s=budget)
        wall = time.perf_counter() - start
        rows = frame.stats["convergence"]
        spp = [0] + [r["spp"] for r in rows]
        sizes = list(np.diff(spp))
        passes = ", ".join(f"{n}@{row['seconds']:.1f}" for n, row in zip(sizes, rows))
        print(f"{sensor.camera.width}x{sensor.camera.height}, budget {budget:5.1f} s: used {wall:6.2f} s ({wall / budget:6.1%}), tracing {frame.stats['trace_seconds']:6.2f} s, "
              f"{frame.stats['spp']} spp, est. error {1e3 * (rows[-1]['est_depth_error_m'] or np.nan):.2f} mm, "
              f"tracer {frame.stats['transport'].get('tracer', 'numpy')}, set-up "
              f"{frame.stats['transport'].get('setup_seconds', float('nan')):.1f} s, passes (spp@s) "
              f"{passes}", flush=True)


if __name__ == "__main__":
    main()
