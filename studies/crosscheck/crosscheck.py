"""Cross-check of tofcore against mitransient: the multipath depth error per pixel, 16 / 80 / 120 MHz sine.

One command (needs the bench venv, see README.md in this folder)::

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 \\
        .venv-bench/bin/python studies/crosscheck/crosscheck.py [--spp 256] [--seeds 16] [--out studies/crosscheck/results]

Scenes: the demo ``corner`` and ``box_on_wall`` geometry with exact Lambertian materials (the demo's ρ),
one isotropic point LED 2.5 cm right of the lens, a 128 × 106 pinhole with Kinect v2's 70.6° FOV,
max path length 5 surface vertices (mitransient ``max_depth`` 6, no Russian roulette). See
``common.py`` for how the two renderers are matched.

Per scene and renderer, ``--seeds`` independent renders of ``--spp`` samples each. Direct-only:
tofcore's bucket k = 1 of the same render; mitransient's ``max_depth = 2`` render with the *same
seed* as its full render (same camera rays, and a point light's direct term is deterministic, so it
is exactly the full render's one-vertex part). The multipath error of a renderer is computed from
its seed-averaged phasors, MP = c/(4πf) · arg(P̄_full · conj P̄_direct), and its per-pixel standard
error by the jackknife over seeds. Then per pixel z = (MP_tofcore − MP_mitransient) /
sqrt(SE_t² + SE_m²). If both renderers estimate the same thing, z is ≈ N(0, 1) (Student-like tails
with few seeds) and RMS(difference) / RMS(combined SE) ≈ 1.

Writes ``crosscheck.json`` (all numbers) and ``crosscheck_maps.png``, ``crosscheck_z.png``.
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

FREQS = (16e6, 80e6, 120e6)
SCENES = ("corner", "box_on_wall")


def jackknife(samples: np.ndarray, stat) -> tuple[np.ndarray, np.ndarray]:
    """stat of the mean over axis 0 and its jackknife standard error (leave one seed out)."""
    n = len(samples)
    total = samples.sum(axis=0)
    full = stat(total / n)
    loo = np.stack([stat((total - samples[i]) / (n - 1)) for i in range(n)])
    mean_loo = loo.mean(axis=0)
    se = np.sqrt((n - 1) / n * ((loo - mean_loo) ** 2).sum(axis=0))
    return full, se


DEFAULT_OUT = Path(__file__).resolve().parent / "results"


def arrays_dir(out: Path) -> Path:
    """Per-pixel arrays: out/crosscheck/ for the committed results, else beside the JSON."""
    return cc.WORK if out.resolve() == DEFAULT_OUT else out


def run_scene(name: str, spp: int, seeds: int, max_depth: int, out: Path, log) -> dict:
    s = cc.make_setup(name)
    res: dict = {"scene": name, "albedo": s.albedo, "spp_per_seed": spp, "seeds": seeds, "max_depth": max_depth}
    # --- tofcore
    t_full, t_dir, t_sec, t_sig, t_sig_dir = [], [], [], [], []
    for seed in range(seeds):
        pf, pd, sec, sig, sig_d = cc.tofcore_phasors(s, FREQS, spp, max_depth, seed=1000 + seed,
                                                     with_signal=True)
        t_full.append(pf)
        t_dir.append(pd)
        t_sig.append(sig)
        t_sig_dir.append(sig_d)
        t_sec.append(sec)
        log(f"{name}: tofcore seed {seed}: {sec:.1f} s")
    # --- mitransient
    r = cc.MitransientRenderer(s, FREQS, spp, cc.WORK / "ply", max_depth)
    m_full, m_dir, m_sec, m_steady, m_steady_dir = [], [], [], [], []
    for seed in range(seeds):
        pf, st, sec_f = r.render(seed=2000 + seed)
        pd, st_d, sec_d = r.render(seed=2000 + seed, max_depth=1)
        m_full.append(pf)
        m_dir.append(pd)
        m_sec.append(sec_f + sec_d)
        m_steady.append(st)
        m_steady_dir.append(st_d)
        log(f"{name}: mitransient seed {seed}: {sec_f:.2f} + {sec_d:.2f} s")
    res["seconds_per_seed"] = {"tofcore": float(np.median(t_sec)), "mitransient_full_plus_direct":
                               float(np.median(m_sec[1:] if seeds > 1 else m_sec))}

    def both(x_full, x_dir):
        return np.stack([np.stack(x_full), np.stack(x_dir)], axis=1)   # (seeds, 2, F, H, W)

    def mp(pair):
        return cc.multipath_error_m(pair[0], pair[1], FREQS)

    t_mp, t_se = jackknife(both(t_full, t_dir), mp)
    m_mp, m_se = jackknife(both(m_full, m_dir), mp)

    # Pixels that see a surface in both renders (nonzero direct light everywhere over the seeds).
    seen = (np.abs(np.stack(t_dir)[:, 0]).min(axis=0) > 0) & (np.abs(np.stack(m_dir)[:, 0]).min(axis=0) > 0)
    res["pixels_compared"] = int(seen.sum())
    res["pixels_total"] = int(seen.size)

    # Sanity checks of the radiometry and the geometry: direct amplitude ratio and direct distance.
    amp_t = np.abs(np.mean(t_dir, axis=0)[0])
    amp_m = np.abs(np.mean(m_dir, axis=0)[0])
    ratio = amp_m[seen] / amp_t[seen]
    dist_t = cc.distance_m(np.mean(t_dir, axis=0), FREQS)[0]
    dist_m = cc.distance_m(np.mean(m_dir, axis=0), FREQS)[0]
    # Indirect radiance (full minus direct-only signal) summed over the image, per seed: a sensitive
    # test of the multipath radiometry (its standard error from the spread over seeds).
    ind_t = np.array([(a - b)[seen].mean() for a, b in zip(t_sig, t_sig_dir)])
    ind_m = np.array([(a - b)[seen].mean() for a, b in zip(m_steady, m_steady_dir)])
    se_ind = np.sqrt(ind_t.var(ddof=1) / seeds + ind_m.var(ddof=1) / seeds) if seeds > 1 else np.nan
    res["direct"] = {
        "amplitude_ratio_mitransient_over_tofcore": {"median": float(np.median(ratio)),
                                                     "p5": float(np.percentile(ratio, 5)),
                                                     "p95": float(np.percentile(ratio, 95))},
        "indirect_radiance_image_mean": {"tofcore": float(ind_t.mean()), "mitransient": float(ind_m.mean()),
                                         "ratio": float(ind_m.mean() / ind_t.mean()),
                                         "z": float((ind_t.mean() - ind_m.mean()) / se_ind)},
        "distance_difference_mm_16MHz": {"median": float(np.median((dist_m - dist_t)[seen]) * 1e3),
                                         "rms": float(np.sqrt(np.mean(((dist_m - dist_t)[seen]) ** 2)) * 1e3)},
    }

    per_f = {}
    for i, f in enumerate(FREQS):
        d = (t_mp[i] - m_mp[i])[seen]
        se = np.sqrt(t_se[i] ** 2 + m_se[i] ** 2)[seen]
        ok = np.isfinite(d) & np.isfinite(se) & (se > 0)
        d, se = d[ok], se[ok]
        z = d / se
        n = len(z)
        # Global test of the image mean: mean difference over its standard error (pixels independent).
        mean_d = float(d.mean())
        mean_d_se = float(np.sqrt(np.sum(se ** 2)) / n)
        per_f[f"{f / 1e6:.0f}MHz"] = {
            "pixels": n,
            "mp_error_mm": {"tofcore_mean": float(np.nanmean(t_mp[i][seen]) * 1e3),
                            "mitransient_mean": float(np.nanmean(m_mp[i][seen]) * 1e3),
                            "tofcore_rms": float(np.sqrt(np.nanmean(t_mp[i][seen] ** 2)) * 1e3),
                            "mitransient_rms": float(np.sqrt(np.nanmean(m_mp[i][seen] ** 2)) * 1e3),
                            "tofcore_max_abs": float(np.nanmax(np.abs(t_mp[i][seen])) * 1e3)},
            "se_mm": {"tofcore_rms": float(np.sqrt(np.mean(t_se[i][seen][ok] ** 2)) * 1e3),
                      "mitransient_rms": float(np.sqrt(np.mean(m_se[i][seen][ok] ** 2)) * 1e3),
                      "combined_rms": float(np.sqrt(np.mean(se ** 2)) * 1e3)},
            "rms_difference_mm": float(np.sqrt(np.mean(d ** 2)) * 1e3),
            "rms_difference_over_combined_se": float(np.sqrt(np.mean(d ** 2)) / np.sqrt(np.mean(se ** 2))),
            "z": {"mean": float(z.mean()), "std": float(z.std()), "median": float(np.median(z)),
                  "p1": float(np.percentile(z, 1)), "p99": float(np.percentile(z, 99)),
                  "frac_abs_gt_2": float(np.mean(np.abs(z) > 2)), "frac_abs_gt_3": float(np.mean(np.abs(z) > 3)),
                  "frac_abs_gt_4": float(np.mean(np.abs(z) > 4))},
            "image_mean_difference_mm": mean_d * 1e3, "image_mean_difference_se_mm": mean_d_se * 1e3,
            "image_mean_difference_z": mean_d / mean_d_se,
        }
    res["frequencies"] = per_f
    arrays = {"t_mp": t_mp, "m_mp": m_mp, "t_se": t_se, "m_se": m_se, "seen": seen}
    arrays_dir(out).mkdir(parents=True, exist_ok=True)
    np.savez_compressed(arrays_dir(out) / f"crosscheck_{name}.npz", **arrays)
    return res, arrays


def student_t_expected(seeds: int) -> dict:
    """Tail fractions of |z| for a difference of two jackknife estimates, by simulation of pure noise."""
    rng = np.random.default_rng(0)
    n = 200_000
    a = rng.standard_normal((seeds, n))
    b = rng.standard_normal((seeds, n))
    se = np.sqrt(a.var(axis=0, ddof=1) / seeds + b.var(axis=0, ddof=1) / seeds)
    z = (a.mean(axis=0) - b.mean(axis=0)) / se
    return {"std": float(z.std()), "frac_abs_gt_2": float(np.mean(np.abs(z) > 2)),
            "frac_abs_gt_3": float(np.mean(np.abs(z) > 3)), "frac_abs_gt_4": float(np.mean(np.abs(z) > 4))}


def plot(results, arrays, out: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nf = len(FREQS)
    fig, axes = plt.subplots(2 * len(SCENES), nf, figsize=(4.2 * nf, 3.2 * 2 * len(SCENES)))
    for si, name in enumerate(SCENES):
        a = arrays[name]
        for i, f in enumerate(FREQS):
            for row, (key, label) in enumerate((("t_mp", "tofcore"), ("m_mp", "mitransient"))):
                ax = axes[2 * si + row, i]
                img = np.where(a["seen"], a[key][i] * 1e3, np.nan)
                lim = np.nanpercentile(np.abs(a["t_mp"][i][a["seen"]]) * 1e3, 99.5)
                im = ax.imshow(img, cmap="RdBu_r", vmin=-lim, vmax=lim)
                ax.set_title(f"{name} {f / 1e6:.0f} MHz: {label}", fontsize=9)
                ax.set_xticks([])
                ax.set_yticks([])
                fig.colorbar(im, ax=ax, fraction=0.046, label="multipath error, mm")
    fig.suptitle("Multipath depth error (full − direct-only), sine modulation; red = too far")
    fig.tight_layout()
    fig.savefig(out / "crosscheck_maps.png", dpi=60)
    plt.close(fig)

    fig, axes = plt.subplots(2, nf, figsize=(4.2 * nf, 6.4))
    x = np.linspace(-6, 6, 241)
    for si, name in enumerate(SCENES):
        a = arrays[name]
        for i, f in enumerate(FREQS):
            ax = axes[si, i]
            se = np.sqrt(a["t_se"][i] ** 2 + a["m_se"][i] ** 2)
            z = ((a["t_mp"][i] - a["m_mp"][i]) / se)[a["seen"] & (se > 0)]
            z = z[np.isfinite(z)]
            ax.hist(np.clip(z, -6, 6), bins=96, range=(-6, 6), density=True, color="0.6", label="z per pixel")
            ax.plot(x, np.exp(-x * x / 2) / np.sqrt(2 * np.pi), "k", lw=1, label="N(0, 1)")
            r = results[name]["frequencies"][f"{f / 1e6:.0f}MHz"]
            ax.set_title(f"{name} {f / 1e6:.0f} MHz: std z {r['z']['std']:.2f}, "
                         f"RMS diff/SE {r['rms_difference_over_combined_se']:.2f}", fontsize=9)
            ax.set_yscale("log")
            ax.set_ylim(1e-4, 1)
            ax.set_xlabel("z = (tofcore − mitransient) / combined SE")
            if i == 0:
                ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "crosscheck_z.png", dpi=80)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--spp", type=int, default=256, help="samples per pixel per seed (both renderers)")
    ap.add_argument("--seeds", type=int, default=16, help="independent renders per renderer and scene")
    ap.add_argument("--max-depth", type=int, default=5, help="surface vertices per path (tofcore's max_depth)")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--out", default=str(DEFAULT_OUT))
    ap.add_argument("--replot", action="store_true", help="redraw the figures from the saved JSON and arrays")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if args.replot:
        with open(out / "crosscheck.json") as fh:
            results = json.load(fh)["scenes"]
        arrays = {n: dict(np.load(arrays_dir(out) / f"crosscheck_{n}.npz")) for n in SCENES}
        plot(results, arrays, out)
        return 0

    def log(msg):
        print(f"[{time.perf_counter() - t0:7.1f} s] {msg}", file=sys.stderr, flush=True)

    mitsuba = cc.mitsuba_setup()
    import mitransient
    results, arrays = {}, {}
    for name in args.scenes.split(","):
        results[name], arrays[name] = run_scene(name, args.spp, args.seeds, args.max_depth, out, log)
    summary = {
        "command": " ".join([Path(sys.executable).name] + sys.argv),
        "versions": {"mitsuba": mitsuba.__version__, "mitransient": getattr(mitransient, "__version__", "?"),
                     "numpy": np.__version__, "python": platform.python_version()},
        "frequencies_hz": FREQS, "resolution": [128, 106], "hfov_deg": cc.HFOV_DEG,
        "led_offset_m": cc.LED_OFFSET_M, "seconds": time.perf_counter() - t0,
        "expected_z_tails_pure_noise": student_t_expected(args.seeds), "scenes": results,
    }
    with open(out / "crosscheck.json", "w") as fh:
        json.dump(summary, fh, indent=1)
    if set(arrays) == set(SCENES):
        plot(results, arrays, out)
    for name, r in results.items():
        print(f"\n{name}: {r['pixels_compared']} pixels, {r['seeds']} seeds × {r['spp_per_seed']} spp; "
              f"direct amplitude ratio mitransient/tofcore {r['direct']['amplitude_ratio_mitransient_over_tofcore']['median']:.5f}, "
              f"direct distance difference median {r['direct']['distance_difference_mm_16MHz']['median']:+.3f} mm")
        print("| f | MP mean tofcore mm | MP mean mitransient mm | RMS diff mm | RMS combined SE mm | ratio "
              "| std z | |z|>2 | |z|>3 | image-mean z |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for f, q in r["frequencies"].items():
            print(f"| {f} | {q['mp_error_mm']['tofcore_mean']:+.3f} | {q['mp_error_mm']['mitransient_mean']:+.3f} "
                  f"| {q['rms_difference_mm']:.4f} | {q['se_mm']['combined_rms']:.4f} "
                  f"| {q['rms_difference_over_combined_se']:.3f} | {q['z']['std']:.3f} "
                  f"| {q['z']['frac_abs_gt_2']:.4f} | {q['z']['frac_abs_gt_3']:.4f} | {q['image_mean_difference_z']:+.2f} |")
    print(f"\npure noise with {args.seeds} seeds: {summary['expected_z_tails_pure_noise']}")
    print(f"wrote {out}/crosscheck.json, crosscheck_maps.png, crosscheck_z.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
