r"""Caustics in the Kinect v2 room: their share of the render error, and light tracing's time to error.

One command (≈ 10 min on the shared 2-core machine at the default 64 × 53 pixels)::

    .venv/bin/python studies/caustics/study.py --json studies/caustics/results/study.json

Pixels whose decoded depth is off by more than 0.1 m (a wrong unwrapping: about 10× the render noise at
16 spp) are counted apart and left out of the squared errors, in every variant alike.

1. **Reference**: the path tracer (tofcore's stages, Sobol' replicates, light vertices with MIS, 5 surface
   vertices) at ``--ref-spp`` with every contribution split into classes by what the LED lights first
   (:mod:`classify`).
2. **Share of the error at equal spp**: ``--seeds`` renders at ``--spp``. The squared error of the decoded
   depth against the reference's, over the pixels both decode, for the whole estimate and with one
   component noisy and the rest taken from the reference:

   .. math:: M_{all} = \overline{(d(\hat S) - d_{ref})^2}, \quad
             M_{c} = \overline{(d(S^{ref}_{\bar c} + \hat S_c) - d_{ref})^2}, \quad
             M_{\bar c} = \overline{(d(\hat S_{\bar c} + S^{ref}_c) - d_{ref})^2}

   (S the mean correlation images; c the caustic classes). The caustic share is M_c / M_all; M_c + M_{c̄}
   = M_all up to the cross term. The raw signal Σw is split the same way (no decoding). Each M is
   corrected for the reference's own noise (× 1/(1 + n/N_ref), the reference being the same estimator
   at N_ref samples).
3. **Light tracing for the caustic component** (:mod:`light_tracer`, ``caustic_only``): ``--lt-paths`` ×
   pixels light paths per render, the same seeds, its M_c^LT against the same reference (corrected by
   the reference's own caustic noise).
4. **MIS, measured**: the path tracer with the three-strategy weights of :mod:`mis` plus light tracing with
   N = ``--mis-ratios`` × n × pixels light paths, summed: M_all^MIS against the same reference.
5. **Time**: the production NumPy tracer (``tofcore.tracer.trace``, ``TOFCORE_TRACER=numpy``, one
   process) at ``--spp``, the light tracer alone and with MIS weights (one process), alternately,
   ``--repeat`` times; medians. The MIS weights' own cost in the path tracer (the reverse densities)
   is measured as the time ratio of :func:`classify.trace_classified` with and without them.

Efficiencies (squared error × seconds, lower is better): c = M_c T_PT, c̄ = M_{c̄} T_PT, b = M_c^LT T_LT.
With the path tracer for everything but the caustics and the light tracer for those (MIS that gives each
path to the better strategy; the best split of a time budget T between them),

.. math:: M(T) = (\sqrt{\bar c} + \sqrt b)^2 / T \quad\text{against}\quad M_{all} T_{PT} / T,

so light tracing pays for the whole frame by the factor G = M_all T_PT / (√c̄ + √b)² (> 1: it pays).
The measured MIS combination pays by M_all T_PT / (M_all^MIS (o T_PT + T_LT^MIS)), o the weights' overhead.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

os.environ["TOFCORE_TRACER"] = "numpy"  # the NumPy reference tracer: the light tracer is NumPy too

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import tofcore  # noqa: E402
from tofcore.scene.demo import suggested_pose  # noqa: E402
from tofcore.tracer.trace import trace  # noqa: E402

from classify import ClassSums, caustic_classes, class_names, trace_classified  # noqa: E402
from frames import depth, mean_images, sensor_at, setup_for, traced  # noqa: E402
from light_tracer import trace_light  # noqa: E402

SCENE = "room"
LT_SEED = 10_000  # light-tracing seeds apart from the path tracer's (the samplers share their dimensions)
GROSS_M = 0.1     # depth errors beyond this are wrong unwrappings: counted, not squared


def depth_error(sensor, d_ref: np.ndarray, correlation: np.ndarray) -> dict:
    """Mean squared depth error (m²) over the pixels both decode, gross errors apart; their counts."""
    d = depth(sensor, correlation)
    ok = np.isfinite(d) & np.isfinite(d_ref)
    diff = (d - d_ref)[ok]
    fine = np.abs(diff) <= GROSS_M
    return {"mse": float(np.mean(diff[fine] ** 2)), "gross": int((~fine).sum()), "pixels": int(ok.sum())}


class Reference:
    """The reference's per-class mean images and depth."""

    def __init__(self, sensor, sums, cls_c, shape):
        self.sensor, self.shape, self.cls_c = sensor, shape, cls_c
        self.n_cls = sums.signal.shape[0]
        self.cls_nc = [c for c in range(self.n_cls) if c not in cls_c]
        self.sig = {i: mean_images(sums, [i], shape)[0] for i in range(self.n_cls)}
        self.corr = {i: mean_images(sums, [i], shape)[1] for i in range(self.n_cls)}
        self.corr_c = sum(self.corr[i] for i in cls_c)
        self.corr_nc = sum(self.corr[i] for i in self.cls_nc)
        self.sig_c = sum(self.sig[i] for i in cls_c)
        self.sig_nc = sum(self.sig[i] for i in self.cls_nc)
        self.depth = depth(sensor, self.corr_c + self.corr_nc)

    def errors(self, pt) -> dict:
        """Squared errors of a path-traced estimate: all, caustic alone, the rest alone, each class alone."""
        sig_c, corr_c = mean_images(pt, self.cls_c, self.shape)
        sig_nc, corr_nc = mean_images(pt, self.cls_nc, self.shape)
        out = {"all": depth_error(self.sensor, self.depth, corr_c + corr_nc),
               "caustic": depth_error(self.sensor, self.depth, self.corr_nc + corr_c),
               "rest": depth_error(self.sensor, self.depth, corr_nc + self.corr_c)}
        for i in range(self.n_cls):
            corr_i = mean_images(pt, [i], self.shape)[1]
            out[f"class {i}"] = depth_error(self.sensor, self.depth, self.corr_c + self.corr_nc - self.corr[i] + corr_i)
        out["signal"] = {"all": float(np.sum((sig_c + sig_nc - self.sig_c - self.sig_nc) ** 2)),
                         "caustic": float(np.sum((sig_c - self.sig_c) ** 2)),
                         "rest": float(np.sum((sig_nc - self.sig_nc) ** 2))}
        return out

    def caustic_errors(self, caustic_corr, caustic_sig) -> dict:
        """Squared errors of a caustic estimate (mean images) with the rest from the reference."""
        return {"caustic": depth_error(self.sensor, self.depth, self.corr_nc + caustic_corr),
                "signal_caustic": float(np.sum((caustic_sig - self.sig_c) ** 2))}


