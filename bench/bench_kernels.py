"""Per-contribution kernels of the tracer, old form against new, side by side in one process.

* Correlation sums: every raw image's g_j(τ) one function at a time (``Modulation.correlations``) against
  the bank that evaluates each frequency's steps as one in-place block (``Modulation.correlation_bank``),
  for every preset, on 65,536 delays spread over 20 m.
* BSDF: ``eval_bsdf`` and ``pdf_bsdf`` called apart against ``eval_pdf_bsdf`` (shared half vector, D,
  Fresnel of cos θo, lobe probability), 65,536 room-like surface points.

Both pairs give the same values bit for bit (checked here too).

    .venv/bin/python bench/bench_kernels.py [--repeat 30]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from tofcore.scene.bsdf import SurfaceParams, eval_bsdf, eval_pdf_bsdf, pdf_bsdf  # noqa: E402
from tofcore.sensor.presets import list_presets, load_preset  # noqa: E402
from tofcore.constants import SPEED_OF_LIGHT_M_S  # noqa: E402

N = 65_536


def milliseconds(function, repeat: int) -> float:
    function()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def unit_rows(rng, n: int, upper: bool = True) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    if upper:
        v[:, 2] = np.abs(v[:, 2])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=30)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    tau = rng.uniform(0.0, 2 * 20.0, N) / SPEED_OF_LIGHT_M_S
    print(f"median of {args.repeat}, {N:,} contributions\n")
    print("| correlation sums | raw images | one function each, ms | bank, ms | speed-up |")
    print("|---|---|---|---|---|")
    for name in list_presets():
        modulation = load_preset(name).modulation
        functions, bank = modulation.correlations(), modulation.correlation_bank()
        assert np.array_equal(bank(tau), np.stack([g(tau) for g in functions]))
        old = milliseconds(lambda: np.stack([g(tau) for g in functions]), args.repeat)
        new = milliseconds(lambda: bank(tau), args.repeat)
        print(f"| {name} | {len(bank)} | {old:.2f} | {new:.2f} | {old / new:.1f}× |")

    params = SurfaceParams(reflectance=rng.uniform(0.3, 0.9, N), roughness=rng.uniform(0.05, 0.6, N),
                           metallic=(rng.random(N) < 0.05).astype(float), ior=np.full(N, 1.5),
                           extinction=np.zeros(N))
    wo, wi = unit_rows(rng, N), unit_rows(rng, N)
    f, pdf = eval_pdf_bsdf(params, wo, wi)
    assert np.array_equal(f, eval_bsdf(params, wo, wi)) and np.array_equal(pdf, pdf_bsdf(params, wo, wi))
    old = milliseconds(lambda: (eval_bsdf(params, wo, wi), pdf_bsdf(params, wo, wi)), args.repeat)
    new = milliseconds(lambda: eval_pdf_bsdf(params, wo, wi), args.repeat)
    print(f"\n| BSDF | eval + pdf apart, ms | eval_pdf_bsdf, ms | speed-up |\n|---|---|---|---|\n"
          f"| 65,536 points | {old:.2f} | {new:.2f} | {old / new:.2f}× |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
