"""Which tofcore lines make CuPy compile a kernel (NVRTC) in this process, and for how long: the cold start.

CuPy compiles each elementwise, reduction or raw kernel the first time a machine uses it and caches it in
``CUPY_CACHE_DIR`` (``~/.cupy/kernel_cache``). Run it with an empty cache to see what a fresh machine pays,
or after ``tofcore warmup --device gpu`` to see what the warm-up leaves out::

    CUPY_CACHE_DIR=$(mktemp -d) python3 bench/gpu_cupy_compiles.py warmup      # what the warm-up compiles
    python3 bench/gpu_cupy_compiles.py crosscheck                              # then: what it left out

``warmup`` runs ``tofcore warmup --device gpu``; ``crosscheck`` traces studies/crosscheck's corner (128 × 106,
sine correlations at two frequencies, 4 progressive spp) and reads its correlation image back.
"""

from __future__ import annotations

import collections
import sys
import time
import traceback
from pathlib import Path

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
    else:
        print(f"usage: {sys.argv[0]} warmup|crosscheck", file=sys.stderr)
        return 2
    print(f"{mode}: {time.perf_counter() - start:.2f} s, {sum(count.values())} NVRTC compiles, "
          f"{sum(seconds.values()):.2f} s in them")
    for where, s in seconds.most_common(25):
        print(f"{s:6.2f} s {count[where]:3d}x  {where}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