def reference(scale: float, ref_spp: int, workers: int, cache: Path):
    """The reference sums, traced once and kept in ``cache`` (an .npz)."""
    if cache.exists():
        data = np.load(cache)
        return ClassSums(data["signal"], data["correlation"], int(data["samples"])), float(data["seconds"])
    t0 = time.perf_counter()
    ref = traced("pt", SCENE, scale, 1_000_000, spp=ref_spp, workers=workers)
    seconds = time.perf_counter() - t0
    cache.parent.mkdir(parents=True, exist_ok=True)
    np.savez(cache, signal=ref.signal, correlation=ref.correlation, samples=ref.samples, seconds=seconds)
    return ref, seconds


def timed(scene, sensor, spp: int, ratios, seed: int) -> dict:
    """Seconds, one process each: the production NumPy tracer; caustic light tracing alone and with MIS
    weights at each ratio; the classified tracer with and without the MIS weights (their overhead)."""
    n_pix = sensor.camera.width * sensor.camera.height
    pose = suggested_pose(scene)
    out = {}
    t0 = time.perf_counter()
    trace(scene, sensor.camera, sensor.leds, world_from_sensor=pose, correlations=sensor.modulation.correlation_bank(),
          spp=spp, seed=seed, workers=1)
    out["pt"] = time.perf_counter() - t0
    setup = setup_for(scene, sensor, seed=LT_SEED + seed)
    for ratio in (None,) + tuple(ratios):
        n_paths = int((1.0 if ratio is None else ratio) * spp * n_pix)
        t0 = time.perf_counter()
        for first in range(0, n_paths, 65536):
            trace_light(setup, first, min(65536, n_paths - first), caustic_only=True,
                        mis_ratio=None if ratio is None else n_paths / spp)
        out["lt" if ratio is None else f"lt_mis {ratio}"] = time.perf_counter() - t0
    setup = setup_for(scene, sensor, seed=seed)
    for name, lt_ratio in (("classified", None), ("classified_mis", 1.0)):
        t0 = time.perf_counter()
        step = max(1, 65536 // spp)
        for p in range(0, n_pix, step):
            trace_classified(setup, p, min(p + step, n_pix), spp, lt_ratio=lt_ratio)
        out[name] = time.perf_counter() - t0
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scale", type=float, default=0.125, help="Kinect v2 resolution factor (default 0.125: 64 × 53)")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--mis-ratios", type=float, nargs="+", default=[0.25, 1.0],
                    help="light paths per path-tracer sample per pixel for the MIS runs (default 0.25 1)")
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--cache", type=Path, default=Path("out/caustics"), help="folder for the reference (.npz)")
    ap.add_argument("--json", type=Path, default=Path("studies/caustics/results/study.json"))
    args = ap.parse_args()
    scene = tofcore.demo_scene(SCENE)
    sensor = sensor_at(args.scale)
    shape = (sensor.camera.height, sensor.camera.width)
    n_pix = shape[0] * shape[1]
    names = class_names(scene.materials)
    cls_c = caustic_classes(scene.materials)
    n_lt = args.spp * n_pix   # light paths of the plain light-tracing runs: one per path-tracer path
    result = {"args": {k: str(v) for k, v in vars(args).items()}, "machine": platform.platform(),
              "pixels": n_pix, "classes": names, "caustic_classes": cls_c}
    ref_sums, result["reference_seconds"] = reference(args.scale, args.ref_spp, args.workers,
                                                      args.cache / f"reference_{args.scale}_{args.ref_spp}.npz")
    ref = Reference(sensor, ref_sums, cls_c, shape)
    result["reference_signal_per_class"] = (ref_sums.signal.sum(axis=(1, 2)) / ref_sums.samples / n_pix).tolist()
    print(f"reference {args.ref_spp} spp ({result['reference_seconds']:.0f} s); mean signal per class "
          + ", ".join(f"{n} {v:.4g}" for n, v in zip(names, result["reference_signal_per_class"])), flush=True)
    rows = []
    for seed in range(args.seeds):
        row = {"pt": ref.errors(traced("pt", SCENE, args.scale, seed, spp=args.spp, workers=args.workers))}
        lt = traced("lt", SCENE, args.scale, LT_SEED + seed, n_paths=n_lt, workers=args.workers)
        sig, corr = mean_images(lt, cls_c, shape)
        row["lt"] = ref.caustic_errors(corr, sig) | {"caustic_signal_total": float(sig.sum())}
        for ratio in args.mis_ratios:
            n_paths = int(ratio * n_lt)
            pt = traced("pt", SCENE, args.scale, seed, spp=args.spp, mis_ratio=n_paths / args.spp,
                        workers=args.workers)
            lt = traced("lt", SCENE, args.scale, LT_SEED + seed, n_paths=n_paths, mis_ratio=n_paths / args.spp,
                        workers=args.workers)
            sig_pt, corr_pt = mean_images(pt, range(len(names)), shape)
            sig_lt, corr_lt = mean_images(lt, cls_c, shape)
            sig_ptc, corr_ptc = mean_images(pt, cls_c, shape)
            row[f"mis {ratio}"] = {"all": depth_error(sensor, ref.depth, corr_pt + corr_lt),
                                   **ref.caustic_errors(corr_ptc + corr_lt, sig_ptc + sig_lt),
                                   "caustic_signal_total": float((sig_ptc + sig_lt).sum())}
        rows.append(row)
        print(f"seed {seed}: depth MSE (mm²) PT all {row['pt']['all']['mse'] * 1e6:.2f}, caustic "
              f"{row['pt']['caustic']['mse'] * 1e6:.2f}; LT caustic {row['lt']['caustic']['mse'] * 1e6:.2f}; "
              + "; ".join(f"MIS {r} all {row[f'mis {r}']['all']['mse'] * 1e6:.2f}" for r in args.mis_ratios),
              flush=True)
    times = [timed(scene, sensor, args.spp, args.mis_ratios, 100 + r) for r in range(args.repeat)]
    median = {k: float(np.median([t[k] for t in times])) for k in times[0]}
    result.update(rows=rows, times=times, median_seconds=median)
    result["summary"] = summary(rows, median, args, names, cls_c,
                                float(ref.sig_c.sum()))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1))
    print(json.dumps(result["summary"], indent=1))
    return 0


