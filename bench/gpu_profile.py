"""Profile of the GPU backend on the Kinect v2 room frame (512 × 424, 16 spp, 5 vertices), for developers.

Prints warm whole-pipeline times (median of 5), a 1-spp pass, the memory pool, a cProfile of one frame
(where host time goes: launches and synchronisation), CPU/GPU agreement at full resolution and the time
to 1 mm estimated depth error. Needs CuPy and a CUDA GPU: ``python bench/gpu_profile.py``.
The benchmark beside the peers is ``bench/bench_gpu.py``.

``PYTHONPATH=. python3 bench/gpu_profile.py --post`` prints only the split of the Kinect frame (16 spp) and of one
1-spp pass into trace and post-trace milliseconds (median of 5 warm renders) with the device allocations
of each part (a counting CuPy allocator), then exits.
"""

import cProfile
import importlib
import io
import pstats
import statistics
import sys
import time

import cupy as cp
import numpy as np

from tofcore import demo_scene, load_preset, render


def sync():
    cp.cuda.Device().synchronize()


def timed(n, **kwargs):
    times, frame = [], None
    for _ in range(n):
        sync()
        t = time.perf_counter()
        frame = render(scene, sensor, device="gpu", **kwargs)
        sync()
        times.append(time.perf_counter() - t)
    return statistics.median(times), times, frame


scene = demo_scene("room")
sensor = load_preset("kinect_v2")


def post_trace_split(n: int = 5) -> None:
    """Trace vs post-trace ms and device allocations per render (16 spp, and 1 spp: one pass)."""
    render_module = importlib.import_module("tofcore.render")
    pool = cp.get_default_memory_pool()
    allocations = {"trace": 0, "post": 0}
    part = ["post"]

    def counting_malloc(size):
        allocations[part[0]] += 1
        return pool.malloc(size)

    original = render_module.trace_progressive

    class Traced:  # the render's passes; the allocations while the tracer runs count as "trace"
        def __init__(self, passes):
            self.passes = passes

        def __iter__(self):
            while True:
                part[0] = "trace"
                try:
                    transport = next(self.passes)
                except StopIteration:
                    return
                finally:
                    part[0] = "post"
                sync()  # the trace's kernels finished before the render reads its clock
                yield transport

        def report(self, report):
            return self.passes.report(report)

        def close(self):
            self.passes.close()

    render_module.trace_progressive = lambda *args, **kwargs: Traced(original(*args, **kwargs))
    cp.cuda.set_allocator(counting_malloc)
    for spp in (16, 1):
        render(scene, sensor, spp=spp, max_depth=5, device="gpu")  # warm
        rows = []
        for _ in range(n):
            allocations.update(trace=0, post=0)
            sync()
            t = time.perf_counter()
            frame = render(scene, sensor, spp=spp, max_depth=5, device="gpu")
            sync()
            total = time.perf_counter() - t
            rows.append((total, frame.stats["trace_seconds"], dict(allocations)))
        total, trace_s, counts = sorted(rows, key=lambda r: r[0])[n // 2]
        print(f"kinect room {spp:2d} spp: whole {total * 1e3:.1f} ms = trace {trace_s * 1e3:.1f} ms + post-trace "
              f"{(total - trace_s) * 1e3:.1f} ms; device allocations: trace {counts['trace']}, "
              f"post-trace {counts['post']}")
    cp.cuda.set_allocator(pool.malloc)
    render_module.trace_progressive = original


if "--post" in sys.argv:
    post_trace_split()
    sys.exit(0)
print("triangles", scene.triangle_count)
t = time.perf_counter()
f = render(scene, sensor, spp=16, max_depth=5, device="gpu")
sync()
print(f"cold first frame {time.perf_counter() - t:.2f} s", f.stats["device"])
med, times, f = timed(5, spp=16, max_depth=5)
print(f"kinect room 16 spp whole pipeline: median {med * 1e3:.1f} ms  all {[round(x * 1e3, 1) for x in times]}")
print(f"  trace {f.stats['trace_seconds'] * 1e3:.1f} ms, rays {f.stats['transport']['rays'] / 1e6:.2f} M, "
      f"valid {f.valid.mean():.3f}, est. error {f.stats['convergence'][-1]['est_depth_error_m'] * 1e3:.2f} mm")
print(f"  memory pool {cp.get_default_memory_pool().total_bytes() / 2**20:.0f} MiB")
med1, _, _ = timed(5, spp=1, max_depth=5)
print(f"1 spp frame: median {med1 * 1e3:.1f} ms")
profile = cProfile.Profile()
profile.enable()
render(scene, sensor, spp=16, max_depth=5, device="gpu")
sync()
profile.disable()
out = io.StringIO()
pstats.Stats(profile, stream=out).sort_stats("tottime").print_stats(30)
print(out.getvalue()[:7000])
fc = render(scene, sensor, spp=2, max_depth=5, device="cpu", seed=3)
fg = render(scene, sensor, spp=2, max_depth=5, device="gpu", seed=3)
scale = np.abs(fc.raw).max(axis=0)
rel = np.abs(fg.raw - fc.raw).max(axis=0) / np.where(scale > 0, scale, 1)
both = fc.valid & fg.valid
print("full-res 2 spp CPU vs GPU: pixels raw rel > 1e-9:", np.mean(rel > 1e-9), "max rel", rel.max(),
      "depth |d| > 1e-6 m:", np.mean(np.abs(fg.depth[both] - fc.depth[both]) > 1e-6),
      "valid differs:", np.mean(fc.valid != fg.valid))
for name in ("corner", "room"):
    t = time.perf_counter()
    fconv = render(demo_scene(name), sensor, spp=1 << 16, max_depth=5, device="gpu", target_error_m=0.001,
                   time_budget_s=40)
    print(f"{name} to 1 mm estimated: {time.perf_counter() - t:.1f} s, spp {fconv.stats['spp']}, "
          f"est. {fconv.stats['convergence'][-1]['est_depth_error_m'] * 1e3:.2f} mm")

# bench_peers' frame (bench/bench_transport.py): trace only, 80 MHz phasor, point LED 2.5 cm beside the lens
import tofcore  # noqa: E402

omega = 2 * np.pi * 80e6
for detail in (10, 101):
    t = time.perf_counter()
    room = demo_scene("room", detail=detail)
    room.bvh
    build = time.perf_counter() - t
    cam = tofcore.Camera.from_fov(512, 424, 70.6, 60.0)
    kwargs = dict(world_from_sensor=tofcore.suggested_pose(room), spp=16, max_depth=5, seed=0, device="gpu",
                  progressive=False, correlations=[lambda tau: np.cos(omega * tau), lambda tau: np.sin(omega * tau)])
    led = [tofcore.LED(position_m=(0.025, 0.0, 0.0))]
    tofcore.trace(room, cam, led, **kwargs)
    times = []
    for _ in range(5):
        sync()
        t = time.perf_counter()
        tr = tofcore.trace(room, cam, led, **kwargs)
        sync()
        times.append(time.perf_counter() - t)
    med = statistics.median(times)
    print(f"bench_peers frame, {room.triangle_count:,} triangles (BVH build {build:.1f} s on the CPU): "
          f"median {med * 1e3:.1f} ms, {tr.stats.rays / 1e6:.1f} M rays, {tr.stats.rays / med / 1e9:.2f} G rays/s, "
          f"all {[round(x * 1e3, 1) for x in times]}")
