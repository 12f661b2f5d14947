"""GPU throughput beside the peers: tofcore (CuPy), Mitsuba 3 ``cuda_ad_rgb`` and mitransient ``cuda_ad_mono``.

The frame is ``bench/bench_peers.py``'s (its scene set-up, materials and Mitsuba dicts are imported,
not copied): the demo room (``--sizes 10k,1M``: 9,800 and 999,698 triangles), 512 × 424, 16 spp,
path length 5 surface vertices, one point LED 2.5 cm beside the lens, Kinect-like pinhole
(70.6° × 60° FOV).

* **tofcore** — ``tofcore.trace(..., device="gpu", progressive=False)`` with an 80 MHz phasor (2
  correlation functions), as ``bench_transport.py`` traces it; rays counted by the tracer. Timed: the
  trace plus the copy of its correlation image to the host, the device synchronised before and after.
  The BVH is built on the CPU before the clock starts (``build_s``).
* **Mitsuba 3** ``cuda_ad_rgb`` — ``path`` integrator, ``max_depth`` 6 (= 5 surface vertices), no
  Russian roulette, independent sampler, box filter. Timed: ``mi.render`` + ``dr.eval`` +
  ``dr.sync_thread`` + the copy of the image to the host.
* **mitransient** ``cuda_ad_mono`` — ``transient_path`` into a ``phasor_hdr_film`` (14 frequencies,
  16–120 MHz), otherwise as Mitsuba.

Each renderer and size runs in a fresh subprocess: one warm-up render (its time is the *cold first
frame*: kernel compilation, uploads, the peers' acceleration structure), then ``--repeat`` timed
renders (median, min–max). Peak GPU memory: the parent samples the device's used memory (NVML, else
``nvidia-smi``) while the subprocess runs and reports the peak above what was in use before it started
(CUDA context included); for tofcore also the CuPy memory pool's size after the runs.

tofcore alone, with the Kinect v2 preset (``tofcore.load_preset("kinect_v2")``: 512 × 424, its LEDs,
noise, lens scattering; the demo scenes with their suggested poses, default detail, as
``bench/gpu_profile.py`` and docs/benchmarks.md "On the GPU"):

* the whole pipeline of a 16-spp room frame (``render``: trace, raw images, scattering, noise, decoding,
  ground truth per path length) and one 1-spp frame (a progressive pass / preview), median of ``--repeat``;
* the time to 1 mm estimated depth error on the ``corner`` and the ``room``:
  ``render(..., target_error_m=0.001, spp=65536, time_budget_s=--converge-budget)`` after a warm-up
  render of the same scene; ``frame.stats["seconds"]``, ``["spp"]`` and the last convergence row's
  ``est_depth_error_m``.

Rays for the peers are estimated as in ``bench_peers.py``: every path of the closed room has 5
surface vertices; Mitsuba traces 6 closest-hit + 5 shadow rays = 11 per path. "tofcore-equivalent
rays/s" = tofcore's own ray count / the peer's frame time; "tofcore ÷ peer" = the ratio of the median
frame times (> 1: the peer is faster).

On the GPU machine (peers unpacked from ``.peers/``, see ``bench/gpu/fetch_peers.sh``)::

    . bench/gpu/setup_peers.sh && python3 bench/bench_gpu.py --json $OUT/bench_gpu.json --markdown $OUT/bench_gpu.md

CPU smoke test of the same code (tofcore on NumPy; the peers' ``llvm_ad_*`` variants with ``--peers``)::

    python bench/bench_gpu.py --device cpu --peers tofcore --sizes 10k --repeat 1 --spp 1
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import threading
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
for _p in (str(ROOT / "bench"), str(ROOT)):
    if _p not in sys.path:
        sys.path.insert(0, _p)

import bench_peers as bp  # noqa: E402  (scene set-up, LED offset, FOV, sizes, Mitsuba dicts)

PEERS = ("tofcore", "mitsuba", "mitransient")
VARIANTS = {"mitsuba": "ad_rgb", "mitransient": "ad_mono"}   # prefixed with cuda_ / llvm_
CONVERGE_SCENES = ("corner", "room")


# ------------------------------------------------------------------------------------------ helpers
def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0] if text else ''}".rstrip(": ")


def _stats(times: list[float]) -> dict:
    return {"median_s": statistics.median(times), "min_s": min(times), "max_s": max(times), "all_s": times}


def _resolution(text: str) -> tuple[int, int]:
    w, h = (int(x) for x in text.lower().split("x"))
    return w, h


# -------------------------------------------------------------------------------------- tofcore side
class _Tof:
    """tofcore on one device, with a synchronise that is a no-op on the CPU."""

    def __init__(self, device: str):
        import tofcore
        from tofcore import backend
        self.tofcore, self.backend = tofcore, backend
        self.dev = backend.select_device(device)

    def sync(self) -> None:
        if self.dev.is_gpu:
            self.dev.xp.cuda.Device().synchronize()

    def memory(self) -> dict:
        if not self.dev.is_gpu:
            return {}
        cp = self.dev.xp
        pool = cp.get_default_memory_pool()
        free, total = cp.cuda.runtime.memGetInfo()
        return {"cupy_pool_total_mib": pool.total_bytes() / 2**20, "cupy_pool_used_mib": pool.used_bytes() / 2**20,
                "device_used_mib": (total - free) / 2**20, "device_total_mib": total / 2**20}

    def info(self) -> dict:
        import numpy as np
        out = {"device": self.dev.as_dict(), "numpy": np.__version__, "python": platform.python_version()}
        if self.dev.is_gpu:
            out["cupy"] = self.dev.xp.__version__
        return out


def run_tofcore_frame(detail: int, spp: int, max_depth: int, width: int, height: int, repeat: int,
                      device: str) -> dict:
    """bench_peers' frame traced by tofcore: cold first frame, then ``repeat`` timed frames."""
    import numpy as np
    tof = _Tof(device)
    tofcore, backend = tof.tofcore, tof.backend
    t0 = time.perf_counter()
    scene, cam, pose, _led_world = bp._setup(detail, width, height)
    scene.bvh
    build_s = time.perf_counter() - t0
    from tofcore.sensor.modulation import phasor_correlations

    leds = [tofcore.LED(position_m=bp.LED)]
    # cos(ωτ) and sin(ωτ) at bench_peers' frequency, as the kernels know them (tofcore.compiled.setup)
    kwargs = dict(world_from_sensor=pose, spp=spp, max_depth=max_depth, device=tof.dev, progressive=False,
                  correlations=phasor_correlations([bp.FREQ]))

    def one(seed: int):
        tof.sync()
        t = time.perf_counter()
        tr = tofcore.trace(scene, cam, leds, seed=seed, **kwargs)
        backend.to_host(tr.correlation())      # the image on the host, as the peers' np.asarray
        tof.sync()
        return time.perf_counter() - t, tr

    cold, _ = one(0)
    warm, last = [], None
    for i in range(repeat):
        dt, last = one(1 + i)
        warm.append(dt)
    s = last.stats
    return dict({"renderer": "tofcore", "triangles": scene.triangle_count, "build_s": build_s, "cold_s": cold,
                 "frame_s": statistics.median(warm), "frames_s": warm, "rays": s.rays,
                 "camera_rays": s.camera_rays, "bounce_rays": s.bounce_rays, "shadow_rays": s.shadow_rays,
                 "skipped_shadow_rays": s.skipped_shadow_rays, "paths": width * height * spp,
                 "tracer": s.tracer, "tracer_reason": s.tracer_reason},
                **tof.info(), **tof.memory())