def summary(rows, seconds, args, names, cls_c, ref_caustic_signal) -> dict:
    """Mean errors over seeds, corrected for the reference's own noise; shares; efficiencies; gains."""
    spp, ref_spp = args.spp, args.ref_spp
    keep = 1.0 / (1.0 + spp / ref_spp)               # E[measured] = M (1 + n/N_ref) for the path tracer
    mean = lambda get: float(np.mean([get(r) for r in rows]))  # noqa: E731
    m = {k: mean(lambda r: r["pt"][k]["mse"]) * keep for k in ("all", "caustic", "rest")}
    s = {k: mean(lambda r: r["pt"]["signal"][k]) * keep for k in ("all", "caustic", "rest")}
    ref_noise_c, ref_noise_all = m["caustic"] * spp / ref_spp, m["all"] * spp / ref_spp
    m_lt = mean(lambda r: r["lt"]["caustic"]["mse"]) - ref_noise_c
    s_lt = mean(lambda r: r["lt"]["signal_caustic"]) - s["caustic"] * spp / ref_spp
    t_pt, t_lt = seconds["pt"], seconds["lt"]
    overhead = seconds["classified_mis"] / seconds["classified"]
    c, cbar, b = m["caustic"] * t_pt, m["rest"] * t_pt, m_lt * t_lt
    out = {
        "depth_rmse_mm": ({k: float(np.sqrt(v)) * 1e3 for k, v in m.items()}
                          | {"caustic_lt": float(np.sqrt(max(m_lt, 0))) * 1e3}),
        "gross_pixels_per_frame_pt": mean(lambda r: r["pt"]["all"]["gross"]),
        "caustic_share_depth": m["caustic"] / m["all"], "rest_share_depth": m["rest"] / m["all"],
        "caustic_share_signal": s["caustic"] / s["all"],
        "share_per_class_depth": {name: mean(lambda r: r["pt"][f"class {i}"]["mse"]) * keep / m["all"]
                                  for i, name in enumerate(names)},
        "lt_caustic_signal_over_ref": mean(lambda r: r["lt"]["caustic_signal_total"]) / ref_caustic_signal,
        "seconds": seconds, "mis_weight_overhead_pt": overhead,
        "lt_over_pt_efficiency_caustic_depth": c / b if b > 0 else None,
        "lt_over_pt_efficiency_caustic_signal": (s["caustic"] * t_pt) / (s_lt * t_lt) if s_lt > 0 else None,
        "ideal_split_gain_G": m["all"] * t_pt / (np.sqrt(cbar) + np.sqrt(max(b, 0.0))) ** 2,
        "gain_if_caustics_were_free": m["all"] / m["rest"],
    }
    for ratio in args.mis_ratios:
        key = f"mis {ratio}"
        m_mis = mean(lambda r: r[key]["all"]["mse"]) - ref_noise_all
        m_mis_c = mean(lambda r: r[key]["caustic"]["mse"]) - ref_noise_c
        t_lt_mis = seconds[f"lt_mis {ratio}"]
        t_mis = overhead * t_pt + t_lt_mis
        out[key] = {"depth_rmse_mm": float(np.sqrt(max(m_mis, 0))) * 1e3,
                    "caustic_depth_rmse_mm": float(np.sqrt(max(m_mis_c, 0))) * 1e3,
                    "mse_gain_equal_spp": m["all"] / m_mis, "seconds": t_mis,
                    "time_to_error_gain": m["all"] * t_pt / (m_mis * t_mis),
                    "time_to_error_gain_without_overhead": m["all"] * t_pt / (m_mis * (t_pt + t_lt_mis)),
                    "gross_pixels_per_frame": mean(lambda r: r[key]["all"]["gross"]),
                    "caustic_signal_over_ref": mean(lambda r: r[key]["caustic_signal_total"]) / ref_caustic_signal}
    return out


if __name__ == "__main__":
    raise SystemExit(main())
