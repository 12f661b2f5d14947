"""Which tofcore lines make CuPy compile a kernel (NVRTC) in this process, and for how long: the cold start.

CuPy compiles each elementwise, reduction or raw kernel the first time a machine uses it and caches it in
``CUPY_CACHE_DIR`` (``~/.cupy/kernel_cache``). Run it with an empty cache to see what a fresh machine pays,
or after ``tofcore warmup --device gpu`` to see what the warm-up leaves out::

    CUPY_CACHE_DIR=$(mktemp -d) python3 bench/gpu_cupy_compiles.py warmup      # what the warm-up compiles
    python3 bench/gpu_cupy_compiles.py crosscheck                              # then: what it left out

``warmup`` runs ``tofcore warmup --device gpu``; ``crosscheck`` traces studies/crosscheck's corner (128 × 106,
sine correlations at two frequencies, 4 progressive spp) and reads its correlation image back; ``kinect [SPP]``
renders the demo room through the Kinect v2 preset at 512 × 424 (a batch's frame; 16 spp by default) twice and
says the seconds of each, from this script's start to the first frame, the numba compiles (its ``numba:compile``
event) and the files the two renders added to the kernel caches (``NUMBA_CACHE_DIR`` or ``~/.cache/tofcore``, and
``CUPY_CACHE_DIR``): after ``tofcore warmup --device gpu`` all of them should be 0 (issue 33, item 3)::

    python3 -m tofcore warmup --device gpu && python3 bench/gpu_cupy_compiles.py kinect 64
"""

from __future__ import annotations

import time

SCRIPT_STARTED = time.perf_counter()

import collections  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import traceback  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "studies" / "crosscheck"))


def watch_compiles():
    """Count the NVRTC compiles and their seconds by the three innermost tofcore frames that caused them."""
    import cupy.cuda.compiler as compiler

    name = "_compile_using_nvrtc_no_warning" if hasattr(compiler, "_compile_using_nvrtc_no_warning") \
        else "compile_using_nvrtc"
    original = getattr(compiler, name)
    count, seconds = collections.Counter(), collections.Counter()

    def compile_and_note(*args, **kwargs):
        start = time.perf_counter()
        try:
            return original(*args, **kwargs)
        finally:
            frames = [f for f in traceback.extract_stack() if str(ROOT) in f.filename and __file__ != f.filename]
            where = " <- ".join(f"{Path(f.filename).relative_to(ROOT)}:{f.lineno}" for f in frames[-3:][::-1])
            count[where] += 1
            seconds[where] += time.perf_counter() - start

    setattr(compiler, name, compile_and_note)
    return count, seconds


def main() -> int:
    mode = sys.argv[1] if len(sys.argv) > 1 else "crosscheck"
    count, seconds = watch_compiles()
    start = time.perf_counter()
    if mode == "warmup":
        from tofcore.cli import main as tofcore_main
        tofcore_main(["warmup", "--device", "gpu"])
    elif mode == "crosscheck":
        import common as cc

        import tofcore
        s = cc.make_setup("corner")
        for t in tofcore.trace_progressive(s.scene, s.camera, [s.led], world_from_sensor=s.pose,
                                           correlations=cc.sine_correlations([20e6, 100e6]), spp=4, max_depth=5,
                                           seed=7, device="gpu"):
            tofcore.backend.to_host(t.correlation())
    elif mode == "kinect":
        return kinect(int(sys.argv[2]) if len(sys.argv) > 2 else 16, count, seconds)
    else:
        print(f"usage: {sys.argv[0]} warmup|crosscheck|kinect [SPP]", file=sys.stderr)
        return 2
    print(f"{mode}: {time.perf_counter() - start:.2f} s, {sum(count.values())} NVRTC compiles, "
          f"{sum(seconds.values()):.2f} s in them")
    for where, s in seconds.most_common(25):
        print(f"{s:6.2f} s {count[where]:3d}x  {where}")
    return 0


def _cache_files() -> set[str]:
    """The files of numba's tofcore cache folders and of CuPy's kernel cache."""
    folders = [os.environ.get("NUMBA_CACHE_DIR") or os.path.join(os.environ.get("XDG_CACHE_HOME")
                                                                  or os.path.expanduser("~/.cache"), "tofcore"),
               os.environ.get("CUPY_CACHE_DIR") or os.path.expanduser("~/.cupy/kernel_cache")]
    return {os.path.join(root, name) for folder in folders for root, _, names in os.walk(folder) for name in names}


def kinect(spp: int, count, seconds) -> int:
    """The ``kinect`` mode (module docstring)."""
    from numba.core import event

    numba_compiles = []

    class Listener(event.Listener):
        def on_start(self, e):
            numba_compiles.append(getattr(e.data.get("dispatcher"), "__name__", "?"))

        def on_end(self, e):
            pass

    event.register("numba:compile", Listener())
    before = _cache_files()
    import tofcore
    from tofcore.scene.demo import demo_scene

    scene, sensor = demo_scene("room"), tofcore.load_preset("kinect_v2")
    times = []
    for _ in range(2):
        start = time.perf_counter()
        frame = tofcore.render(scene, sensor, spp=spp, device="gpu")
        times.append(time.perf_counter() - start)
        if len(times) == 1:
            first_done = time.perf_counter() - SCRIPT_STARTED
    added = sorted(_cache_files() - before)
    print(f"kinect room 512 x 424, {spp} spp, {frame.stats['transport']['tracer']} tracer on "
          f"{frame.stats['device']['description']}: first frame {times[0]:.2f} s (script start to first frame "
          f"{first_done:.2f} s), second {times[1]:.2f} s; {sum(count.values())} NVRTC compiles "
          f"({sum(seconds.values()):.2f} s), {len(numba_compiles)} numba compiles, {len(added)} new cache files")
    for name in added[:20]:
        print(f"  new: {name}")
    for where, s in seconds.most_common(10):
        print(f"{s:6.2f} s {count[where]:3d}x  {where}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
