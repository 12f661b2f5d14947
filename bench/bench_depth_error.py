"""The render-error estimate after every pass: the compiled one (tofcore.compiled.depth_error) against the array
program (tofcore.render's NumPy/CuPy code, in row bands on threads on the CPU), on the same transport.

Traces the Kinect v2 room frame (512 × 424, 16 spp, 5 vertices, the compiled tracer) once on the device, then
times ``render.render_error`` both ways, alternating, and prints the medians, the ratio, and how far σ and the
flips agree. The compiled estimate is ``depth_error.render_error`` (renders use it on a GPU), the array
program ``render.render_error`` on the same transport marked as traced by NumPy (what CPU renders use).

Usage::

    .venv/bin/python bench/bench_depth_error.py --repeat 7
    PYTHONPATH=. python3 bench/bench_depth_error.py --device gpu --repeat 11 --json $OUT/depth_error.json
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu", choices=("cpu", "gpu"))
    p.add_argument("--repeat", type=int, default=7)
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--json", type=Path)
    a = p.parse_args()
    import tofcore
    from tofcore import backend

    render = importlib.import_module("tofcore.render")
    sensor = tofcore.load_preset("kinect_v2")
    scene = tofcore.demo_scene("room")
    pose = tofcore.suggested_pose(scene, sensor)
    transport = tofcore.trace(scene, sensor.camera, sensor.leds, world_from_sensor=pose,
                              correlations=sensor.modulation.correlation_bank(), spp=a.spp, max_depth=5, seed=0,
                              device=a.device)
    assert transport.stats.tracer == "compiled", transport.stats.tracer_reason
    as_numpy = dataclasses.replace(transport, stats=dataclasses.replace(transport.stats, tracer="numpy"))
    n_raw = len(sensor.modulation.correlation_bank())
    xp = backend.namespace(transport.replicate_sum)

    from tofcore.compiled import depth_error

    def timed(t):
        start = time.perf_counter()  # the trace is done: its sums were read back by the sample counts
        if t is transport:
            sigma, flips = depth_error.render_error(t, sensor, n_raw, render.flip_threshold_m(sensor))
        else:
            sigma, flips = render.render_error(t, sensor, n_raw)
        host = backend.to_host(xp.stack([sigma, flips.astype(sigma.dtype)]))  # the render reads both back
        return time.perf_counter() - start, host[0], host[1] > 0.5

    _, sigma, flips = timed(transport)  # compiles (or loads) the kernels
    _, ref_sigma, ref_flips = timed(as_numpy)
    times = {"compiled": [], "array program": []}
    for _ in range(a.repeat):
        times["compiled"].append(timed(transport)[0])
        times["array program"].append(timed(as_numpy)[0])
    seen = np.isfinite(ref_sigma)
    rel = np.abs(sigma[seen] - ref_sigma[seen]) / ref_sigma[seen]
    result = {"device": a.device, "spp": a.spp, "pixels": int(sigma.size),
              "median_s": {k: statistics.median(v) for k, v in times.items()},
              "min_s": {k: min(v) for k, v in times.items()},
              "speed_up": statistics.median(times["array program"]) / statistics.median(times["compiled"]),
              "sigma_max_rel_difference": float(rel.max()), "same_nan": bool(np.array_equal(seen, np.isfinite(sigma))),
              "flips": int(ref_flips.sum()), "flips_differing": int((flips != ref_flips).sum())}
    for k, v in times.items():
        print(f"{k:14s} median {1e3 * statistics.median(v):8.1f} ms  min {1e3 * min(v):8.1f} ms  ({a.repeat} runs)")
    print(f"speed-up {result['speed_up']:.1f}x; sigma max rel difference {result['sigma_max_rel_difference']:.1e}; "
          f"flips {result['flips']} (differing {result['flips_differing']})")
    if a.json:
        a.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
