"""Is the coarse-grid difference between tofcore's and mitransient's transient references the binning kernels'?

bench/bench_transient.py compares the two renderers' histograms summed into 10 cm bins. There, the references
agree on every kernel-free quantity (per-pixel sum over the bins, mean path length) but their 10 cm
histograms differ by more than their noise: tofcore's tent splat (half-width one fine bin) spills a narrow
peak lying within half a fine bin of a 10 cm edge into the next coarse bin; mitransient's box does not.

This check renders, on the same set-up (corner, max_depth 4, point LED, the bench's 1 cm grid to 10 m):

* mitransient with 1 cm bins (box),
* tofcore with 1 cm bins (tent, half-width 1 cm: 5 mm ramps at the 10 cm edges when summed),
* tofcore with ``--fine`` (default 1 mm) bins: summed into 10 cm, its ramps shrink to ± half a fine bin, the
  kernel tends to mitransient's box,

and reports ‖r − r_mitransient‖ / ‖r_mitransient‖ on the 10 cm grid for both tofcore references, beside the
noise of the two references. If the kernels explain the difference, the finer tofcore grid closes it down to
the noise. CPU (mitransient on ``llvm_ad_mono``, needs DRJIT_LIBLLVM_PATH)::

    .venv/bin/python bench/transient_kernel_check.py --size 64x53 [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_transient as bt  # noqa: E402
import common as cc  # noqa: E402  (bench_transient puts studies/crosscheck on the path)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", choices=("cpu", "gpu"), default="cpu")
    ap.add_argument("--size", default="64x53")
    ap.add_argument("--max-depth", type=int, default=4)
    ap.add_argument("--bin", type=float, default=0.01)
    ap.add_argument("--bins", type=int, default=1000)
    ap.add_argument("--coarse", type=int, default=10)
    ap.add_argument("--fine", type=int, default=10, help="tofcore's finer grid: this many bins per --bin (default 10)")
    ap.add_argument("--spp", default="tofcore:512,mitransient:4096", help="spp per reference render")
    ap.add_argument("--renders", type=int, default=4)
    ap.add_argument("--mi-batch", type=int, default=1024)
    ap.add_argument("--work", default=str(bt.ROOT / "out" / "bench_transient"))
    ap.add_argument("--json")
    args = ap.parse_args()
    spp = {k: int(v) for k, v in (x.split(":") for x in args.spp.split(","))}
    width, height = (int(x) for x in args.size.lower().split("x"))
    cc.DEVICE = args.device
    s = cc.make_setup("corner", width, height)
    fine = argparse.Namespace(**{**vars(args), "bin": args.bin / args.fine, "bins": args.bins * args.fine,
                                 "coarse": args.coarse * args.fine})
    t0 = time.perf_counter()
    refs = {"mitransient (box, 1 cm)": bt.Reference(bt.MitransientRenderer(s, args), spp["mitransient"],
                                                     args.renders, args, seed0=1_000),
            "tofcore (tent, 1 cm)": bt.Reference(bt.TofcoreRenderer(s, args), spp["tofcore"], args.renders, args,
                                                 seed0=1_000),
            f"tofcore (tent, {args.bin / args.fine * 1e3:g} mm)": bt.Reference(
                bt.TofcoreRenderer(s, fine), spp["tofcore"], args.renders, fine, seed0=2_000)}
    names = list(refs)
    m = refs[names[0]]
    norm = float(np.sqrt((m.coarse ** 2).sum()))
    out = {"size": args.size, "max_depth": args.max_depth, "coarse_m": args.bin * args.coarse,
           "seconds": time.perf_counter() - t0, "references": {}}
    for name in names:
        r = refs[name]
        out["references"][name] = {
            "spp": r.spp, "renders": r.k,
            "rel_difference_to_mitransient_coarse": float(np.sqrt(((r.coarse - m.coarse) ** 2).sum()) / norm),
            "rel_noise_of_both": float(np.sqrt((r.coarse_var + m.coarse_var).sum()) / norm),
            "sum_ratio_to_mitransient": float(r.coarse.sum() / m.coarse.sum())}
    text = json.dumps(out, indent=1)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
