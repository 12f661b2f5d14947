"""Where the GPU's post-trace milliseconds go: each stage of the Kinect v2 frame after the trace, timed with the
device synchronised before and after it (so a stage's time is its own kernels' and launches').

Wraps the stages of the trace (set-up, packing and upload, first hits, the frame's sums, the passes: what a
1-spp preview frame spends before its pass) and of :mod:`tofcore.render` (the per-pass error estimate, the camera's images — raw images,
scattering, noise, decoding with the phasor and edge filters —, the per-k ground truth, the read-back) and,
inside the camera's images, the camera's decode and the scattering, renders the demo room at 16 spp and at 1 spp
a few times, and prints the mean of each stage per frame. It does so twice in the same process: with the camera's
decode as the compiled kernels (tofcore.compiled.camera_decode, what renders use) and as the CuPy decoder
(tofcore.sensor.decode.decode: ``camera_decode.unsupported`` patched to refuse everything), and prints the decode's ms both ways.

Usage::

    PYTHONPATH=. python3 bench/gpu_post_stages.py [--repeat 5] [--json $OUT/post_stages.json]
"""

from __future__ import annotations

import argparse
import collections
import importlib
import json
import math
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--json", type=Path)
    a = p.parse_args()
    import cupy as cp

    import tofcore
    from tofcore.compiled import camera_decode
    from tofcore.sensor import optics

    render = importlib.import_module("tofcore.render")
    trace = importlib.import_module("tofcore.tracer.trace")
    compiled_tracer = importlib.import_module("tofcore.compiled.tracer")
    cuda_build = importlib.import_module("tofcore.compiled.cuda")
    stages = importlib.import_module("tofcore.tracer.stages")
    times: dict[str, list[float]] = collections.defaultdict(list)

    def timed(module, name: str, label: str):
        function = getattr(module, name)

        def wrapper(*args, **kwargs):
            cp.cuda.Device().synchronize()
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                cp.cuda.Device().synchronize()
                times[label].append(time.perf_counter() - start)
        setattr(module, name, wrapper)

    decode_labels = ("  camera decode, kernels", "  camera decode, CuPy decoder")
    for module, name, label in ((camera_decode, "decode", decode_labels[0]),
                                (render.decoding, "decode", decode_labels[1]),
                                (render, "render_error", "error estimate"),
                                (render, "_camera_images", "camera images (all below)"),
                                (optics, "apply_scattering", "  lens scattering"),
                                (render, "_decode_clean_per_k", "per-k ground truth"),
                                (render, "_read_back", "read-back"),
                                (render, "_frame", "frame (camera, per-k, read-back)"),
                                (trace, "make_setup", "trace: set-up (scene tables on the device)"),
                                (compiled_tracer, "_choice", "trace: packing and upload"),
                                (cuda_build, "first_hit", "trace: first hits"),
                                (stages, "first_hit", "trace: first hits (array program)"),
                                (trace, "_empty_transport", "trace: the frame's sums"),
                                (cuda_build, "trace_pass", "trace: the passes")):
        timed(module, name, label)

    scene, sensor = tofcore.demo_scene("room"), tofcore.load_preset("kinect_v2")
    unsupported = camera_decode.unsupported
    result = {}
    for decoder in ("kernels", "CuPy decoder"):
        camera_decode.unsupported = unsupported if decoder == "kernels" else (lambda *args: "bench: the CuPy decoder")
        for spp in (16, 1):
            tofcore.render(scene, sensor, spp=spp, max_depth=5, device="gpu")  # warm
            times.clear()
            whole = []
            for _ in range(a.repeat):
                cp.cuda.Device().synchronize()
                start = time.perf_counter()
                tofcore.render(scene, sensor, spp=spp, max_depth=5, device="gpu")
                cp.cuda.Device().synchronize()
                whole.append(time.perf_counter() - start)
            per_frame = {k: 1e3 * sum(v) / a.repeat for k, v in times.items()}
            result[f"{spp} spp, {decoder}"] = dict(per_frame, whole=1e3 * statistics.median(whole))
            print(f"Kinect v2 room, {spp} spp, the camera's decode by the {decoder}, ms per frame (mean of "
                  f"{a.repeat}); whole frame median {1e3 * statistics.median(whole):.1f} ms")
            for k, v in sorted(per_frame.items(), key=lambda kv: -kv[1]):
                print(f"  {k:40s} {v:8.2f}")
    camera_decode.unsupported = unsupported
    for spp in (16, 1):
        kernels, cupy = (result[f"{spp} spp, {d}"] for d in ("kernels", "CuPy decoder"))
        frame = "frame (camera, per-k, read-back)"
        print(f"{spp} spp: the camera's decode {kernels.get(decode_labels[0], math.nan):.2f} ms (kernels) against "
              f"{cupy.get(decode_labels[1], math.nan):.2f} ms (CuPy decoder); the frame after the trace "
              f"{kernels[frame]:.1f} against {cupy[frame]:.1f} ms")
    if a.json:
        a.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
