"""The compiled tracer's kernels of several source trees, one process, interleaved: CPU seconds per trace.

Each tree's ``tofcore/compiled/kernels.py`` (with that tree's ``_target.py``) is loaded under its own
module name, as :mod:`tofcore.compiled.cuda` loads the CUDA build, and its ``trace_pixels`` traces the
same packed bench frame (bench_compiled's: room 9.8 k, 16 spp, 5 vertices) on one numba thread, the
trees taking turns, so load from other processes falls on all of them alike. The rest of tofcore (scene,
packing, the NumPy reference) is this tree's. Prints whether every sum and ray count equals the first
tree's and the NumPy tracer's, then per tree the best and median CPU-seconds and the ratios to the first.

Usage (a tree of ``main`` beside this one, e.g. ``git worktree add --detach /tmp/base main``)::

    .venv/bin/python bench/compare_kernels.py /tmp/base . --rounds 16 --resolution 64x53
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def load(name: str, path: Path):
    """Execute the file ``path`` as module ``name``."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def tree_kernels(index: int, tree: Path):
    """``tree``'s kernels.py as module ``tofcore.compiled.kernels_v<index>``, decorated by ``tree``'s _target.py.

    Its machine code is cached in ``tree``'s ``__pycache__/compare-v<index>``, not in the tree's own numba
    cache: code cached under the module name ``kernels_v<index>`` cannot be loaded by a normal import.
    """
    import numba

    import tofcore.compiled._target as own

    compiled = tree / "tofcore" / "compiled"
    before = numba.config.CACHE_DIR
    numba.config.CACHE_DIR = str(compiled / "__pycache__" / f"compare-v{index}")
    sys.modules["tofcore.compiled._target"] = load(f"tofcore.compiled._target_v{index}", compiled / "_target.py")
    try:
        return load(f"tofcore.compiled.kernels_v{index}", compiled / "kernels.py")
    finally:
        sys.modules["tofcore.compiled._target"] = own
        numba.config.CACHE_DIR = before


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("trees", nargs="+", type=Path, help="source trees; ratios are to the first")
    p.add_argument("--rounds", type=int, default=8)
    p.add_argument("--resolution", default="64x53")
    a = p.parse_args()
    import numba

    import tofcore
    from bench_compiled import frame_args, packed_for

    numba.set_num_threads(1)
    width, height = (int(x) for x in a.resolution.split("x"))
    spp = 16
    kernels = [tree_kernels(i, tree.resolve()) for i, tree in enumerate(a.trees)]
    args, kwargs = frame_args(width, height, spp)
    packed = packed_for(args, kwargs)
    os.environ["TOFCORE_TRACER"] = "numpy"
    ref = tofcore.trace(*args, **kwargs, workers=1)
    n = width * height
    scene, settings = packed.scene(), packed.settings()
    pixels = (0, n, np.zeros(n, np.int64), np.full(n, spp, np.int64))

    def run(k):
        out = (np.zeros_like(ref.signal_sum), np.zeros_like(ref.correlation_sum), np.zeros_like(ref.replicate_sum),
               np.zeros_like(ref.ambient_sum), np.zeros((0, 0)), np.zeros((n, 5), np.int64))
        start = time.process_time()
        k.trace_pixels(scene, settings, pixels, out)
        return time.process_time() - start, out

    outs = [run(k)[1] for k in kernels]  # compiles or loads each tree's cache
    numpy_sums = (ref.signal_sum, ref.correlation_sum, ref.replicate_sum)
    print("equal to the first tree:", [all(np.array_equal(x, y) for x, y in zip(outs[0], o)) for o in outs],
          "| first equal to NumPy:", all(np.array_equal(x, y) for x, y in zip(outs[0][:3], numpy_sums)))
    seconds = np.array([[run(k)[0] for k in kernels] for _ in range(a.rounds)]).T
    for tree, s in zip(a.trees, seconds):
        print(f"{str(tree):30s} best {s.min():.3f} s, median {np.median(s):.3f} s; to the first: best/best "
              f"{s.min() / seconds[0].min():.3f}, median of rounds {np.median(s / seconds[0]):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