def run_tofcore_pipeline(spp: int, max_depth: int, repeat: int, device: str) -> dict:
    """Kinect v2 room: whole-pipeline frame at ``spp`` and a 1-spp frame, medians of ``repeat``."""
    tof = _Tof(device)
    tofcore = tof.tofcore
    sensor = tofcore.load_preset("kinect_v2")
    scene = tofcore.demo_scene("room")
    pose = tofcore.suggested_pose(scene)
    scene.bvh

    def one(n_spp: int, seed: int):
        tof.sync()
        t = time.perf_counter()
        frame = tofcore.render(scene, sensor, pose, spp=n_spp, max_depth=max_depth, seed=seed, device=tof.dev)
        tof.sync()
        return time.perf_counter() - t, frame

    out = {"renderer": "tofcore", "preset": sensor.name, "scene": "room", "triangles": scene.triangle_count,
           "width": sensor.camera.width, "height": sensor.camera.height, "max_depth": max_depth}
    cold, _ = one(spp, 0)
    times, trace_s, frame = [], [], None
    for i in range(repeat):
        dt, frame = one(spp, 1 + i)
        times.append(dt)
        trace_s.append(frame.stats["trace_seconds"])
    conv = frame.stats["convergence"][-1]
    out["full"] = dict(_stats(times), spp=spp, cold_s=cold, trace_median_s=statistics.median(trace_s),
                       rays=frame.stats["transport"]["rays"], est_depth_error_m=conv["est_depth_error_m"],
                       valid_fraction=float(frame.valid.mean()))
    one(1, 100)                                                  # warm-up of the 1-spp pass
    times, trace_s = [], []
    for i in range(repeat):
        dt, frame = one(1, 101 + i)
        times.append(dt)
        trace_s.append(frame.stats["trace_seconds"])
    out["one_spp"] = dict(_stats(times), spp=1, trace_median_s=statistics.median(trace_s),
                          rays=frame.stats["transport"]["rays"])
    out["device_stats"] = frame.stats.get("device")
    return dict(out, **tof.info(), **tof.memory())


