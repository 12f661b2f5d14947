"""Route (c) of issue 32's spike: what float32 would buy the scalar CPU shading.

The traversal is float32 already; the shading and path state are float64. On x86 a scalar float32 add,
multiply or fused multiply-add costs what the float64 one does (same latency, same port), so a float32
scalar tracer gains only where the operation itself is cheaper in float32: the C library's transcendental
functions (``cosf`` against ``cos`` …), division and square root. This times those operations in numba,
one call per element of an array of arguments in the shading's ranges, ns per call, float64 and float32
in turn (best of ``--repeat``), and prints the saving they could bring to a profile's libm share.

    .venv/bin/python bench/bench_float32_libm.py --repeat 7
"""

import argparse
import math
import time

import numpy as np
from numba import njit


def _kernel(op):
    """A jitted loop that sums op(x) over x (the sum keeps LLVM from dropping the calls)."""
    @njit(cache=False)
    def run(x):
        acc = x[0] - x[0]
        for i in range(x.shape[0]):
            acc += op(x[i])
        return acc
    return run


OPS = {  # name → (scalar function, argument range as in the shading)
    "cos": (njit(lambda v: math.cos(v)), (0.0, 40.0)),        # 2πfτ for τ up to ~25 ns at 80 MHz
    "sincos": (njit(lambda v: math.sin(v) + math.cos(v)), (0.0, 40.0)),
    "acos": (njit(lambda v: math.acos(v)), (-1.0, 1.0)),       # Oren–Nayar's angles
    "exp": (njit(lambda v: math.exp(v)), (-30.0, 0.0)),       # Beckmann's exp(−tan²θ/α²)
    "tan": (njit(lambda v: math.tan(v)), (0.0, 1.5)),
    "sqrt": (njit(lambda v: math.sqrt(v)), (0.0, 4.0)),
    "divide": (njit(lambda v: v / (v + v * v)), (0.1, 4.0)),   # every operand of the type under test
}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=1_000_000)
    p.add_argument("--repeat", type=int, default=7)
    a = p.parse_args()
    rng = np.random.default_rng(0)
    print(f"{'op':8s} {'float64 ns':>10s} {'float32 ns':>10s} {'f64/f32':>8s}")
    for name, (op, (lo, hi)) in OPS.items():
        run = _kernel(op)
        x64 = rng.uniform(lo, hi, a.n)
        x32 = x64.astype(np.float32)
        best = {}
        for x in (x64, x32):
            run(x[:10])  # compile
            times = []
            for _ in range(a.repeat):
                start = time.perf_counter()
                run(x)
                times.append(time.perf_counter() - start)
            best[x.dtype] = min(times) / a.n * 1e9
        f64, f32 = best[np.dtype(np.float64)], best[np.dtype(np.float32)]
        print(f"{name:8s} {f64:10.2f} {f32:10.2f} {f64 / f32:8.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
