"""RMS depth error against wall time, tofcore beside mitransient, on the same scenes (issues 6 and 10).

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
  Both the raw and the corrected RMS are written. ``--tofcore-ref scene:spp`` uses a tofcore render
  instead (light vertices, seed apart, its variance from its replicates) where mitransient's own
  reference cannot converge in useful time (the room's fireflies); the JSON records how that
  reference agrees with mitransient's (z-scores of the phasor differences).
* tofcore: ``trace_progressive`` (passes of 1, 1, 2, 4, 8, 16, 16, … spp) after a warm-up trace of
  the same set-up (4 spp; as mitransient's warm-up render, it keeps the process's first-use costs —
  kernel loading, the GPU's first allocations — out of the estimator's curve: bench/bench_gpu.py
  reports the cold first frame); after every pass the wall time since the call (minus the time this
  script spends evaluating) and the error. Two
  variants: ``tofcore`` — the estimator of issue 10 (scrambled Sobol' replicates, light vertices with
  MIS, adaptive sampling driven by the replicates' 80 MHz depth error) — and ``tofcore-mc``, plain
  Monte Carlo (independent uniforms, next-event estimation only, uniform spp), as before issue 10.
* mitransient: separate renders at 16, 64, 256, 1024, … spp (above 1024 spp as 1024-spp batches,
  seeds 0, 1, …), each timed after a warm-up render of the same size (the JIT kernels are cached;
  the cold first-call times are in the JSON).

Both use all cores (tofcore: 2 worker threads; Dr.Jit: its thread pool). Time to 5 mm and to 1 mm,
per renderer from its own curve: where it crosses, else extrapolated from its last point with
error ∝ t^(−1/2) (optimistic for curves that fall more slowly, such as mitransient's in the room).
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
import tofcore.tracer.estimator  # noqa: E402

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


VARIANTS = {"tofcore": dict(sampler="sobol", light_paths=True, adaptive=True),
            "tofcore-mc": dict(sampler="independent", light_paths=False, adaptive=False)}


def depth_sigma(t, f_hz: float) -> np.ndarray:
    """(H, W) standard error (m) of the depth of one frequency from the tracer's replicates (delta method)."""
    means, counts = (tofcore.backend.to_host(x) for x in t.replicate_means())
    i = FREQS.index(f_hz)
    p = means[:, 1 + 2 * i] + 1j * means[:, 2 + 2 * i]               # (R, H, W) replicate phasors
    centre = p.mean(axis=0)
    dphi = np.angle(p * np.conj(centre)[None])
    r = p.shape[0]
    var = (dphi ** 2).sum(axis=0) / (r * (r - 1))
    sigma = cc.C / (4 * np.pi * f_hz) * np.sqrt(var)
    return np.where((counts.min(axis=0) >= 1) & (np.abs(centre) > 0), sigma, np.nan)


def run_tofcore(s: cc.Setup, spp: int, ref, ref_var, mask, log, variant: str = "tofcore") -> list[dict]:
    settings = VARIANTS[variant]

    def allocate(t, n):
        return tofcore.tracer.estimator.allocate_samples(depth_sigma(t, FREQS[MAIN]),
                                                         tofcore.backend.to_host(t.sample_count), n)

    def passes(n_spp: int):
        return tofcore.trace_progressive(s.scene, s.camera, [s.led], world_from_sensor=s.pose,
                                         correlations=cc.sine_correlations(FREQS), spp=n_spp, max_depth=5, seed=7,
                                         sampler=settings["sampler"], light_paths=settings["light_paths"],
                                         allocate=allocate if settings["adaptive"] else None, device=cc.DEVICE)

    for _ in passes(4):  # warm-up, as mitransient's warm-up render: the process's first-use costs are not
        pass             # the estimator's (bench/bench_gpu.py reports the cold first frame)
    rows, spent_eval = [], 0.0
    t0 = time.perf_counter()
    for t in passes(spp):
        now = time.perf_counter()
        e0 = now
        p = cc.phasors_from_correlation(tofcore.backend.to_host(t.correlation()))
        row = {"seconds": now - t0 - spent_eval, "spp": float(t.sample_count.mean()), "rays": int(t.stats.rays),
               "errors": errors(p, ref, ref_var, mask)}
        rows.append(row)
        spent_eval += time.perf_counter() - e0
        q = row["errors"][f"{FREQS[MAIN] / 1e6:.0f}MHz"]
        log(f"{s.name}: {variant} {row['spp']:.0f} spp {row['seconds']:.1f} s: RMS {q['rms_m'] * 1e3:.2f} mm "
            f"(raw {q['rms_raw_m'] * 1e3:.2f})")
    return rows


