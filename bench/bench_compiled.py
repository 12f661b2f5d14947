"""The compiled tracer (tofcore.compiled): CPU threads against the NumPy reference, and the CUDA spike.

The bench_peers frame (demo room, 9,800 triangles, 512 × 424, 16 spp, 5 surface vertices, one point LED
2.5 cm beside the lens, an 80 MHz phasor) traced by

* ``--cpu-threads 1,2,16``: the compiled tracer on that many numba threads (``tofcore.trace``,
  ``TOFCORE_TRACER=compiled``), wall seconds of the trace; with ``--numpy`` also the NumPy tracer;
* ``--kernels``: CPU-seconds per call of the compiled kernels on one thread — traversal of 200,000 random
  rays inside the room (against ``BVH.intersect`` on the same rays), any-hit traversal of 200,000 shadow
  rays between two random points, ``eval_bsdf``, ``sample_bsdf``, a Sobol' pair;
* ``--gpu``: the same source compiled by numba.cuda (:mod:`tofcore.compiled.cuda`), one thread per pixel:
  the cold first call (compilation) and the median of ``--repeat`` warm frames, kernel and whole call;
  first checked against the CPU tracer on a small frame (``--check``), sums compared as
  tests/tofcore/test_compiled.py compares them.

Usage::

    .venv/bin/python bench/bench_compiled.py --kernels
    .venv/bin/python bench/bench_compiled.py --cpu-threads 1,2 --numpy --spp 16 [--json out.json]
    python3 bench/bench_compiled.py --gpu --check --repeat 5 --cpu-threads 16 --json $OUT/compiled.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def frame_args(width: int, height: int, spp: int, detail: int = 10, max_depth: int = 5):
    import tofcore
    from tofcore.sensor.modulation import phasor_correlations

    scene = tofcore.demo_scene("room", detail=detail)
    camera = tofcore.Camera.from_fov(width, height, 70.6, 60.0)
    return (scene, camera, [tofcore.LED(position_m=(0.025, 0.0, 0.0))]), dict(
        world_from_sensor=tofcore.suggested_pose(scene), correlations=phasor_correlations([80e6]), spp=spp,
        max_depth=max_depth, seed=0)


def cpu_trace(tracer: str, threads: int, args, kwargs) -> dict:
    import tofcore

    os.environ["TOFCORE_TRACER"] = tracer
    start, cpu = time.perf_counter(), time.process_time()
    t = tofcore.trace(*args, **kwargs, workers=threads)
    return {"tracer": t.stats.tracer, "threads": threads, "seconds": time.perf_counter() - start,
            "cpu_seconds_this_process": time.process_time() - cpu, "trace_seconds": t.stats.seconds,
            "setup_seconds": t.stats.setup_seconds, "rays": t.stats.rays, "transport": t}


def packed_for(args, kwargs):
    """The compiled tracer's arrays for a frame (the context the CPU tracer builds)."""
    from tofcore import backend
    from tofcore.compiled import setup
    from tofcore.tracer.setup import TraceSettings, make_setup

    settings = TraceSettings(world_from_sensor=kwargs["world_from_sensor"], correlations=kwargs["correlations"],
                             max_depth=kwargs["max_depth"], seed=kwargs["seed"])
    return setup.pack(make_setup(*args, settings, backend.select_device("cpu")))


def same(a: dict, b) -> dict:
    """How far the GPU sums are from the CPU transport's (the tolerance of tests/tofcore/test_compiled.py)."""
    out = {}
    for name in ("signal_sum", "correlation_sum", "replicate_sum"):
        x, y = getattr(b, name), a[name]
        close = np.isclose(x, y, rtol=1e-9, atol=1e-12 * max(np.abs(x).max(), 1e-300))
        out[name] = {"share_close": float(close.mean()), "bit_equal": float((x == y).mean()),
                     "total_rel": float(abs(y.sum() - x.sum()) / abs(x.sum()))}
    return out


