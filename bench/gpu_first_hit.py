"""The ground truth's pixel-centre rays on the GPU, both ways in one process: the CUDA build's two kernels around
the BVH's traversal (``tofcore.compiled.cuda.first_hit``, what GPU renders use) and the array program
(``tofcore.tracer.stages.first_hit``, CuPy), in turn, on the Kinect v2 room (512 × 424); ms per call (each
synchronised, the read-back to host arrays included), and how far the records differ.

Usage::

    PYTHONPATH=. python3 bench/gpu_first_hit.py [--repeat 21]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeat", type=int, default=21)
    a = p.parse_args()
    import cupy as cp

    import tofcore
    from tofcore import backend
    from tofcore.compiled import cuda, setup
    from tofcore.scene.demo import suggested_pose
    from tofcore.tracer import stages
    from tofcore.tracer.setup import TraceSettings, make_setup
    from tofcore.tracer.transport import TraceStats

    scene, sensor = tofcore.demo_scene("room"), tofcore.load_preset("kinect_v2")
    settings = TraceSettings(world_from_sensor=suggested_pose(scene, [sensor]), correlations=sensor.modulation.correlation_bank(),
                             max_depth=5, seed=0)
    ts = make_setup(scene, sensor.camera, sensor.leds, settings, backend.select_device("gpu"))
    device_scene = cuda.upload(setup.pack(ts), scene.bvh)
    ways = {"kernels": lambda: cuda.first_hit(device_scene, ts, TraceStats()),
            "array program": lambda: stages.first_hit(ts, TraceStats())}
    times = {name: [] for name in ways}
    records = {name: way() for name, way in ways.items()}  # warm
    for _ in range(a.repeat):
        for name, way in ways.items():
            cp.cuda.Device().synchronize()
            start = time.perf_counter()
            way()
            times[name].append(time.perf_counter() - start)
    for name, t in times.items():
        print(f"first hits, {name}: median {1e3 * statistics.median(t):.2f} ms, min {1e3 * min(t):.2f} ms "
              f"({a.repeat} calls, Kinect v2 room {sensor.camera.width} x {sensor.camera.height})")
    got, want = records["kernels"], records["array program"]
    for field in ("distance_m", "position_m", "normal", "material_id", "object_id", "direction"):
        x, y = getattr(got, field), getattr(want, field)
        same_nan = bool(np.array_equal(np.isnan(x), np.isnan(y))) if x.dtype.kind == "f" else True
        diff = float(np.nanmax(np.abs(x.astype(np.float64) - y))) if x.size else 0.0
        print(f"  {field:12s} max |kernels - array program| {diff:.3g}, same misses: {same_nan}, "
              f"equal: {bool(np.array_equal(x, y, equal_nan=True))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