def tofcore_reference(s: cc.Setup, spp: int, log) -> tuple[np.ndarray, np.ndarray, float]:
    """A tofcore reference (light vertices, QMC, uniform spp, seed apart): phasors and per-pixel distance variance."""
    t0 = time.perf_counter()
    t = tofcore.trace(s.scene, s.camera, [s.led], world_from_sensor=s.pose, correlations=cc.sine_correlations(FREQS),
                      spp=spp, max_depth=5, seed=123_456, progressive=False, light_paths=True, device=cc.DEVICE)
    seconds = time.perf_counter() - t0
    log(f"{s.name}: tofcore reference {spp} spp in {seconds:.0f} s")
    ref = cc.phasors_from_correlation(tofcore.backend.to_host(t.correlation()))
    var = np.stack([depth_sigma(t, f) ** 2 for f in FREQS])
    return ref, np.nan_to_num(var), seconds


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


TARGETS_M = (5e-3, 1e-3)
RENDERERS = ("tofcore", "tofcore-mc", "mitransient")


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


def time_to(res: dict, key: str, target_m: float) -> dict:
    """Wall time at which each renderer's RMS error reaches ``target_m``, from its own curve.

    Measured where the curve crosses the target, else extrapolated from its last point with
    error ∝ t^(−1/2). Ratios are tofcore's time over mitransient's.
    """
    out = {}
    for who in RENDERERS:
        rows = [r for r in res.get(who, []) if r["errors"][key]["rms_m"] > 0]
        if not rows:
            continue
        t = np.array([r["seconds"] for r in rows])
        e = np.array([r["errors"][key]["rms_m"] for r in rows])
        c = _crossing(t, e, target_m)
        if c is not None:
            out[who] = {"seconds": c, "how": "measured"}
        else:
            out[who] = {"seconds": float(t[-1] * (e[-1] / target_m) ** 2),
                        "how": f"extrapolated e ∝ t^-1/2 from {t[-1]:.1f} s ({e[-1] * 1e3:.2f} mm)"}
    for who in ("tofcore", "tofcore-mc"):
        if who in out and "mitransient" in out:
            out[f"ratio_{who}_over_mitransient"] = out[who]["seconds"] / out["mitransient"]["seconds"]
    return out


STYLES = {"tofcore": "-o", "tofcore-mc": ":^", "mitransient": "--s"}


def plot(results: dict, out: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    key = f"{FREQS[MAIN] / 1e6:.0f}MHz"
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 5.2), gridspec_kw={"width_ratios": [1.35, 1]})
    colors = {"corner": "tab:blue", "room": "tab:red"}
    for name, r in results.items():
        c = colors.get(name, "k")
        for who in RENDERERS:
            rows = r.get(who)
            if not rows:
                continue
            t = np.array([x["seconds"] for x in rows])
            n = np.array([x["spp"] for x in rows])
            e = np.array([x["errors"][key]["rms_m"] for x in rows]) * 1e3
            ax.plot(t, e, STYLES[who], color=c, ms=3.5, lw=1.3, label=f"{name}: {who}")
            bx.plot(n, e, STYLES[who], color=c, ms=3.5, lw=1.3, label=f"{name}: {who}")
            for target in TARGETS_M:
                tt = r["time_to"][f"{target * 1e3:g}mm"].get(who)
                if tt is None:
                    continue
                if tt["how"] != "measured":
                    ax.plot([t[-1], tt["seconds"]], [e[-1], target * 1e3], ":", color=c, lw=0.8)
                ax.plot([tt["seconds"]], [target * 1e3], "x", color=c, ms=7)
    for a in (ax, bx):
        for target in TARGETS_M:
            a.axhline(target * 1e3, color="k", lw=0.8)
        a.set_xscale("log")
        a.set_yscale("log")
        a.grid(True, which="both", alpha=0.3)
    where = ("one GPU (tofcore device='gpu', mitransient cuda_ad_mono)" if cc.DEVICE == "gpu"
             else "2 cores, shared machine")
    ax.set_xlabel(f"wall time, s ({where}; 128 × 106 pixels)")
    ax.set_ylabel(f"RMS depth error at {FREQS[MAIN] / 1e6:.0f} MHz, mm (vs reference)")
    ax.set_title("Error against run time, same scene and path length (5); x: time to 5 mm and 1 mm\n"
                 "tofcore: QMC + light vertices + adaptive; tofcore-mc: plain Monte Carlo (before issue 10)",
                 fontsize=9)
    ax.legend(fontsize=7)
    bx.set_xlabel("samples per pixel (mean)")
    bx.set_title("the same errors against spp", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "error_vs_time.png", dpi=100)
    plt.close(fig)