def run_tofcore_converge(name: str, max_depth: int, target_m: float, spp_cap: int, budget_s: float,
                         device: str) -> dict:
    """Time to ``target_m`` estimated depth error (Kinect v2, demo scene ``name``), after a warm-up render."""
    tof = _Tof(device)
    tofcore = tof.tofcore
    sensor = tofcore.load_preset("kinect_v2")
    scene = tofcore.demo_scene(name)
    pose = tofcore.suggested_pose(scene)
    scene.bvh
    tofcore.render(scene, sensor, pose, spp=1, max_depth=max_depth, seed=1, device=tof.dev)   # warm-up
    tof.sync()
    t = time.perf_counter()
    frame = tofcore.render(scene, sensor, pose, spp=spp_cap, max_depth=max_depth, seed=0, device=tof.dev,
                           target_error_m=target_m, time_budget_s=budget_s)
    tof.sync()
    wall = time.perf_counter() - t
    est = frame.stats["convergence"][-1]["est_depth_error_m"]
    return dict({"renderer": "tofcore", "preset": sensor.name, "scene": name, "triangles": scene.triangle_count,
                 "target_error_m": target_m, "time_budget_s": budget_s, "spp_cap": spp_cap,
                 "seconds": frame.stats["seconds"], "wall_s": wall, "spp": frame.stats["spp"],
                 "est_depth_error_m": est, "reached": est is not None and est <= target_m,
                 "passes": len(frame.stats["convergence"]),
                 "convergence": [{k: r[k] for k in ("seconds", "spp", "est_depth_error_m")}
                                 for r in frame.stats["convergence"]]},
                **tof.info(), **tof.memory())


# -------------------------------------------------------------------------------------- Mitsuba side
def run_mitsuba(detail: int, spp: int, max_depth: int, width: int, height: int, repeat: int, transient: bool,
                variant: str) -> dict:
    """bench_peers' Mitsuba / mitransient frame on ``variant``: cold first frame, then ``repeat`` timed frames."""
    import numpy as np
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as exc:
        return {"error": f"cannot import Mitsuba ({_first_line(exc)})", "unavailable": True}
    try:
        mi.set_variant(variant)
    except Exception as exc:   # variant not in this build, no CUDA driver / OptiX
        return {"error": f"Mitsuba {mi.__version__}: variant {variant} unusable ({_first_line(exc)})",
                "unavailable": True}
    if transient:
        try:
            import mitransient  # noqa: F401  (registers transient_path and phasor_hdr_film)
        except Exception as exc:
            return {"error": f"cannot import mitransient ({_first_line(exc)})", "unavailable": True}
    scene, cam, pose, led_world = bp._setup(detail, width, height)
    integ, film = bp.mitsuba_integrator_film(transient, max_depth)
    t0 = time.perf_counter()
    sc = bp._mitsuba_scene(mi, scene, cam, pose, led_world, integ, film, spp)
    load_s = time.perf_counter() - t0
    integrator = sc.integrator()

    def one(seed: int) -> float:
        dr.sync_thread()
        t = time.perf_counter()
        img = integrator.render(sc, seed=seed, spp=spp) if transient else mi.render(sc, seed=seed, spp=spp)
        dr.eval(img)
        dr.sync_thread()
        np.asarray(img[1] if transient else img)   # the image on the host
        return time.perf_counter() - t

    cold = one(0)
    warm = [one(1 + i) for i in range(repeat)]
    out = {"renderer": "mitransient" if transient else "mitsuba", "variant": mi.variant(), "version": mi.__version__,
           "drjit": dr.__version__, "triangles": scene.triangle_count, "load_s": load_s, "cold_s": cold,
           "frame_s": statistics.median(warm), "frames_s": warm, "paths": width * height * spp,
           "rays_estimated": width * height * spp * (2 * max_depth + 1), "python": platform.python_version(),
           "numpy": np.__version__}
    if transient:
        import mitransient
        out["mitransient"] = mitransient.__version__
        out["frequencies"] = len(np.asarray(sc.sensors()[0].film().frequencies).ravel())
    return out


