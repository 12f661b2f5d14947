"""Where the compiled CUDA path tracer's time goes (issue 21, for developers; needs numba-cuda and a GPU).

Times the bench_peers frame (room 9.8k, 512 × 424, 16 spp, 5 vertices) traced by
:mod:`tofcore.compiled.cuda` for several register limits and block sizes, prints each build's registers
and local memory per thread, and times closest-hit camera rays alone through the same traversal
(rays/s, to set beside the hand-written CUDA traversal's 7.3 G rays/s in NOTES-gpu.md)::

    python3 bench/gpu/probe_megakernel.py --registers none,128,64 --json $OUT/probe.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_compiled import frame_args, packed_for  # noqa: E402
from numba import cuda, float32, int64  # noqa: E402


def build_camera_rays(k):
    from tofcore.compiled.layout import N_COUNTERS, STACK_SIZE

    @cuda.jit
    def camera_rays(scene, key, n_pix, prims):
        i = cuda.grid(1)
        if i >= prims.shape[0]:
            return
        work = (cuda.local.array(N_COUNTERS, int64), cuda.local.array(STACK_SIZE, int64),
                cuda.local.array(STACK_SIZE, float32), cuda.local.array(1, float32))
        origin, direction = k.camera_start(scene, (key, i % n_pix, i // n_pix, False))
        prim, u, v = k.next_hit(scene[0], origin, direction, 1, -1, work)
        prims[i] = prim

    return camera_rays


def kernel_resources(kernel) -> dict:
    out = {}
    for name in ("get_regs_per_thread", "get_local_mem_per_thread", "get_shared_mem_per_block",
                 "get_max_threads_per_block"):
        try:
            value = getattr(kernel, name)()  # numba-cuda: {signature: value} over the compiled signatures
            out[name[4:]] = [int(v) for v in value.values()] if isinstance(value, dict) else int(value)
        except Exception as exc:  # the API differs between numba-cuda versions
            out[name[4:]] = repr(exc)[:80]
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--registers", default="none,128,64")
    p.add_argument("--blocks", default="64,128,256")
    p.add_argument("--resolution", default="512x424")
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--json", default=None)
    a = p.parse_args()
    from tofcore.compiled import cuda as compiled_cuda

    width, height = (int(x) for x in a.resolution.split("x"))
    n_pix = width * height
    args, kwargs = frame_args(width, height, a.spp)
    packed = packed_for(args, kwargs)
    results: dict = {"frame": f"room 9.8k, {a.resolution}, {a.spp} spp"}
    for reg in a.registers.split(","):
        limit = None if reg == "none" else int(reg)
        start = time.perf_counter()
        first = compiled_cuda.trace_frame(packed, n_pix, a.spp, 128, limit)
        row = {"cold_s": time.perf_counter() - start, "rays": int(first["counters"][:4].sum())}
        row.update(kernel_resources(compiled_cuda.load_kernels(limit)[1]))
        for tpb in (int(x) for x in a.blocks.split(",")):
            runs = [compiled_cuda.trace_frame(packed, n_pix, a.spp, tpb, limit)["kernel_s"] for _ in range(a.repeat)]
            row[f"kernel_ms_tpb{tpb}"] = 1e3 * statistics.median(runs)
        results[f"registers_{reg}"] = row
        print(reg, json.dumps(row), flush=True)

    module, _ = compiled_cuda.load_kernels(None)
    camera_rays = build_camera_rays(module)
    dev = cuda.to_device
    scene = (tuple(dev(x) for x in packed.geo), dev(packed.cam), dev(packed.cam_table), dev(packed.frame),
             tuple(dev(x) for x in packed.leds), dev(packed.corr_kinds), dev(packed.corr_table))
    n = n_pix * a.spp
    prims = cuda.device_array(n, dtype="int64")
    start = time.perf_counter()
    camera_rays[(n + 127) // 128, 128](scene, packed.key, n_pix, prims)
    cuda.synchronize()
    cold = time.perf_counter() - start
    times = []
    for _ in range(a.repeat):
        start = time.perf_counter()
        camera_rays[(n + 127) // 128, 128](scene, packed.key, n_pix, prims)
        cuda.synchronize()
        times.append(time.perf_counter() - start)
    t = statistics.median(times)
    results["camera_rays"] = {"rays": n, "ms": 1e3 * t, "rays_per_s": n / t, "cold_s": cold,
                              "hit_share": float((prims.copy_to_host() >= 0).mean()),
                              **kernel_resources(camera_rays)}
    print("camera rays", json.dumps(results["camera_rays"]), flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