def report(results: dict) -> None:
    key = f"{FREQS[MAIN] / 1e6:.0f}MHz"
    for name, res in results.items():
        ref = res["reference"]
        print(f"\n{name} ({res['pixels']} pixels; reference {ref['renderer']} {ref['spp']} spp, its RMS SE "
              f"{ref['rms_se_m'][key] * 1e3:.2f} mm at {key}):")
        for who in RENDERERS:
            if not res.get(who):
                continue
            last = res[who][-1]
            times = ", ".join(f"{k} at {v[who]['seconds']:.3g} s ({v[who]['how']})"
                              for k, v in res["time_to"].items() if who in v)
            print(f"  {who:12s} last point {last['spp']:.0f} spp {last['seconds']:.1f} s RMS "
                  f"{last['errors'][key]['rms_m'] * 1e3:.2f} mm; {times}")
        for k, v in res["time_to"].items():
            ratios = ", ".join(f"{w}/mitransient {v[f'ratio_{w}_over_mitransient']:.2f}×"
                               for w in ("tofcore", "tofcore-mc") if f"ratio_{w}_over_mitransient" in v)
            print(f"  time to {k}: {ratios}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="corner,room")
    ap.add_argument("--tofcore-spp", default="corner:512,room:256", help="most spp per scene (progressive)")
    ap.add_argument("--tofcore-mc-spp", default="corner:256,room:128", help="most spp per scene, plain MC variant")
    ap.add_argument("--mitransient-spp", default="corner:16,64,256,1024,4096,16384;room:16,64,256,1024,2048",
                    help="spp settings per scene")
    ap.add_argument("--ref-batches", default="corner:32,room:16", help="reference 1024-spp batches per scene")
    ap.add_argument("--tofcore-ref", default="", help="scene:spp of a tofcore reference replacing mitransient's, "
                                                         "e.g. room:4096")
    ap.add_argument("--device", choices=sorted(cc.MITSUBA_VARIANTS), default="cpu",
                    help="cpu: mitransient llvm_ad_mono, tofcore on the CPU; gpu: mitransient cuda_ad_mono, "
                         "tofcore device='gpu'")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"))
    ap.add_argument("--replot", action="store_true", help="recompute the times and the figure from the JSON")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    key = f"{FREQS[MAIN] / 1e6:.0f}MHz"
    if args.replot:
        with open(out / "error_vs_time.json") as fh:
            data = json.load(fh)
        for res in data["scenes"].values():
            res["time_to"] = {f"{x * 1e3:g}mm": time_to(res, key, x) for x in TARGETS_M}
        with open(out / "error_vs_time.json", "w") as fh:
            json.dump(data, fh, indent=1)
        plot(data["scenes"], out)
        report(data["scenes"])
        return 0

    def per_scene(text, cast):
        return {k: cast(v) for k, v in (x.split(":") for x in text.split(",") if x)}

    t_spp, mc_spp = per_scene(args.tofcore_spp, int), per_scene(args.tofcore_mc_spp, int)
    m_spp = {k: [int(s) for s in v.split(",")] for k, v in (x.split(":") for x in args.mitransient_spp.split(";"))}
    refb, tref = per_scene(args.ref_batches, int), per_scene(args.tofcore_ref, int)
    t00 = time.perf_counter()

    def log(msg):
        print(f"[{time.perf_counter() - t00:7.1f} s] {msg}", file=sys.stderr, flush=True)

    cc.DEVICE = args.device
    mi = cc.mitsuba_setup()
    import mitransient
    results = {}
    for name in args.scenes.split(","):
        s = cc.make_setup(name)
        r = cc.MitransientRenderer(s, FREQS, BATCH, cc.WORK / "ply", max_depth=5)
        r.name = name
        m_ref, m_var, m_sec = reference(r, refb[name], log)
        ref, ref_var = m_ref, m_var
        res = {}
        if name in tref:
            ref, ref_var, t_sec = tofcore_reference(s, tref[name], log)
            both = (np.abs(ref[0]) > 0) & (np.abs(m_ref[0]) > 0)
            scale = cc.C / (4 * np.pi * np.asarray(FREQS))[:, None, None]
            z = scale * np.angle(ref * np.conj(m_ref)) / np.sqrt(ref_var + m_var)
            res["reference_agreement"] = {f"{f / 1e6:.0f}MHz": {
                "std_z": float(np.std(z[i][both])), "mean_z": float(np.mean(z[i][both])),
                "frac_abs_z_gt_3": float(np.mean(np.abs(z[i][both]) > 3))} for i, f in enumerate(FREQS)}
            res["reference"] = {"renderer": "tofcore", "spp": tref[name], "seconds": t_sec,
                                "mitransient_reference": {"spp": refb[name] * BATCH, "seconds": m_sec}}
            log(f"{name}: tofcore vs mitransient references: {res['reference_agreement']}")
        else:
            res["reference"] = {"renderer": "mitransient", "spp": refb[name] * BATCH, "seconds": m_sec}
        mask = np.abs(ref[0]) > 0
        res["reference"]["rms_se_m"] = {f"{f / 1e6:.0f}MHz": float(np.sqrt(np.mean(ref_var[i][mask])))
                                        for i, f in enumerate(FREQS)}
        res["pixels"] = int(mask.sum())
        log(f"{name}: reference {res['reference']}")
        # Alternate the renderers' long runs as little as possible: tofcore first, then mitransient.
        res["tofcore"] = run_tofcore(s, t_spp[name], ref, ref_var, mask, log, "tofcore")
        res["tofcore-mc"] = run_tofcore(s, mc_spp[name], ref, ref_var, mask, log, "tofcore-mc")
        res["mitransient"], res["mitransient_cold_seconds"] = run_mitransient(r, m_spp[name], ref, ref_var, mask, log)
        res["time_to"] = {f"{x * 1e3:g}mm": time_to(res, key, x) for x in TARGETS_M}
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
