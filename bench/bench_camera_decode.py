"""The camera's decode: the compiled one (tofcore.compiled.camera_decode, three passes over the pixels) against the
decoder's array program (tofcore.sensor.decode.decode, NumPy on the CPU, CuPy on a GPU), on the same raw images.

Traces the Kinect v2 room frame (512 × 424, 5 vertices, the compiled tracer) once on the device, makes the camera's
raw images as a render does (lens scattering, shot, read and gain noise, full well: render._camera_raw), then
decodes them both ways with the camera's settings, in turn, and prints the medians, the ratio, and how far the
two agree (reasons, float32 outputs in ulps). ``--raw FILE`` keeps the CPU's raw images in FILE (.npy) between
runs; the first call of the compiled decode (compiling or loading its machine code) is timed apart.

Usage::

    .venv/bin/python bench/bench_camera_decode.py --repeat 9 --raw /tmp/kinect_raw.npy
    PYTHONPATH=. python3 bench/bench_camera_decode.py --device gpu --repeat 21 --json $OUT/camera_decode.json
"""

from __future__ import annotations

import argparse
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
    p.add_argument("--spp", type=int, default=4)
    p.add_argument("--raw", type=Path, help="keep the raw images here (.npy; CPU only)")
    p.add_argument("--json", type=Path)
    a = p.parse_args()
    import tofcore
    from tofcore import backend
    from tofcore.sensor import decode as decoding
    from tofcore.sensor.noise import NoiseStream

    render = importlib.import_module("tofcore.render")
    sensor = tofcore.load_preset("kinect_v2")
    scene = tofcore.demo_scene("room")
    plan = render.make_plan(scene, sensor, max_depth=5, ambient=None)
    if a.raw is not None and a.raw.exists() and a.device == "cpu":
        raw = np.load(a.raw)
        xp = np
    else:
        pose = tofcore.suggested_pose(scene, sensor)
        transport = tofcore.trace(scene, sensor.camera, sensor.leds, world_from_sensor=pose,
                                  correlations=sensor.modulation.correlation_bank(), spp=a.spp, max_depth=5, seed=0,
                                  device=a.device)
        xp = backend.namespace(transport.correlation_sum)
        setup = render.frame_setup(sensor, plan, xp)
        n_raw = len(sensor.modulation.correlation_bank())
        raw = render._camera_raw(transport, sensor, plan, NoiseStream.from_seed(0), n_raw, setup)
        if a.raw is not None and xp is np:
            np.save(a.raw, raw)
    settings = render.frame_setup(sensor, plan, xp).camera

    from tofcore.compiled import camera_decode

    def sync():
        if xp is not np:
            xp.cuda.Device().synchronize()

    def timed(decode):
        sync()
        start = time.perf_counter()
        decoded = decode(raw, sensor.modulation, settings, check=False)
        sync()
        return time.perf_counter() - start, decoded

    first_s, fast = timed(camera_decode.decode)  # compiles (or loads) the kernels
    _, reference = timed(decoding.decode)
    times = {"compiled": [], "array program": []}
    for _ in range(a.repeat):
        times["compiled"].append(timed(camera_decode.decode)[0])
        times["array program"].append(timed(decoding.decode)[0])
    fields = ("distance", "amplitude", "offset", "intensity", "confidence", "reason")
    fast, reference = ({f: backend.to_host(getattr(d, f)) for f in fields} for d in (fast, reference))
    ulps = {}
    for name in ("distance", "amplitude", "offset", "intensity", "confidence"):
        seen = ~np.isnan(reference[name]) & ~np.isnan(fast[name])
        bits = [d[name][seen].view(np.int32).astype(np.int64) for d in (fast, reference)]
        ulps[name] = int(np.abs(bits[0] - bits[1]).max()) if seen.any() else 0
    result = {"device": a.device, "spp": a.spp, "pixels": int(reference["reason"].size), "first_call_s": first_s,
              "median_s": {k: statistics.median(v) for k, v in times.items()},
              "min_s": {k: min(v) for k, v in times.items()},
              "speed_up": statistics.median(times["array program"]) / statistics.median(times["compiled"]),
              "reasons_differing": int((fast["reason"] != reference["reason"]).sum()),
              "reasons": np.bincount(reference["reason"].ravel(), minlength=7).tolist(),
              "max_ulp": ulps}
    print(f"first compiled call (compile or cache load) {first_s:.2f} s")
    for k, v in times.items():
        print(f"{k:14s} median {1e3 * statistics.median(v):8.2f} ms  min {1e3 * min(v):8.2f} ms  ({a.repeat} runs)")
    print(f"speed-up {result['speed_up']:.1f}x; reasons differing {result['reasons_differing']} of {result['pixels']} "
          f"(reasons {result['reasons']}); max float32 ulps {ulps}")
    if a.json:
        a.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