# ------------------------------------------------------------------------------------- GPU memory poll
class GpuMemory:
    """Samples the used memory of one GPU in a thread (NVML, else nvidia-smi); ``peak_mib`` above the start."""

    def __init__(self, interval_s: float = 0.02):
        self.interval_s, self._read, self.source = interval_s, None, None
        index = (os.environ.get("CUDA_VISIBLE_DEVICES") or "0").split(",")[0]
        index = int(index) if index.strip().isdigit() else 0
        try:
            import pynvml
            pynvml.nvmlInit()
            handle = pynvml.nvmlDeviceGetHandleByIndex(index)
            self._read = lambda: pynvml.nvmlDeviceGetMemoryInfo(handle).used / 2**20
            self.source = "NVML"
            name = pynvml.nvmlDeviceGetName(handle)
            self.name = name.decode() if isinstance(name, bytes) else str(name)
            drv = pynvml.nvmlSystemGetDriverVersion()
            self.driver = drv.decode() if isinstance(drv, bytes) else str(drv)
            self.total_mib = pynvml.nvmlDeviceGetMemoryInfo(handle).total / 2**20
            return
        except Exception:
            pass
        smi = shutil.which("nvidia-smi")
        if smi:
            def read(query="memory.used"):
                out = subprocess.run([smi, f"--query-gpu={query}", "--format=csv,noheader,nounits", "-i", str(index)],
                                     capture_output=True, text=True, timeout=10, check=True).stdout
                return out.strip().splitlines()[0]
            try:
                self.name, self.driver, total = (x.strip() for x in read("name,driver_version,memory.total").split(","))
                self.total_mib = float(total)
                self._read = lambda: float(read())
                self.source, self.interval_s = "nvidia-smi", max(interval_s, 0.1)
                return
            except Exception:
                pass
        self.name = self.driver = self.total_mib = None

    def info(self) -> dict:
        return {"gpu": self.name, "driver": self.driver, "memory_total_mib": self.total_mib,
                "memory_source": self.source}

    def __enter__(self):
        self.peak_mib = self.base_mib = None
        if self._read is None:
            return self
        self.base_mib = self.peak_mib = self._read()
        self._stop = threading.Event()

        def loop():
            while not self._stop.wait(self.interval_s):
                try:
                    self.peak_mib = max(self.peak_mib, self._read())
                except Exception:
                    pass
        self._thread = threading.Thread(target=loop, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        if self._read is not None:
            self._stop.set()
            self._thread.join()

    @property
    def delta_mib(self) -> float | None:
        return None if self.base_mib is None else self.peak_mib - self.base_mib


# ------------------------------------------------------------------------------------------- driver
def _worker(args) -> dict:
    width, height = _resolution(args.resolution)
    w = args.worker
    if w == "tofcore":
        return run_tofcore_frame(args.detail, args.spp, args.max_depth, width, height, args.repeat, args.device)
    if w == "tofcore_pipeline":
        return run_tofcore_pipeline(args.spp, args.max_depth, args.repeat, args.device)
    if w == "tofcore_converge":
        return run_tofcore_converge(args.scene, args.max_depth, args.target_error, args.converge_spp,
                                    args.converge_budget, args.device)
    if w in VARIANTS:
        return run_mitsuba(args.detail, args.spp, args.max_depth, width, height, args.repeat, w == "mitransient",
                           f"{args.peer_backend}_{VARIANTS[w]}")
    raise SystemExit(f"unknown worker {w}")


def _spawn(args, gpu: GpuMemory, worker: str, extra: list[str], timeout_s: float) -> dict:
    cmd = [args.python, os.path.abspath(__file__), "--worker", worker, "--device", args.device,
           "--peer-backend", args.peer_backend, "--spp", str(args.spp), "--max-depth", str(args.max_depth),
           "--resolution", args.resolution, "--repeat", str(args.repeat)] + extra
    t0 = time.perf_counter()
    with gpu:
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=os.environ)
        except subprocess.TimeoutExpired:
            return {"error": f"timed out after {timeout_s:.0f} s", "wall_s": time.perf_counter() - t0}
    wall = time.perf_counter() - t0
    result = None
    for line in reversed(proc.stdout.strip().splitlines()):
        if line.startswith("{"):
            try:
                result = json.loads(line)
                break
            except json.JSONDecodeError:
                continue
    if result is None:
        tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        result = {"error": f"exit {proc.returncode}: {tail}"}
    if proc.returncode and "error" not in result:
        result["error"] = f"exit {proc.returncode}"
    result["wall_s"] = wall
    result["gpu_peak_mib"] = gpu.delta_mib
    if "error" in result and proc.stderr.strip():
        result["stderr_tail"] = proc.stderr.strip().splitlines()[-15:]
    return result


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="Run on the GPU machine from the repository root after "
                                        "`. bench/gpu/setup_peers.sh`; see the module docstring.")
    ap.add_argument("--peers", default=",".join(PEERS), help="comma list of tofcore, mitsuba, mitransient "
                    "(default: all)")
    ap.add_argument("--sizes", default="10k,1M", help="comma list of 10k, 500k, 1M (default: 10k,1M)")
    ap.add_argument("--repeat", type=int, default=5, help="timed frames per renderer after the warm-up (default 5)")
    ap.add_argument("--spp", type=int, default=16, help="samples per pixel of the peers' frame and of the "
                    "Kinect whole-pipeline frame (default 16)")
    ap.add_argument("--max-depth", type=int, default=5, help="surface vertices per path (default 5)")
    ap.add_argument("--resolution", default="512x424", help="WxH of the peers' frame (default 512x424)")
    ap.add_argument("--device", choices=("gpu", "cpu"), default="gpu",
                    help="tofcore's device; cpu is a smoke test of this script on NumPy (default gpu)")
    ap.add_argument("--peer-backend", choices=("cuda", "llvm"),
                    help="Mitsuba variants cuda_ad_* or llvm_ad_* (default: cuda with --device gpu, else llvm)")
    ap.add_argument("--no-extras", action="store_true", help="skip tofcore's Kinect pipeline, 1-spp and "
                    "convergence runs")
    ap.add_argument("--converge-budget", type=float, help="time_budget_s of each time-to-1-mm render "
                    "(default 60 on the GPU, 10 on the CPU; 0 skips them)")
    ap.add_argument("--target-error", type=float, default=0.001, help="target RMS estimated depth error, m "
                    "(default 0.001)")
    ap.add_argument("--converge-spp", type=int, default=65536, help="spp cap of the convergence renders")
    ap.add_argument("--timeout", type=float, default=150, help="seconds per frame subprocess before it is "
                    "killed (default 150; convergence: budget + this)")
    ap.add_argument("--deadline", type=float, default=420, help="start no run after this many seconds and cut "
                    "the running one there (default 420: the whole benchmark stays under 8 min)")
    ap.add_argument("--python", default=sys.executable, help="Python of the subprocesses (default: this one)")
    ap.add_argument("--json", help="write all results to this JSON file")
    ap.add_argument("--markdown", help="write the tables (Markdown, for docs/benchmarks.md) to this file")
    ap.add_argument("--table", help="print the tables from a JSON written by --json, render nothing")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--detail", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--scene", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.peer_backend is None:
        args.peer_backend = "cuda" if args.device == "gpu" else "llvm"
    if args.converge_budget is None:
        args.converge_budget = 60.0 if args.device == "gpu" else 10.0

    if args.worker:   # one renderer in this process; its JSON is the last line of stdout
        try:
            r = _worker(args)
        except ImportError as exc:
            r = {"error": f"cannot import ({_first_line(exc)})", "unavailable": True}
        except Exception as exc:
            r = {"error": _first_line(exc), "traceback": traceback.format_exc().splitlines()[-8:]}
            if type(exc).__name__ == "GpuUnavailable":    # no CuPy / no CUDA device: skip tofcore's other runs
                r["unavailable"] = True
        print(json.dumps(r, default=float), flush=True)
        return 0

    if args.table:
        with open(args.table) as fh:
            report = json.load(fh)
        text = tables(report)
        print(text)
        return 0

    peers = [p.strip() for p in args.peers.split(",") if p.strip()]
    unknown = [p for p in peers if p not in PEERS]
    sizes = [s.strip() for s in args.sizes.split(",") if s.strip()]
    bad = [s for s in sizes if s not in bp.SIZES]
    if unknown or bad:
        ap.error(f"unknown peers {unknown} or sizes {bad}; peers: {list(PEERS)}, sizes: {list(bp.SIZES)}")

    gpu = GpuMemory()
    started = time.perf_counter()
    report = {"settings": {k: getattr(args, k) for k in ("peers", "sizes", "repeat", "spp", "max_depth", "resolution",
                                                           "device", "peer_backend", "converge_budget",
                                                           "target_error", "converge_spp", "deadline")},
              "machine": dict(gpu.info(), host_python=platform.python_version(), cpus=os.cpu_count(),
                              date=time.strftime("%Y-%m-%d %H:%M:%S")),
              "frames": {}, "extras": {}}

    def log(msg: str) -> None:
        print(f"# [{time.perf_counter() - started:6.1f} s] {msg}", file=sys.stderr, flush=True)

    def save() -> None:   # after every run, so that a cut-off benchmark still leaves its results
        report["total_s"] = time.perf_counter() - started
        if args.json:
            Path(args.json).parent.mkdir(parents=True, exist_ok=True)
            tmp = Path(args.json + ".tmp")
            tmp.write_text(json.dumps(report, indent=1, default=float))
            os.replace(tmp, args.json)
        if args.markdown:
            Path(args.markdown).parent.mkdir(parents=True, exist_ok=True)
            Path(args.markdown).write_text(tables(report) + "\n")

    def spawn(worker: str, extra: list[str], timeout_s: float) -> dict:
        left = args.deadline - (time.perf_counter() - started)
        if left < 5:
            return {"error": f"not started: past the --deadline of {args.deadline:g} s"}
        return _spawn(args, gpu, worker, extra, min(timeout_s, left))

    log(f"GPU: {gpu.name} (driver {gpu.driver}, memory by {gpu.source})" if gpu.source else
        "GPU memory: no NVML or nvidia-smi here; peak GPU memory not measured")
    unavailable: dict[str, str] = {}
    report["unavailable"] = unavailable
    for size in sizes:
        report["frames"][size] = {}
        for p in peers:
            if p in unavailable:
                continue
            r = spawn(p, ["--detail", str(bp.SIZES[size])], args.timeout)
            report["frames"][size][p] = r
            save()
            if r.get("unavailable"):
                unavailable[p] = r["error"]
                log(f"{p}: skipped: {r['error']}")
            elif "error" in r:
                log(f"{size} {p}: FAILED: {r['error']}")
            else:
                log(f"{size} {p}: frame {r['frame_s'] * 1e3:.1f} ms (cold {r['cold_s']:.2f} s, "
                    f"peak GPU {_mib(r.get('gpu_peak_mib'))}, wall {r['wall_s']:.0f} s)")

    if "tofcore" in peers and "tofcore" not in unavailable and not args.no_extras:
        r = spawn("tofcore_pipeline", [], args.timeout)
        report["extras"]["pipeline"] = r
        save()
        if "error" in r:
            log(f"tofcore Kinect pipeline: FAILED: {r['error']}")
        else:
            log(f"tofcore Kinect room {args.spp} spp: {r['full']['median_s'] * 1e3:.1f} ms; "
                f"1 spp: {r['one_spp']['median_s'] * 1e3:.1f} ms")
        if args.converge_budget > 0:
            for name in CONVERGE_SCENES:
                # Shrink the budget rather than be killed at the deadline (start-up + warm-up + final frame: 45 s).
                left = args.deadline - (time.perf_counter() - started) - 45
                budget = min(args.converge_budget, left)
                if left < min(5.0, args.converge_budget):
                    r = {"error": f"not started: too close to the --deadline of {args.deadline:g} s"}
                else:
                    r = spawn("tofcore_converge", ["--scene", name, "--converge-budget", f"{budget:.3g}",
                                                   "--target-error", str(args.target_error),
                                                   "--converge-spp", str(args.converge_spp)],
                              budget + args.timeout)
                report["extras"][f"converge_{name}"] = r
                save()
                if "error" in r:
                    log(f"tofcore time to {args.target_error * 1e3:g} mm, {name}: FAILED: {r['error']}")
                else:
                    log(f"tofcore time to {args.target_error * 1e3:g} mm, {name}: {r['seconds']:.1f} s, "
                        f"{r['spp']} spp, est. {_mm(r['est_depth_error_m'])}")
    save()
    print(tables(report), flush=True)
    return 0


