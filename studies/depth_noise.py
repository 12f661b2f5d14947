"""Depth noise against distance and against amplitude: the presets against the cameras they name.

Thesis §4.0.3 (Abbildung 4.7–4.9): temporal σ of the depth of a flat target orthogonal to the optical
axis, 1000 frames per position. Medians of its data in ±150 mm bins (issue 25), σ in mm:

* Kinect v2 on white and on black paper (Fig. 4.8), O3D303 at 30 MHz with one exposure, Xtion 2 (Fig. 4.7);
* Fankhauser et al. 2015 (ICAR, "Kinect v2 for Mobile Robot Navigation: Evaluation and Modeling"), the
  Kinect v2 axial noise at θ = 0: σ_z = 1.5 − 0.5 z + 0.3 z² mm (z in m).

Simulation: each preset as shipped (noise, lens scattering, the camera's own processing) looks at a plane
of reflectance 0.85 (white paper; black paper: 0.1 and 0.3, :data:`BLACK_REFLECTANCES` — the thesis gives no
reflectances), through a 16 × 16 pixel crop around the principal point, direct light only; one render per
seed; σ is the RMS over the 10 × 10 inner pixels of each pixel's standard deviation over the seeds (the
crop's border is left out: the 3 × 3 filter and the PSF need neighbours). The "0.5 m" point is rendered at
0.575 m for the Kinect v2: it cuts z < 0.5 m (libfreenect2 ``min_depth``), so that bin's data come
from 0.50–0.65 m. The Xtion 2 preset starts at Tab. 4.1's 0.8 m, so its 0.5 m point is invalid although
the thesis measured there.

The second figure is σ against the amplitude A of the decoded IR image (Fig. 4.9: "follows Li's equation
2.43"): the simulated points of both reflectances, and eq. 2.43 evaluated with the preset's charges.

    .venv/bin/python studies/depth_noise.py --out out/studies      # ~2 min on 2 cores
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

import _common as C
import tofcore
from tofcore.sensor import noise

DISTANCES_M = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0)
WHITE_REFLECTANCE = 0.85
#: black paper's near-infrared reflectance is not given in the thesis; two plausible values are shown
BLACK_REFLECTANCES = (0.1, 0.3)
#: issue 25: medians of the thesis's data (Fig. 4.7, 4.8) in ±150 mm bins, mm; None: no data.
MEASURED_MM = {
    "kinect_v2 white": (1.5, 1.2, 1.3, 1.3, 1.6, 2.2, 2.4, 2.7),
    "kinect_v2 black": (1.5, 1.2, 1.6, 2.3, 3.4, 4.1, 4.7, 6.2),
    "o3d303 white": (4.4, 6.5, 14.2, 22.7, 27.3, 48.6, 51.0, 68.4),
    "xtion2 white": (10.5, 5.8, 6.1, 9.9, 17.0, 18.4, 17.1, None),
}
ROWS = (("kinect_v2", WHITE_REFLECTANCE, "kinect_v2 white"),
        *(("kinect_v2", r, "kinect_v2 black") for r in BLACK_REFLECTANCES),
        ("o3d303", WHITE_REFLECTANCE, "o3d303 white"), ("xtion2", WHITE_REFLECTANCE, "xtion2 white"))
#: presets whose range starts at 0.5 m: their "0.5 m" bin can only hold data from 0.50–0.65 m
NEAR_BIN_M = {"kinect_v2": 0.575}


def fankhauser_mm(z_m: np.ndarray) -> np.ndarray:
    """Kinect v2 axial noise of Fankhauser et al. 2015 at a surface angle of 0: 1.5 − 0.5 z + 0.3 z² mm."""
    return 1.5 - 0.5 * z_m + 0.3 * z_m**2


def plane(z_m: float, reflectance: float) -> tofcore.Scene:
    """A 10 × 10 m Lambertian plane at z = ``z_m`` in the sensor frame, facing the camera."""
    v = np.array([[-5.0, -5.0, z_m], [5.0, -5.0, z_m], [5.0, 5.0, z_m], [-5.0, 5.0, z_m]])
    return tofcore.Scene.from_arrays(v, np.array([[0, 1, 2], [0, 2, 3]]), np.zeros(2, int),
                                     [tofcore.Material(name="target", reflectance=reflectance, roughness=1.0)])


def crop(sensor: tofcore.Sensor, size: int) -> tofcore.Sensor:
    """The preset with only ``size`` × ``size`` pixels around its principal point (same rays)."""
    cam = sensor.camera
    x0, y0 = int(round(cam.cx)) - size // 2, int(round(cam.cy)) - size // 2
    return dataclasses.replace(sensor, camera=dataclasses.replace(cam, width=size, height=size,
                                                                  cx=cam.cx - x0, cy=cam.cy - y0))


def plane_noise(sensor: tofcore.Sensor, z_m: float, reflectance: float, *, seeds: int,
                size: int = 16, border: int = 3) -> dict:
    """Temporal depth σ (mm), valid fraction and mean amplitude (e⁻) of a plane at ``z_m``, over ``seeds`` renders."""
    small, scene = crop(sensor, size), plane(z_m, reflectance)
    inner = (slice(border, size - border),) * 2
    depth, amplitude = [], []
    for seed in range(seeds):
        frame = tofcore.render(scene, small, np.eye(4), spp=4, max_depth=1, seed=seed, adaptive=False)
        depth.append(frame.depth[inner])
        amplitude.append(frame.amplitude[inner])
    depth = np.asarray(depth, np.float64)
    valid = np.isfinite(depth)
    enough = valid.sum(axis=0) >= 3
    with np.errstate(invalid="ignore"):
        sd = np.nanstd(np.where(enough, depth, np.nan), axis=0, ddof=1)
    sigma = float(np.sqrt(np.nanmean(sd**2))) * C.MM if enough.any() else float("nan")
    return {"z_m": z_m, "sigma_mm": sigma, "valid_fraction": float(valid.mean()),
            "amplitude_e": float(np.mean(amplitude))}


def eq_2_43_mm(sensor: tofcore.Sensor, amplitude_e: np.ndarray) -> np.ndarray | None:
    """σ of Li's eq. 2.43 (mm) at the highest frequency for decoded amplitudes, B = the signal's own offset.

    For a square wave of duty 0.5 decoded with N steps the offset of the signal is A / c with
    c = (8/π²) (its first harmonic); B + A = offset. CW only (None for pulsed).
    """
    mod = sensor.modulation
    if not mod.is_cw:
        return None
    contrast = 8.0 / np.pi**2 if mod.kind == "cw_square" else 2.0 / np.pi
    mean = amplitude_e / contrast   # the signal's mean charge per bucket, A of eq. 2.43
    return noise.li_sigma_m(mean, np.zeros_like(mean), max(mod.frequencies_hz), contrast) * C.MM


def main() -> None:
    args = C.parser(__doc__, spp=4, max_depth=1).parse_args()
    args.seeds = 24
    started = time.perf_counter()
    import matplotlib.pyplot as plt

    results = {}
    for name, reflectance, label in ROWS:
        sensor = tofcore.load_preset(name)
        points = []
        for z in DISTANCES_M:
            at = NEAR_BIN_M.get(name, z) if z == 0.5 else z
            points.append(dict(plane_noise(sensor, at, reflectance, seeds=args.seeds), bin_m=z))
            print(f"{label} {z:.1f} m: {points[-1]['sigma_mm']:.2f} mm, "
                  f"{100 * points[-1]['valid_fraction']:.0f} % valid", flush=True)
        measured = MEASURED_MM[label]
        for p, m in zip(points, measured):
            p["measured_mm"] = m
            p["ratio"] = None if m is None or not np.isfinite(p["sigma_mm"]) else p["sigma_mm"] / m
        results[f"{label} {reflectance}"] = {"label": label, "preset": name, "reflectance": reflectance,
                                             "points": points}

    z = np.array(DISTANCES_M)
    fig, axes = plt.subplots(2, 2, figsize=(11, 8), constrained_layout=True)
    for ax, label in zip(axes.ravel(), MEASURED_MM):
        meas = [np.nan if m is None else m for m in MEASURED_MM[label]]
        ax.plot(z, meas, "o-", color="k", label="measured (thesis, median of ±150 mm bin)")
        for row, style in zip([r for r in results.values() if r["label"] == label], ("s--", "^--")):
            sim = [p["sigma_mm"] for p in row["points"]]
            ax.plot(z, sim, style, color="tab:red", label=f"simulated ({row['preset']}, ρ = {row['reflectance']})")
        if label.startswith("kinect_v2"):
            zz = np.linspace(0.5, 4.0, 50)
            ax.plot(zz, fankhauser_mm(zz), ":", color="tab:blue", label="Fankhauser et al. 2015")
            ax.fill_between(z, 0.75 * np.array(meas), 1.25 * np.array(meas), color="k", alpha=0.08,
                            label="measured ± 25 %")
        ax.set_title(label)
        ax.set_xlabel("distance z (m)")
        ax.set_ylabel("σ of depth (mm)")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    C.write_outputs(args.out, "depth_noise", fig, {"rows": results, "seeds": args.seeds,
                                                    "black_reflectances": BLACK_REFLECTANCES}, started)

    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2), constrained_layout=True)
    amplitude_numbers = {}
    for ax, name in zip(axes, ("kinect_v2", "o3d303", "xtion2")):
        sensor = tofcore.load_preset(name)
        pts = [(p["amplitude_e"], p["sigma_mm"], row["reflectance"]) for row in results.values()
               if row["preset"] == name for p in row["points"] if np.isfinite(p["sigma_mm"])]
        a = np.array([p[0] for p in pts])
        s = np.array([p[1] for p in pts])
        for reflectance, marker in ((WHITE_REFLECTANCE, "s"), *((r, m) for r, m in zip(BLACK_REFLECTANCES, "^v"))):
            sel = np.array([p[2] == reflectance for p in pts])
            if sel.any():
                ax.loglog(a[sel], s[sel], marker, color="tab:red", label=f"simulated, ρ = {reflectance}")
        aa = np.geomspace(a.min() / 1.5, a.max() * 1.5, 50)
        li = eq_2_43_mm(sensor, aa)
        if li is not None:
            ax.loglog(aa, li, "-", color="k", label="eq. 2.43 (shot noise, one frequency, no filter)")
        ax.set_title(f"{name}: σ against amplitude (Fig. 4.9)")
        ax.set_xlabel("amplitude A of the IR image (e⁻)" if sensor.modulation.is_cw else "Q1 + Q2 (e⁻)")
        ax.set_ylabel("σ of depth (mm)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
        amplitude_numbers[name] = {"amplitude_e": a.tolist(), "sigma_mm": s.tolist()}
    C.write_outputs(args.out, "depth_noise_amplitude", fig, {"points": amplitude_numbers}, started)


if __name__ == "__main__":
    main()
