"""RMS depth error against wall time, tofcore beside mitransient, on the same scenes (issue 6, item 3).

One command (bench venv, see README.md here)::

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 \\
        .venv-bench/bin/python studies/crosscheck/error_vs_time.py [--out studies/crosscheck/results]

Scenes: the demo ``corner`` and ``room`` geometry with Lambertian materials (``common.py``; the room's
metal box becomes diffuse ρ = 0.6), one point LED 2.5 cm beside the lens, 128 × 106 pinhole, Kinect's
70.6° FOV, path length 5 surface vertices, sine modulation. Depth = radial distance from the phasor
of one frequency (80 MHz in the figure; 16 and 120 MHz in the JSON); the error of a pixel is
c/(4πf) · arg(P · conj P_ref), so phase wrapping does not matter.

* reference: mitransient, ``--ref-batches`` independent renders of 1024 spp each (seeds apart from the
  measured runs), averaged. Its own per-pixel variance (spread of the batches / K) is subtracted from
  the mean squared error of every measured image (E[(x − r)²] = MSE(x) + Var(r) for an independent
  unbiased r), so a reference that is not fully converged does not put a floor under the curves.
  Both the raw and the corrected RMS are written.
* tofcore: ``trace_progressive`` (passes of 1, 1, 2, 4, 8, 16, 16, … spp); after every pass the
  wall time since the call (minus the time this script spends evaluating) and the error.
* mitransient: separate renders at 16, 64, 256, 1024, … spp (above 1024 spp as 1024-spp batches,
  seeds 0, 1, …), each timed after a warm-up render of the same size (the JIT kernels are cached;
  the cold first-call times are in the JSON).

Both use all cores (tofcore: 2 worker threads; Dr.Jit: its thread pool). Time to 1 mm: where a
curve crosses it, else the fit error = a · t^(−1/2) over the second half of the curve, extrapolated.
Writes ``error_vs_time.json`` and ``error_vs_time.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common as cc  # noqa: E402

import tofcore  # noqa: E402

FREQS = (16e6, 80e6, 120e6)
MAIN = 1   # index of the plotted frequency (80 MHz)
BATCH = 1024


def errors(p: np.ndarray, ref: np.ndarray, ref_var: np.ndarray, mask: np.ndarray) -> dict:
    """RMS of c/(4πf)·arg(P conj P_ref) over the mask, raw and with the reference variance subtracted (m)."""
    out = {}
    for i, f in enumerate(FREQS):
        e = cc.C / (4 * np.pi * f) * np.angle(p[i] * np.conj(ref[i]))
        mse = float(np.mean(e[mask] ** 2))
        corr = mse - float(np.mean(ref_var[i][mask]))
        out[f"{f / 1e6:.0f}MHz"] = {"rms_raw_m": float(np.sqrt(mse)), "rms_m": float(np.sqrt(max(corr, 0.0))),
                                    "median_abs_m": float(np.median(np.abs(e[mask])))}
    return out


def reference(r: cc.MitransientRenderer, batches: int, log) -> tuple[np.ndarray, np.ndarray, float]:
    """Mean phasors of ``batches`` × 1024-spp mitransient renders and the per-pixel variance of the mean distance."""
    ps, seconds = [], 0.0
    for b in range(batches):
        p, _, sec = r.render(seed=100_000 + b, spp=BATCH)
        ps.append(p)
        seconds += sec
        if b % 8 == 7:
            log(f"reference batch {b + 1}/{batches}: {seconds:.0f} s")
    ps = np.stack(ps)
    ref = ps.mean(axis=0)
    scale = cc.C / (4 * np.pi * np.asarray(FREQS))[:, None, None]
    d = scale * np.angle(ps * np.conj(ref)[None])
    var = d.var(axis=0, ddof=1) / batches
    return ref, var, seconds


def run_tofcore(s: cc.Setup, spp: int, ref, ref_var, mask, log) -> list[dict]:
    rows, spent_eval = [], 0.0
    t0 = time.perf_counter()
    for t in tofcore.trace_progressive(s.scene, s.camera, [s.led], world_from_sensor=s.pose,
                                       correlations=cc.sine_correlations(FREQS), spp=spp, max_depth=5, seed=7):
        now = time.perf_counter()
        e0 = now
        p = cc.phasors_from_correlation(t.correlation())
        row = {"seconds": now - t0 - spent_eval, "spp": int(t.sample_count[0]), "rays": int(t.stats.rays),
               "errors": errors(p, ref, ref_var, mask)}
        rows.append(row)
        spent_eval += time.perf_counter() - e0
        q = row["errors"][f"{FREQS[MAIN] / 1e6:.0f}MHz"]
        log(f"{s.name}: tofcore {row['spp']} spp {row['seconds']:.1f} s: RMS {q['rms_m'] * 1e3:.2f} mm "
            f"(raw {q['rms_raw_m'] * 1e3:.2f})")
    return rows


def run_mitransient(r: cc.MitransientRenderer, spps, ref, ref_var, mask, log) -> tuple[list[dict], dict]:
    rows, cold = [], {}
    for spp in spps:
        per = min(spp, BATCH)
        n = spp // per
        t_c = time.perf_counter()
        r.render(seed=50_000 + spp, spp=per)            # warm-up (compiles the kernels for this size)
        cold[str(per)] = time.perf_counter() - t_c
        acc, seconds = 0, 0.0
        for b in range(n):
            p, _, sec = r.render(seed=b, spp=per)
            acc = acc + p
            seconds += sec
        row = {"seconds": seconds, "spp": spp, "errors": errors(acc / n, ref, ref_var, mask)}
        rows.append(row)
        q = row["errors"][f"{FREQS[MAIN] / 1e6:.0f}MHz"]
        log(f"{r.name}: mitransient {spp} spp {seconds:.2f} s: RMS {q['rms_m'] * 1e3:.2f} mm "
            f"(raw {q['rms_raw_m'] * 1e3:.2f})")
    return rows, cold


def _crossing(x: np.ndarray, e: np.ndarray, target: float) -> float | None:
    """x where e first falls to target, interpolated in log-log; None if it never does."""
    below = np.flatnonzero(e <= target)
    if not len(below):
        return None
    i = below[0]
    if i == 0:
        return float(x[0])
    return float(np.exp(np.interp(np.log(target), [np.log(e[i]), np.log(e[i - 1])],
                                  [np.log(x[i]), np.log(x[i - 1])])))


def time_to(res: dict, key: str, target_m: float = 1e-3) -> dict:
    """Wall time at which each renderer's RMS error reaches target.

    Both renderers use the same estimator (same error at the same spp, see the error-vs-spp panel),
    so the spp needed is taken from whichever curve reaches the target, else extrapolated with
    e ∝ spp^(−1/2) from the point with the most spp of either renderer. A renderer whose own curve
    crosses the target gets its measured time; otherwise that spp × its seconds per spp at its
    last point (the pass schedule makes time linear in spp).
    """
    curves = {}
    for who in ("tofcore", "mitransient"):
        rows = [r for r in res[who] if r["errors"][key]["rms_m"] > 0]
        curves[who] = (np.array([r["spp"] for r in rows], float), np.array([r["seconds"] for r in rows]),
                       np.array([r["errors"][key]["rms_m"] for r in rows]))
    spp_need, how = None, ""
    for who in ("mitransient", "tofcore"):
        spp, _, e = curves[who]
        c = _crossing(spp, e, target_m)
        if c is not None and (spp_need is None or c < spp_need):
            spp_need, how = c, f"measured on the {who} curve"
    if spp_need is None:
        who = max(curves, key=lambda w: curves[w][0][-1])
        spp, _, e = curves[who]
        spp_need = float(spp[-1] * (e[-1] / target_m) ** 2)
        how = f"extrapolated e ∝ spp^-1/2 from {who} at {spp[-1]:.0f} spp ({e[-1] * 1e3:.2f} mm)"
    out = {"spp": spp_need, "spp_how": how}
    for who, (spp, t, e) in curves.items():
        c = _crossing(t, e, target_m)
        if c is not None:
            out[who] = {"seconds": c, "how": "measured"}
        else:
            out[who] = {"seconds": spp_need * t[-1] / spp[-1], "how": f"{spp_need:.0f} spp × {t[-1] / spp[-1]:.4g} s/spp",
                        "seconds_per_spp": t[-1] / spp[-1]}
    out["ratio_tofcore_over_mitransient"] = out["tofcore"]["seconds"] / out["mitransient"]["seconds"]
    return out


def plot(results: dict, out: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    key = f"{FREQS[MAIN] / 1e6:.0f}MHz"
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 5.2), gridspec_kw={"width_ratios": [1.35, 1]})
    colors = {"corner": "tab:blue", "room": "tab:red"}
    for name, r in results.items():
        c = colors.get(name, "k")
        tt = r["time_to_1mm"]
        for who, style in (("tofcore", "-o"), ("mitransient", "--s")):
            rows = r[who]
            t = np.array([x["seconds"] for x in rows])
            n = np.array([x["spp"] for x in rows])
            e = np.array([x["errors"][key]["rms_m"] for x in rows]) * 1e3
            ax.plot(t, e, style, color=c, ms=3.5, lw=1.3, label=f"{name}: {who}")
            bx.plot(n, e, style, color=c, ms=3.5, lw=1.3, label=f"{name}: {who}")
            if tt[who]["how"] != "measured":
                ax.plot([t[-1], tt[who]["seconds"]], [e[-1], 1.0], ":", color=c, lw=1)
            ax.plot([tt[who]["seconds"]], [1.0], "x" if who == "tofcore" else "+", color=c, ms=9)
        if not tt["spp_how"].startswith("measured"):
            m = r["mitransient"][-1]
            bx.plot([m["spp"], tt["spp"]], [m["errors"][key]["rms_m"] * 1e3, 1.0], ":", color=c, lw=1)
    for a in (ax, bx):
        a.axhline(1.0, color="k", lw=0.8)
        a.set_xscale("log")
        a.set_yscale("log")
        a.grid(True, which="both", alpha=0.3)
    ax.set_xlabel("wall time, s (2 cores, shared machine; 128 × 106 pixels)")
    ax.set_ylabel(f"RMS depth error at {FREQS[MAIN] / 1e6:.0f} MHz, mm (vs reference)")
    ax.set_title("Error against run time, same scene, estimator and path length (5)\n"
                 "dotted: to 1 mm at the spp the shared error-vs-spp curve needs (× tofcore, + mitransient)",
                 fontsize=9)
    ax.legend(fontsize=8)
    bx.set_xlabel("samples per pixel")
    bx.set_title("the same errors against spp: one curve per scene (same estimator)", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "error_vs_time.png", dpi=100)
    plt.close(fig)


def report(results: dict) -> None:
    key = f"{FREQS[MAIN] / 1e6:.0f}MHz"
    for name, res in results.items():
        tt = res["time_to_1mm"]
        print(f"\n{name} ({res['pixels']} pixels; reference {res['reference']['spp']} spp, "
              f"its RMS SE {res['reference']['rms_se_m'][key] * 1e3:.2f} mm at {key}); 1 mm needs "
              f"{tt['spp']:.0f} spp ({tt['spp_how']}):")
        for who in ("tofcore", "mitransient"):
            last = res[who][-1]
            print(f"  {who:12s} last point {last['spp']} spp {last['seconds']:.1f} s RMS "
                  f"{last['errors'][key]['rms_m'] * 1e3:.2f} mm; 1 mm at {tt[who]['seconds']:.0f} s ({tt[who]['how']})")
        print(f"  time to 1 mm, tofcore / mitransient: {tt['ratio_tofcore_over_mitransient']:.1f}x")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="corner,room")
    ap.add_argument("--tofcore-spp", default="corner:512,room:128", help="most spp per scene (progressive)")
    ap.add_argument("--mitransient-spp", default="corner:16,64,256,1024,4096,16384;room:16,64,256,1024,2048",
                    help="spp settings per scene")
    ap.add_argument("--ref-batches", default="corner:32,room:16", help="reference 1024-spp batches per scene")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"))
    ap.add_argument("--replot", action="store_true", help="recompute the 1 mm times and the figure from the JSON")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.replot:
        with open(out / "error_vs_time.json") as fh:
            data = json.load(fh)
        for res in data["scenes"].values():
            res["time_to_1mm"] = time_to(res, f"{FREQS[MAIN] / 1e6:.0f}MHz")
        with open(out / "error_vs_time.json", "w") as fh:
            json.dump(data, fh, indent=1)
        plot(data["scenes"], out)
        report(data["scenes"])
        return 0
    t_spp = {k: int(v) for k, v in (x.split(":") for x in args.tofcore_spp.split(","))}
    m_spp = {k: [int(s) for s in v.split(",")] for k, v in (x.split(":") for x in args.mitransient_spp.split(";"))}
    refb = {k: int(v) for k, v in (x.split(":") for x in args.ref_batches.split(","))}
    t00 = time.perf_counter()

    def log(msg):
        print(f"[{time.perf_counter() - t00:7.1f} s] {msg}", file=sys.stderr, flush=True)

    mi = cc.mitsuba_setup()
    import mitransient
    results = {}
    for name in args.scenes.split(","):
        s = cc.make_setup(name)
        r = cc.MitransientRenderer(s, FREQS, BATCH, cc.WORK / "ply", max_depth=5)
        r.name = name
        ref, ref_var, ref_s = reference(r, refb[name], log)
        mask = np.abs(ref[0]) > 0
        res = {"reference": {"renderer": "mitransient", "spp": refb[name] * BATCH, "seconds": ref_s,
                             "rms_se_m": {f"{f / 1e6:.0f}MHz": float(np.sqrt(np.mean(ref_var[i][mask])))
                                          for i, f in enumerate(FREQS)}},
               "pixels": int(mask.sum())}
        log(f"{name}: reference {res['reference']}")
        # Alternate the two renderers' long runs as little as possible: tofcore first, then mitransient.
        res["tofcore"] = run_tofcore(s, t_spp[name], ref, ref_var, mask, log)
        res["mitransient"], res["mitransient_cold_seconds"] = run_mitransient(r, m_spp[name], ref, ref_var, mask, log)
        res["time_to_1mm"] = time_to(res, f"{FREQS[MAIN] / 1e6:.0f}MHz")
        res["load_avg_1min_after"] = os.getloadavg()[0]
        results[name] = res
        with open(out / "error_vs_time.json", "w") as fh:
            json.dump({"command": " ".join([Path(sys.executable).name] + sys.argv),
                       "versions": {"mitsuba": mi.__version__, "mitransient": getattr(mitransient, "__version__", "?"),
                                    "numpy": np.__version__, "python": platform.python_version()},
                       "frequencies_hz": FREQS, "plotted_hz": FREQS[MAIN], "resolution": [128, 106],
                       "scenes": results}, fh, indent=1)
    plot(results, out)
    report(results)
    print(f"wrote {out}/error_vs_time.json, error_vs_time.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