# -------------------------------------------------------------------------------------------- tables
def _mib(x) -> str:
    return "–" if x is None else f"{x:,.0f}"


def _mm(x) -> str:
    return "–" if x is None else f"{x * 1e3:.2f} mm"


def _num(x: float) -> str:
    """Three significant digits, thousands separated."""
    return f"{x:,.0f}" if abs(x) >= 100 else f"{x:.3g}"


def _ms(x) -> str:
    return f"{x * 1e3:.1f}" if x < 10 else f"{x * 1e3:,.0f}"


def tables(report: dict) -> str:
    s, m = report["settings"], report["machine"]
    w, h = _resolution(s["resolution"])
    paths = w * h * s["spp"]
    peer_rays = paths * (2 * s["max_depth"] + 1)
    versions = {}
    for by_peer in report["frames"].values():
        for p, r in by_peer.items():
            if "error" not in r:
                versions.setdefault(p, r)
    label = {"tofcore": f"tofcore {s['device'].upper()}"}
    if "tofcore" in versions:
        t = versions["tofcore"]
        label["tofcore"] += f" (CuPy {t['cupy']})" if t.get("cupy") else f" (NumPy {t.get('numpy')})"
        label["tofcore"] += (", compiled tracer (numba)" if t.get("tracer") == "compiled"
                             else f", array tracer ({t.get('tracer_reason') or 'TOFCORE_TRACER'})")
    for p in ("mitsuba", "mitransient"):
        if p in versions:
            r = versions[p]
            extra = (f", mitransient {r['mitransient']}, {r['frequencies']} phasor frequencies"
                     if p == "mitransient" else "")
            label[p] = f"{p} (Mitsuba {r['version']} `{r['variant']}`{extra})"
    lines = [f"GPU: {m.get('gpu') or 'not read'} (driver {m.get('driver') or '?'}), {m.get('cpus')} CPUs, "
             f"Python {m.get('host_python')}; {m.get('date')}. bench_peers frame: demo room, "
             f"{s['resolution'].replace('x', ' × ')}, {s['spp']} spp, path length {s['max_depth']}, one point LED "
             f"2.5 cm beside the lens; warm frames, median of {s['repeat']} [min–max], each renderer in a fresh "
             f"process.", "",
             "| triangles | renderer | ms / frame | M paths/s | G rays/s (own count) | G tofcore-equiv. rays/s "
             "| tofcore ÷ peer | cold first frame s | peak GPU MiB |",
             "|---|---|---|---|---|---|---|---|---|"]
    for size, by_peer in report["frames"].items():
        tof = by_peer.get("tofcore")
        tof = tof if tof and "error" not in tof else None
        for p, r in by_peer.items():
            if "error" in r:
                if not r.get("unavailable"):
                    lines.append(f"| {size} | {p} | failed: {r['error']} | | | | | | |")
                continue
            f = r["frame_s"]
            frames = r["frames_s"]
            rays = r["rays"] if p == "tofcore" else peer_rays
            equiv = _num(tof["rays"] / f / 1e9) if tof else "–"
            ratio = "1" if p == "tofcore" else (f"{tof['frame_s'] / f:.2f}" if tof else "–")
            mem = _mib(r.get("gpu_peak_mib"))
            if p == "tofcore" and r.get("cupy_pool_total_mib") is not None:
                mem += f" (pool {r['cupy_pool_total_mib']:,.0f})"
            lines.append(f"| {r['triangles']:,} | {label.get(p, p)} | {_ms(f)} [{_ms(min(frames))}–"
                         f"{_ms(max(frames))}] | {_num(paths / f / 1e6)} | {_num(rays / f / 1e9)} | {equiv} "
                         f"| {ratio} | {r['cold_s']:.2f} | {mem} |")
    for p, why in report.get("unavailable", {}).items():
        lines.append(f"| – | {p} | not run: {why} | | | | | | |")
    lines += ["", f"own count: tofcore counts its rays; peers: paths × {2 * s['max_depth'] + 1} (closest-hit + shadow "
              "rays, closed room). tofcore-equiv.: tofcore's ray count / the renderer's frame time. tofcore ÷ peer: "
              "median frame times (> 1: the peer is faster). cold: the first frame in a fresh process (kernel "
              "compilation or disk-cache load, uploads, acceleration structure). Peak GPU: device memory in use "
              "above the level before the process started, context included (sampled); pool: CuPy's memory pool "
              "after the runs."]

    ex = report.get("extras") or {}
    if ex:
        pl = ex.get("pipeline") or {}
        size = f"{pl['width']} × {pl['height']}, " if "width" in pl else ""
        lines += ["", f"tofcore alone, Kinect v2 preset ({size}its LEDs, noise and scattering), demo scenes at their "
                  f"suggested poses, path length {s['max_depth']}:", "", "| frame | time | notes |", "|---|---|---|"]
        pl = ex.get("pipeline")
        if pl and "error" not in pl:
            fl, one = pl["full"], pl["one_spp"]
            lines.append(f"| room ({pl['triangles']:,} triangles), {fl['spp']} spp, whole pipeline | "
                         f"**{_ms(fl['median_s'])} ms** [{_ms(fl['min_s'])}–{_ms(fl['max_s'])}] | trace "
                         f"{_ms(fl['trace_median_s'])} ms, {fl['rays'] / 1e6:.1f} M rays, cold first frame "
                         f"{fl['cold_s']:.2f} s, est. depth error {_mm(fl['est_depth_error_m'])}, peak GPU "
                         f"{_mib(pl.get('gpu_peak_mib'))} MiB |")
            lines.append(f"| the same, one 1-spp frame (a progressive pass) | **{_ms(one['median_s'])} ms** "
                         f"[{_ms(one['min_s'])}–{_ms(one['max_s'])}] | trace {_ms(one['trace_median_s'])} ms |")
        elif pl:
            lines.append(f"| room whole pipeline, 1-spp frame | failed | {pl['error']} |")
        for name in CONVERGE_SCENES:
            c = ex.get(f"converge_{name}")
            if c is None:
                continue
            target = f"{s['target_error'] * 1e3:g} mm"
            if "error" in c:
                lines.append(f"| time to {target} estimated depth error, {name} | failed | {c['error']} |")
            elif c["reached"]:
                lines.append(f"| time to {target} estimated depth error, {name} ({c['triangles']:,} triangles) | "
                             f"**{c['seconds']:.1f} s** | {c['spp']:,} spp, est. {_mm(c['est_depth_error_m'])} |")
            else:
                lines.append(f"| time to {target} estimated depth error, {name} ({c['triangles']:,} triangles) | "
                             f"not reached | {_mm(c['est_depth_error_m'])} after {c['seconds']:.1f} s "
                             f"({c['spp']:,} spp; budget {c['time_budget_s']:g} s) |")
    lines += ["", f"Total {report.get('total_s', 0):.0f} s."]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
