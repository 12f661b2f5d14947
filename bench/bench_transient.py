"""Transient histograms beside mitransient's ``transient_hdr_film``: time to equal error (issue 31).

One scene, one bin grid, both renderers in one process on one device:

* scene: the cross-check's diffuse ``corner`` (``studies/crosscheck/common.py``: the demo geometry written
  to PLY for Mitsuba, exact Lambertian ρ = 0.8, two-sided), 128 × 106 pinhole (Kinect's 70.6° horizontal
  FOV), one isotropic point LED (1 W/sr) 2.5 cm beside the lens, ``--max-depth`` 4 surface vertices
  (Mitsuba ``max_depth`` 5: it counts the camera ray; no Russian roulette in either);
* bins: ``--bins`` 1000 of ``--bin`` 1 cm of optical path length L from 0 (10 m); L is the whole path
  lens → surfaces → LED in both (mitransient: ``camera_unwarp`` off, camera rays start at the 10 µm near
  clip plane of common.py, so L is ≤ 10 µm short; bins are 1 cm).

The two renderers bin differently. mitransient puts a sample's whole weight into the bin it falls in
(``TransientImageBlock.put``: floor((L − start_opl) / bin_width_opl), a box of one bin width); tofcore splits
it between the two nearest bin centres (b + ½)·w (``compiled.kernels.add_transient``: a tent of half-width
w, which keeps Σw and Σw·L). Fine-grid histograms are therefore different quantities (the tent smooths
peaks over two bins and has about 2/3 of the box's variance per bin on smooth signals). So:

* errors are measured on a **coarse grid** (``--coarse`` 10 fine bins summed: 10 cm). Summed, mitransient's
  coarse kernel is the exact 10 cm box and tofcore's the same box with 0.5 cm linear ramps at its edges
  (variance (k − ⅓)/k = 0.967 of the box on smooth signals);
* each renderer's error is against **its own** high-spp reference (K independent renders, seeds apart from
  the measured ones), so the small kernel difference that remains is not counted as error of either; the
  reference's own variance (spread of the K renders / K) is subtracted from the mean squared error
  (E[(x − r)²] = MSE(x) + Var(r) for independent unbiased x, r);
* error = relative RMS: sqrt(Σ_(pixel, coarse bin) (x − r)² − Σ Var r) / ‖r_mitransient‖ (one normaliser for
  both: mitransient's coarse reference);
* "equal error means the same quantity": the two references are compared on what the binning kernels do not
  change — per pixel the sum over bins (steady radiance inside the range) and the mean path length Σ w·L / Σ w
  (mitransient's from bin centres: ± w/2 quantisation, RMS w/√12 per pixel for a narrow peak) — with
  z-scores from the references' spreads; and on the coarse grid (‖r_t − r_m‖ / ‖r_m‖ beside the noise of the
  two references), where what remains beyond noise is the kernels' 0.5 cm edge ramps
  (bench/transient_kernel_check.py: with 1 mm tofcore bins the 10 cm difference falls to the noise).

Timing, per renderer, after a warm-up render of each size (kernels compiled, memory pools filled): the call
until its histogram is complete on the device (device synchronised before and after; tofcore:
``tofcore.trace(..., device=)`` → ``transient_sum``; mitransient: ``integrator.render`` in batches of at
most ``--mi-batch`` spp accumulated on the device, ``dr.eval`` + ``dr.sync_thread``); the download of the
(P, B) histogram to the host is timed apart (``copy_s``, not in the curves). Each spp setting is rendered
``--repeat`` times with other seeds (fewer if slow): median time, RMS over the repeats of the error. Time to
each ``--levels`` relative error is read off each renderer's error-against-time curve (its lower envelope:
a point's time is the least of its own and every later point's; log-log interpolation where it crosses;
else extrapolated from the last point with error ∝ t^(−1/2), marked). Ratio = tofcore's
time / mitransient's.

GPU (one run, peers unpacked by bench/gpu/setup_peers.sh)::

    . bench/gpu/setup_peers.sh && python3 bench/bench_transient.py --device gpu --out $OUT

CPU smoke test (mitransient on ``llvm_ad_mono``: DRJIT_LIBLLVM_PATH, a Mitsuba with LLVM variants)::

    .venv/bin/python bench/bench_transient.py --device cpu --size 32x27 --ref-spp tofcore:256,mitransient:1024 \
        --max-spp tofcore:64,mitransient:1024 --mi-batch 256 --out /tmp/bt

Writes ``bench_transient.json``, ``bench_transient.png`` and ``bench_transient.md`` (the table) in ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
import traceback
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
for _p in (str(ROOT / "studies" / "crosscheck"), str(ROOT)):
    if _p not in sys.path:
        sys.path.insert(0, _p)

import common as cc  # noqa: E402  (the cross-check's scenes, PLY export, Mitsuba dicts)

import tofcore  # noqa: E402
from tofcore import backend  # noqa: E402

RENDERERS = ("tofcore", "mitransient")
STYLES = {"tofcore": ("-o", "tab:blue"), "mitransient": ("--s", "tab:orange"), "tofcore-mc": (":^", "tab:green")}
T00 = time.perf_counter()
DEADLINE = [np.inf]   # perf_counter time after which no render starts (--deadline)


def time_left() -> float:
    return DEADLINE[0] - time.perf_counter()


def log(msg: str) -> None:
    print(f"[{time.perf_counter() - T00:7.1f} s] {msg}", file=sys.stderr, flush=True)


# ------------------------------------------------------------------------------------------- renderers
class TofcoreRenderer:
    """tofcore on ``device``: ``render(spp, seed)`` → (P, B) device sums and their sample count, timed."""

    def __init__(self, s: cc.Setup, args, variant: str = "tofcore"):
        self.s, self.args, self.name = s, args, variant
        self.dev = backend.select_device(args.device)
        self.kwargs = dict(world_from_sensor=s.pose, correlations=[], max_depth=args.max_depth,
                           transient_bin_m=args.bin, transient_max_m=(args.bins - 0.5) * args.bin, device=self.dev)
        if variant == "tofcore-mc":    # plain Monte Carlo: independent uniforms, next-event estimation only
            self.kwargs.update(sampler="independent", light_paths=False)

    warm_max = 16    # passes of at most 16 spp (tofcore.tracer.trace.next_pass_size with progressive=False)

    def sync(self) -> None:
        if self.dev.is_gpu:
            self.dev.xp.cuda.Device().synchronize()

    def render(self, spp: int, seed: int) -> tuple[np.ndarray, float, float, dict]:
        """(P, B) mean histogram on the host, seconds to the histogram on the device, seconds of the copy, info."""
        self.sync()
        t0 = time.perf_counter()
        tr = tofcore.trace(self.s.scene, self.s.camera, [self.s.led], spp=spp, seed=seed, **self.kwargs)
        self.sync()
        t1 = time.perf_counter()
        h = backend.to_host(tr.transient_sum)
        n = backend.to_host(tr.sample_count)
        copy_s = time.perf_counter() - t1
        assert h.shape[1] == self.args.bins, h.shape
        info = {"rays": int(tr.stats.rays), "tracer": tr.stats.tracer, "passes": int(tr.stats.passes),
                "signal": backend.to_host(tr.signal_sum).sum(axis=0) / n}
        return h / n[:, None], t1 - t0, copy_s, info


class MitransientRenderer:
    """mitransient ``transient_path`` into a ``transient_hdr_film`` with the same bins."""

    name = "mitransient"

    def __init__(self, s: cc.Setup, args):
        self.s, self.args = s, args
        mi = cc.mitsuba_setup()          # cc.DEVICE: cuda_ad_mono or llvm_ad_mono; registers mitransient
        import drjit as dr
        import mitransient
        self.mi, self.dr, self.version = mi, dr, (mi.__version__, mitransient.__version__, dr.__version__)
        self.plys = cc.export_plys(s, Path(args.work) / "ply")
        film = {"type": "transient_hdr_film", "temporal_bins": args.bins, "bin_width_opl": args.bin,
                "start_opl": 0.0}
        t0 = time.perf_counter()
        self.scene = mi.load_dict(cc.mitsuba_scene_dict(
            s, self.plys, film=film, spp=args.mi_batch,
            integrator={"type": "transient_path", "max_depth": args.max_depth + 1, "rr_depth": 1000}))
        self.load_s = time.perf_counter() - t0
        self.integrator = self.scene.integrator()
        self.variant = mi.variant()
        self.warm_max = args.mi_batch    # larger renders are batches of this size

    def render(self, spp: int, seed: int) -> tuple[np.ndarray, float, float, dict]:
        dr = self.dr
        per = min(spp, self.args.mi_batch)
        if spp % per:
            raise ValueError(f"mitransient spp {spp} is not a multiple of the batch {per}")
        dr.sync_thread()
        t0 = time.perf_counter()
        acc = steady_acc = None
        assert spp // per <= 64, "at most 64 batches a render (seeds seed·64 + batch)"
        for b in range(spp // per):
            steady, tr = self.integrator.render(self.scene, seed=seed * 64 + b, spp=per)
            acc = tr if acc is None else acc + tr
            steady_acc = steady if steady_acc is None else steady_acc + steady
            dr.eval(acc, steady_acc)
        dr.sync_thread()
        t1 = time.perf_counter()
        h = np.array(acc, dtype=np.float64)            # (H, W, B, 1)
        st = np.array(steady_acc, dtype=np.float64)
        copy_s = time.perf_counter() - t1
        n = spp // per
        h = h.reshape(h.shape[0] * h.shape[1], h.shape[2]) / n
        assert h.shape[1] == self.args.bins, h.shape
        return h, t1 - t0, copy_s, {"signal": st.reshape(-1) / n}


# ------------------------------------------------------------------------------------------- statistics
def coarse(h: np.ndarray, k: int) -> np.ndarray:
    return h.reshape(h.shape[0], -1, k).sum(axis=2)


class Reference:
    """Mean of K independent renders, the variance of that mean per entry, per-pixel moments per render."""

    def __init__(self, r, spp: int, k: int, args, seed0: int, budget_s: float = np.inf):
        fine_sum = fine_sq = None
        coarse_sq = None
        self.sums, self.firsts, self.signals = [], [], []
        centres = (np.arange(args.bins) + 0.5) * args.bin
        seconds = 0.0
        for i in range(k):
            if i >= 2 and seconds / i > time_left() or i >= 4 and seconds * (i + 1) / i > budget_s:
                log(f"{r.name}: reference stops at {i} renders ({seconds:.1f} s; budget {budget_s:g} s)")
                k = i
                break
            h, sec, _, info = r.render(spp, seed0 + i)
            seconds += sec
            hc = coarse(h, args.coarse)
            fine_sum = h.copy() if fine_sum is None else fine_sum + h
            fine_sq = h * h if fine_sq is None else fine_sq + h * h
            coarse_sq = hc * hc if coarse_sq is None else coarse_sq + hc * hc
            self.sums.append(h.sum(axis=1))
            self.firsts.append(h @ centres)
            self.signals.append(info["signal"])
            log(f"{r.name}: reference render {i + 1}/{k} ({spp} spp) {sec:.2f} s")
        self.fine = fine_sum / k
        self.fine_var = np.maximum(fine_sq / k - self.fine ** 2, 0.0) * k / (k - 1) / k
        self.coarse = coarse(self.fine, args.coarse)
        self.coarse_var = np.maximum(coarse_sq / k - self.coarse ** 2, 0.0) * k / (k - 1) / k
        self.sums, self.firsts, self.signals = (np.stack(x) for x in (self.sums, self.firsts, self.signals))
        self.spp, self.k, self.seconds = spp, k, seconds

    def pixel_sum(self):
        """(P,) Σ_b r and the variance of that mean."""
        return self.sums.mean(0), self.sums.var(0, ddof=1) / self.k

    def pixel_mean_length(self):
        """(P,) Σ w·L / Σ w (bin centres) and its variance (from the spread of the K renders' ratios)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            per = self.firsts / self.sums
            return self.firsts.mean(0) / self.sums.mean(0), np.nanvar(per, axis=0, ddof=1) / self.k

    def summary(self, norm: float) -> dict:
        return {"spp": self.spp, "renders": self.k, "seconds": self.seconds,
                "rel_rms_se_coarse": float(np.sqrt(self.coarse_var.sum()) / norm),
                "rel_rms_se_fine": float(np.sqrt(self.fine_var.sum()) / norm),
                "range_share": float(self.sums.mean(0).sum() / max(self.signals.mean(0).sum(), 1e-300))}


def rel_error(x_fine: np.ndarray, ref: Reference, k: int, norm_c: float, norm_f: float) -> dict:
    xc = coarse(x_fine, k)
    mse_c = float(((xc - ref.coarse) ** 2).sum())
    mse_f = float(((x_fine - ref.fine) ** 2).sum())
    return {"coarse_raw": np.sqrt(mse_c) / norm_c, "coarse_sq": (mse_c - float(ref.coarse_var.sum())) / norm_c ** 2,
            "fine_raw": np.sqrt(mse_f) / norm_f, "fine_sq": (mse_f - float(ref.fine_var.sum())) / norm_f ** 2}


def sweep(r, ref: Reference, spps, args, norm_c, norm_f, budget_s: float, seed0: int) -> list[dict]:
    """Renders at each spp (a warm-up, then up to --repeat timed with other seeds) until the budget is spent."""
    rows, start, last = [], time.perf_counter(), None
    for spp in spps:
        left = min(budget_s - (time.perf_counter() - start), time_left())
        guess = None if last is None else last["seconds"] * spp / last["spp"]
        if guess is not None and (2 if spp <= r.warm_max else 1) * guess > left:   # (warm-up +) one timed render
            log(f"{r.name}: stop before {spp} spp (≈ {guess:.2f} s a render, {left:.1f} s of the budget left)")
            break
        if spp <= r.warm_max:                                  # warm-up of this size (above: the same passes
            r.render(spp, seed0 + 999)                         # or batches as the last size warmed up)
        times, copies, errs = [], [], []
        for i in range(args.repeat):
            h, sec, copy_s, _ = r.render(spp, seed0 + 10 * spp + i)
            times.append(sec)
            copies.append(copy_s)
            errs.append(rel_error(h, ref, args.coarse, norm_c, norm_f))
            if sec * (args.repeat - i - 1) > 0.25 * max(left, 0.0) or sec > args.slow_s:
                break
        e = {key: float(np.mean([x[key] for x in errs])) for key in errs[0]}
        row = {"spp": spp, "seconds": statistics.median(times), "all_seconds": times,
               "copy_s": statistics.median(copies), "renders": len(times),
               "rel_error": float(np.sqrt(max(e["coarse_sq"], 0.0))), "rel_error_raw": e["coarse_raw"],
               "rel_error_fine": float(np.sqrt(max(e["fine_sq"], 0.0))), "rel_error_fine_raw": e["fine_raw"]}
        rows.append(row)
        last = row
        log(f"{r.name}: {spp} spp {row['seconds'] * 1e3:.1f} ms (copy {row['copy_s'] * 1e3:.1f} ms, "
            f"{len(times)} renders): rel. error {row['rel_error'] * 100:.3f} % "
            f"(raw {row['rel_error_raw'] * 100:.3f} %, "
            f"fine {row['rel_error_fine'] * 100:.3f} %)")
    return rows


def crossing(t: np.ndarray, e: np.ndarray, target: float) -> float | None:
    """t where e first falls to target, interpolated in log-log; None if it never does."""
    below = np.flatnonzero(e <= target)
    if not len(below):
        return None
    i = below[0]
    if i == 0:
        return float(t[0]) if e[0] == target else None
    return float(np.exp(np.interp(np.log(target), [np.log(e[i]), np.log(e[i - 1])], [np.log(t[i]), np.log(t[i - 1])])))


def time_to(rows: list[dict], target: float, key: str = "rel_error") -> dict | None:
    """Seconds to reach ``target`` on the curve's lower envelope: a point's time is the least time of it and
    every point after it (a longer render that is faster, from timing noise, reaches that error sooner)."""
    rows = [r for r in rows if r[key] > 0]
    if not rows:
        return None
    t = np.minimum.accumulate(np.array([r["seconds"] for r in rows])[::-1])[::-1]
    e = np.array([r[key] for r in rows])
    c = crossing(t, e, target)
    if c is not None:
        return {"seconds": c, "how": "measured"}
    if e[0] < target:     # already below at the first point: extrapolate back from it
        return {"seconds": float(t[0] * (e[0] / target) ** 2), "how": f"below at the first point ({t[0]:.3g} s), "
                "extrapolated back e ∝ t^-1/2"}
    return {"seconds": float(t[-1] * (e[-1] / target) ** 2),
            "how": f"extrapolated e ∝ t^-1/2 from {t[-1]:.3g} s ({e[-1] * 100:.3g} %)"}


def agreement(rt: Reference, rm: Reference, args, norm_c: float) -> dict:
    """How the two references agree on what the binning kernels do not change, and on the coarse grid."""
    st, vst = rt.pixel_sum()
    sm, vsm = rm.pixel_sum()
    lt, vlt = rt.pixel_mean_length()
    lm, vlm = rm.pixel_mean_length()
    ok = (sm > 0) & (st > 0)
    z_sum = (st - sm)[ok] / np.sqrt(vst + vsm)[ok]
    dl = (lt - lm)[ok]
    z_len = dl / np.sqrt(vlt + vlm)[ok]
    diff_c = float(np.sqrt(((rt.coarse - rm.coarse) ** 2).sum()) / norm_c)
    noise_c = float(np.sqrt((rt.coarse_var + rm.coarse_var).sum()) / norm_c)
    diff_f = float(np.sqrt(((rt.fine - rm.fine) ** 2).sum()) / np.sqrt((rm.fine ** 2).sum()))
    return {
        "pixels": int(ok.sum()),
        "sum_over_bins": {"image_mean_tofcore": float(st.mean()), "image_mean_mitransient": float(sm.mean()),
                          "ratio_of_image_means": float(st.sum() / sm.sum()),
                          "rel_rms_pixel_difference": float(np.sqrt(np.mean(((st - sm)[ok] / sm[ok]) ** 2))),
                          "z_mean": float(z_sum.mean()), "z_std": float(z_sum.std()),
                          "frac_abs_z_gt_3": float(np.mean(np.abs(z_sum) > 3))},
        "mean_path_length": {"image_mean_tofcore_m": float(np.mean(lt[ok])),
                             "image_mean_mitransient_m": float(np.mean(lm[ok])),
                             "mean_difference_mm": float(dl.mean() * 1e3),
                             "rms_difference_mm": float(np.sqrt(np.mean(dl ** 2)) * 1e3),
                             "bin_quantisation_rms_mm": float(args.bin / np.sqrt(12) * 1e3),
                             "z_mean": float(np.nanmean(z_len)), "z_std": float(np.nanstd(z_len))},
        "coarse_histogram": {"rel_difference": diff_c, "rel_noise_of_both_references": noise_c},
        "fine_histogram_rel_difference": diff_f,
    }


# ------------------------------------------------------------------------------------------- report
def table(res: dict) -> str:
    s = res["settings"]
    lines = [f"{res['machine']}; {s['scene']} {s['size']}, max_depth {s['max_depth']} surface vertices, "
             f"{s['bins']} bins of {s['bin'] * 100:g} cm from 0 (errors on {s['coarse']}-bin sums = "
             f"{s['bin'] * s['coarse'] * 100:g} cm), each renderer against its own reference.", "",
             "| relative RMS error | " + " | ".join(f"{w} s" for w in res["renderers"]) + " | tofcore ÷ mitransient |",
             "|---|" + "---|" * (len(res["renderers"]) + 1)]
    for lev, tt in res["time_to"].items():
        cells = []
        for w in res["renderers"]:
            x = tt.get(w)
            cells.append("–" if x is None else
                         f"{x['seconds']:.3g}" + ("" if x["how"] == "measured" else " (extrap.)"))
        ratio = tt.get("ratio_tofcore_over_mitransient")
        lines.append(f"| {lev} | " + " | ".join(cells) + f" | {'–' if ratio is None else f'{ratio:.2f}×'} |")
    lines += ["", "| renderer | spp | s | rel. error % | fine-grid % |", "|---|---|---|---|---|"]
    for w in res["renderers"]:
        for r in res["curves"][w]:
            lines.append(f"| {w} | {r['spp']} | {r['seconds']:.4f} | {r['rel_error'] * 100:.3f} | "
                         f"{r['rel_error_fine'] * 100:.3f} |")
    return "\n".join(lines)


def plot(res: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12.5, 5))
    for w in res["renderers"]:
        rows = res["curves"][w]
        if not rows:
            continue
        style, color = STYLES.get(w, ("-", "k"))
        t = np.array([r["seconds"] for r in rows])
        n = np.array([r["spp"] for r in rows])
        e = np.array([r["rel_error"] for r in rows]) * 100
        ax.plot(t, e, style, color=color, ms=4, label=w)
        bx.plot(n, e, style, color=color, ms=4, label=w)
        for lev, tt in res["time_to"].items():
            x = tt.get(w)
            if x is not None:
                ax.plot([x["seconds"]], [float(lev.rstrip("%"))], "x", color=color, ms=8)
    for a in (ax, bx):
        for lev in res["time_to"]:
            a.axhline(float(lev.rstrip("%")), color="k", lw=0.6)
        a.set_xscale("log")
        a.set_yscale("log")
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=8)
        coarse_cm = res["settings"]["bin"] * res["settings"]["coarse"] * 100
        a.set_ylabel(f"relative RMS error of the transient histogram, % ({coarse_cm:g} cm bins)")
    s = res["settings"]
    ax.set_xlabel(f"wall time per render, s ({res['machine_short']})")
    bx.set_xlabel("samples per pixel")
    ax.set_title(f"{s['scene']} {s['size']}, {s['max_depth']} vertices, {s['bins']} × {s['bin'] * 100:g} cm bins; "
                 "x: time to each level", fontsize=9)
    bx.set_title("the same against spp (each against its own reference)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ------------------------------------------------------------------------------------------- main
def powers(lo: int, hi: int) -> list[int]:
    out, n = [], lo
    while n <= hi:
        out.append(n)
        n *= 2
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", choices=("gpu", "cpu"), default="gpu")
    ap.add_argument("--scene", default="corner", choices=sorted(cc.ALBEDO))
    ap.add_argument("--size", default="128x106")
    ap.add_argument("--max-depth", type=int, default=4, help="surface vertices per path (default 4)")
    ap.add_argument("--bin", type=float, default=0.01, help="bin width, m of optical path length (default 0.01)")
    ap.add_argument("--bins", type=int, default=1000, help="bins from 0 (default 1000: 10 m)")
    ap.add_argument("--coarse", type=int, default=10, help="fine bins summed into one for the errors (default 10)")
    ap.add_argument("--renderers", default="mitransient,tofcore", help="mitransient, tofcore, tofcore-mc (in this "
                    "order: load, warm-up and reference of each, then the sweeps)")
    ap.add_argument("--ref-spp", default="tofcore:4096,mitransient:32768", help="spp of each reference render")
    ap.add_argument("--ref-renders", type=int, default=8, help="independent renders per reference (default 8)")
    ap.add_argument("--ref-budget", type=float, default=30.0, help="seconds of reference renders per renderer "
                    "(at least 4 renders; default 30)")
    ap.add_argument("--max-spp", default="tofcore:4096,mitransient:32768", help="largest spp of the sweeps")
    ap.add_argument("--min-spp", default="tofcore:1,mitransient:4")
    ap.add_argument("--mi-batch", type=int, default=4096, help="mitransient spp per render call (default 4096)")
    ap.add_argument("--repeat", type=int, default=3, help="timed renders per spp (fewer when slow)")
    ap.add_argument("--slow-s", type=float, default=2.0, help="one timed render only above this many seconds")
    ap.add_argument("--sweep-budget", type=float, default=50.0, help="seconds of sweep per renderer (default 50)")
    ap.add_argument("--deadline", type=float, default=270.0, help="seconds from the start after which no render "
                    "starts; the figure and table are still written (default 270)")
    ap.add_argument("--levels", default="20,10,5,2,1", help="relative RMS errors, %% (default 20,10,5,2,1)")
    ap.add_argument("--out", default="out/bench_transient")
    ap.add_argument("--work", default=str(ROOT / "out" / "bench_transient"), help="PLY files")
    ap.add_argument("--replot", action="store_true", help="recompute times, table and figure from the JSON")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    levels = [float(x) for x in args.levels.split(",")]
    if args.replot:
        res = json.loads((out / "bench_transient.json").read_text())
        finish(res, levels, out)
        return 0
    DEADLINE[0] = T00 + args.deadline
    if args.bins % args.coarse:
        ap.error("--bins must be a multiple of --coarse")
    per = {k: int(v) for k, v in (x.split(":") for x in args.ref_spp.split(","))}
    hi = {k: int(v) for k, v in (x.split(":") for x in args.max_spp.split(","))}
    lo = {k: int(v) for k, v in (x.split(":") for x in args.min_spp.split(","))}
    width, height = (int(x) for x in args.size.lower().split("x"))
    cc.DEVICE = args.device
    s = cc.make_setup(args.scene, width, height)
    s.scene.bvh
    names = [w.strip() for w in args.renderers.split(",") if w.strip()]
    machine = f"{platform.node()}, {os.cpu_count()} CPUs"
    try:
        if args.device == "gpu":
            import cupy
            p = cupy.cuda.runtime.getDeviceProperties(0)
            machine = f"{p['name'].decode()}, {os.cpu_count()} CPUs"
    except Exception:
        pass
    res = {"command": " ".join([Path(sys.executable).name] + sys.argv), "machine": machine,
           "machine_short": machine.split(",")[0], "date": time.strftime("%Y-%m-%d %H:%M:%S"),
           "settings": {"scene": args.scene, "size": args.size, "max_depth": args.max_depth, "bin": args.bin,
                        "bins": args.bins, "coarse": args.coarse, "device": args.device, "mi_batch": args.mi_batch,
                        "repeat": args.repeat, "ref_renders": args.ref_renders, "sweep_budget": args.sweep_budget,
                        "light": "point LED 1 W/sr, 2.5 cm beside the lens", "albedo": list(s.albedo)},
           "versions": {"numpy": np.__version__, "python": platform.python_version()},
           "renderers": [], "curves": {}, "references": {}, "cold": {}, "errors": {}}

    def save():
        (out / "bench_transient.json").write_text(json.dumps(res, indent=1, default=float))

    renderers, refs = {}, {}
    for w in names:   # load + warm-up + reference of every renderer first: the normaliser is mitransient's
        try:
            t0 = time.perf_counter()
            r = MitransientRenderer(s, args) if w == "mitransient" else TofcoreRenderer(s, args, w)
            if w == "mitransient":
                res["versions"].update(dict(zip(("mitsuba", "mitransient", "drjit"), r.version)), variant=r.variant)
            _, cold_s, _, info = r.render(lo[w], 12345)
            res["cold"][w] = {"first_render_s": cold_s, "with_load_s": time.perf_counter() - t0}
            if w != "mitransient":
                res["cold"][w].update(tracer=info["tracer"])
                if args.device == "gpu":
                    res["versions"]["cupy"] = r.dev.xp.__version__
            log(f"{w}: first render ({lo[w]} spp) {cold_s:.2f} s (with set-up {res['cold'][w]['with_load_s']:.2f} s)")
            refs[w] = Reference(r, per.get(w, per.get("tofcore")), args.ref_renders,
                                args, seed0=1_000_000, budget_s=args.ref_budget)
            renderers[w] = r
        except Exception as exc:
            res["errors"][w] = f"{type(exc).__name__}: {exc}"
            log(f"{w}: FAILED: {exc}\n{traceback.format_exc()}")
        save()
    norm_ref = refs.get("mitransient") or next(iter(refs.values()), None)
    if norm_ref is None:
        return 1
    norm_c = float(np.sqrt((norm_ref.coarse ** 2).sum()))
    norm_f = float(np.sqrt((norm_ref.fine ** 2).sum()))
    res["normaliser"] = {"renderer": "mitransient" if "mitransient" in refs else next(iter(refs)),
                         "coarse_norm": norm_c, "fine_norm": norm_f}
    for w, ref in refs.items():
        res["references"][w] = ref.summary(norm_c)
        log(f"{w}: reference {res['references'][w]}")
    if "tofcore" in refs and "mitransient" in refs:
        res["agreement"] = agreement(refs["tofcore"], refs["mitransient"], args, norm_c)
        log(f"references agree: {json.dumps(res['agreement'], indent=1)}")
    save()
    for w, r in renderers.items():
        try:
            res["curves"][w] = sweep(r, refs[w], powers(lo[w], hi[w]), args, norm_c, norm_f, args.sweep_budget,
                                     seed0=0)
            res["renderers"].append(w)
        except Exception as exc:
            res["errors"][w + " sweep"] = f"{type(exc).__name__}: {exc}"
            log(f"{w}: sweep FAILED: {exc}\n{traceback.format_exc()}")
        save()
    res["total_s"] = time.perf_counter() - T00
    finish(res, levels, out)
    return 0


def finish(res: dict, levels: list[float], out: Path) -> None:
    res["time_to"] = {}
    for lev in levels:
        tt = {w: time_to(res["curves"][w], lev / 100) for w in res["renderers"]}
        tt = {w: v for w, v in tt.items() if v is not None}
        if "tofcore" in tt and "mitransient" in tt:
            tt["ratio_tofcore_over_mitransient"] = tt["tofcore"]["seconds"] / tt["mitransient"]["seconds"]
        res["time_to"][f"{lev:g}%"] = tt
    (out / "bench_transient.json").write_text(json.dumps(res, indent=1, default=float))
    text = table(res)
    (out / "bench_transient.md").write_text(text + "\n")
    print(text, flush=True)
    try:
        plot(res, out / "bench_transient.png")
    except Exception as exc:   # no matplotlib: the JSON and the table are still written
        log(f"plot failed: {exc}")


if __name__ == "__main__":
    sys.exit(main())