def kernel_costs(n: int = 200_000) -> dict:
    """CPU-seconds per call (ns) of the compiled kernels on one thread, and of the NumPy traversal."""
    import numba

    import tofcore
    from tofcore import rng
    from tofcore.compiled import kernels as k
    from tofcore.compiled import setup
    from tofcore.tracer.surface import MaterialTable

    scene = tofcore.demo_scene("room", detail=10)
    geo = setup.scene_arrays(scene, MaterialTable(scene))
    r = np.random.default_rng(0)
    lo, hi = scene.bounds
    o = (lo + (hi - lo) * (0.1 + 0.8 * r.random((n, 3)))).astype(np.float32)
    d = r.normal(size=(n, 3))
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)

    to = (lo + (hi - lo) * (0.1 + 0.8 * r.random((n, 3)))).astype(np.float32)  # shadow rays: o → to
    shadow = (to - o).astype(np.float64)
    length = np.linalg.norm(shadow, axis=1)
    shadow = (shadow / length[:, None]).astype(np.float32)
    length = length.astype(np.float32)
    no_limit = np.full(n, np.inf, np.float32)

    @numba.njit
    def traverse(geo, o, d, t_max, any_hit):
        hits = 0
        work = (np.zeros(k.N_COUNTERS, np.int64), np.empty(k.STACK_SIZE, np.int64), np.empty(k.STACK_T_SIZE, np.float32),
                np.zeros(1))
        for i in range(o.shape[0]):
            h = k.intersect(geo, (o[i, 0], o[i, 1], o[i, 2]), (d[i, 0], d[i, 1], d[i, 2]), t_max[i], -1,
                            any_hit, work)
            hits += h[1] >= 0
        return hits

    @numba.njit
    def bsdf(n, sample):
        total = 0.0
        params = k.surface_params(0.5, 0.5, 0.0, 1.52, 0.0, 0.0, 0.0)
        for i in range(n):
            c = 0.1 + 0.8 * (i % 1000) / 1000.0
            wo = (np.sqrt(1.0 - c * c), 0.0, c)
            if sample:
                total += k.sample_bsdf(params, wo, (i % 997) / 997.0, (i % 991) / 991.0, (i % 983) / 983.0)[1]
            else:
                total += k.eval_bsdf(params, wo, (0.0, np.sqrt(0.75), 0.5))
        return total

    @numba.njit
    def sobol(key, n):
        total = 0.0
        for i in range(n):
            u, v = k.sample_2d(key, i, i % 16, 3, False)
            total += u + v
        return total

    key = rng.seed_key(1)
    jobs = {"traversal (compiled)": lambda: traverse(geo, o, d, no_limit, False),
            "any-hit traversal of shadow rays between two random points (compiled)":
                lambda: traverse(geo, o, shadow, length, True),
            "eval_bsdf": lambda: bsdf(n, False),
            "sample_bsdf": lambda: bsdf(n, True), "Sobol' pair": lambda: sobol(key, n),
            "traversal (NumPy BVH.intersect, 1 thread)": lambda: scene.bvh.intersect(o, d, workers=1)}
    out = {}
    for name, job in jobs.items():
        job()  # compile / warm
        start = time.process_time()
        job()
        out[name + " ns"] = 1e9 * (time.process_time() - start) / n
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cpu-threads", default="", help="comma list of numba thread counts for the CPU tracer")
    p.add_argument("--numpy", action="store_true", help="also time the NumPy tracer")
    p.add_argument("--numpy-workers", type=int, default=2, help="its worker processes (1: all in this process)")
    p.add_argument("--kernels", action="store_true", help="CPU-seconds per call of the compiled kernels")
    p.add_argument("--gpu", action="store_true", help="time the numba.cuda build of the same kernels")
    p.add_argument("--check", action="store_true", help="compare the GPU sums with the CPU tracer's first")
    p.add_argument("--repeat", type=int, default=5, help="warm GPU frames (median reported)")
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--resolution", default="512x424")
    p.add_argument("--json", default=None, help="write the results here")
    a = p.parse_args()
    width, height = (int(x) for x in a.resolution.split("x"))
    args, kwargs = frame_args(width, height, a.spp)
    results: dict = {"frame": f"room 9.8k, {width}x{height}, {a.spp} spp, 5 vertices"}
    for threads in [int(x) for x in a.cpu_threads.split(",") if x]:
        r = cpu_trace("compiled", threads, args, kwargs)
        r.pop("transport")
        results[f"compiled_cpu_{threads}"] = r
        print(json.dumps(r), flush=True)
    if a.kernels:
        results["kernels"] = kernel_costs()
        print(json.dumps(results["kernels"]), flush=True)
    if a.numpy:
        r = cpu_trace("numpy", a.numpy_workers, args, kwargs)
        r.pop("transport")
        results[f"numpy_cpu_{a.numpy_workers}"] = r
        print(json.dumps(r), flush=True)
    if a.gpu:
        from tofcore.compiled import cuda

        start = time.perf_counter()
        cuda.load_kernels()
        if a.check:
            small_args, small_kwargs = frame_args(64, 53, 4, detail=4)
            ref = cpu_trace("numpy", 2, small_args, small_kwargs)["transport"]
            got = cuda.trace_frame(packed_for(small_args, small_kwargs), small_args[0].bvh, 64 * 53, 4)
            results["check_64x53_4spp"] = same(got, ref)
            results["check_64x53_4spp"]["counters"] = [int(x) for x in got["counters"]]
            results["check_64x53_4spp"]["counters_numpy"] = [ref.stats.camera_rays, ref.stats.bounce_rays,
                                                              ref.stats.shadow_rays, ref.stats.light_rays,
                                                              ref.stats.skipped_shadow_rays]
            print(json.dumps(results["check_64x53_4spp"]), flush=True)
        packed, bvh = packed_for(args, kwargs), args[0].bvh
        first = cuda.trace_frame(packed, bvh, width * height, a.spp)
        results["gpu_cold_s"] = time.perf_counter() - start
        runs = [cuda.trace_frame(packed, bvh, width * height, a.spp) for _ in range(a.repeat)]
        cuda.PROFILE = True  # one more frame with a synchronisation after every stage: where the time goes
        cuda.STAGE_SECONDS.clear()
        cuda.trace_frame(packed, bvh, width * height, a.spp)
        cuda.PROFILE = False
        results["gpu_stage_ms"] = {k: round(1e3 * v, 2) for k, v in cuda.STAGE_SECONDS.items()}
        results["gpu_one_spp_ms"] = 1e3 * statistics.median(
            cuda.trace_frame(packed, bvh, width * height, 1)["kernel_s"] for _ in range(a.repeat))
        results["gpu_kernel_ms"] = 1e3 * statistics.median(r["kernel_s"] for r in runs)
        results["gpu_call_ms"] = 1e3 * statistics.median(r["seconds"] for r in runs)
        results["gpu_rays"] = int(first["counters"][:4].sum())
        print(json.dumps({k: v for k, v in results.items() if k.startswith("gpu")}), flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
