"""The BVH node test of the compiled CPU kernels, vector against scalar: ``kernels.slab_test`` (the four
children's slab tests as LLVM vector instructions) against the same tests one child at a time, on 200,000
random node records (planes with 1 % NaN and 1 % inf), one thread; checks the hit masks and entry distances
are bit for bit the same, then times both in turn.

    .venv/bin/python bench/bench_slab_test.py [--rounds 5]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "tofcore"))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--nodes", type=int, default=200_000)
    a = p.parse_args()
    from test_kernel_twins import random_nodes, slab_tests

    vector, scalar = slab_tests()
    args = random_nodes(np.random.default_rng(1), a.nodes)
    got, ref = vector(*args), scalar(*args)
    same = bool((got[0] == ref[0]).all() and np.array_equal(got[1].view(np.int32), ref[1].view(np.int32)))
    print(f"{a.nodes} node tests: masks and entry distances bit for bit the same: {same}")
    best = {"vector": np.inf, "scalar": np.inf}
    for _ in range(a.rounds):
        for name, f in (("vector", vector), ("scalar", scalar)):
            start = time.perf_counter()
            f(*args)
            best[name] = min(best[name], time.perf_counter() - start)
    print(f"best of {a.rounds}: vector {1e3 * best['vector']:.2f} ms, scalar {1e3 * best['scalar']:.2f} ms "
          f"({best['scalar'] / best['vector']:.1f}x)")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
