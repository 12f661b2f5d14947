"""Systematic error against true distance: square wave 20 / 30 MHz, sine, and pulsed with ambient light.

Thesis §6.4 (Abbildung 6.10, 6.11): the square wave (4 buckets) gives a sinusoidal error whose amplitude and
period depend on the frequency (20 MHz: Xtion 2, 30 MHz: O3D303); the sine wave gives none (it is the
thesis's reference); the 2-bucket pulsed sensor shows no error without ambient light but a distance
-dependent one when an environment map adds ambient light (similar to the Xtion 2's measured error).

Two ways, which must agree:

* synthetic: ``tofcore.sensor.decode.systematic_error_curve`` — one ideal, noise-free return per distance;
* rendered: a large Lambertian-like plane (σ = 0.5, ρ = 0.8) swept from 0.3 to 4.9 m in front of a 3 × 3
  pixel camera (0.3° field of view, LED at the lens so the LED offset adds nothing), path traced with
  max path length 2 (the second vertex is needed for the plane to reflect the environment map), noise and
  scattering off; error = decoded distance − ground-truth distance of the centre pixel.

The ambient light is an equirectangular environment map (a dim sky and a bright "window" behind the
camera); it is unmodulated, so it cancels in the CW phase but biases the 2-bucket pulsed sensor towards
c t0 / 4 (closed form: error = a (d_max − 2d) / (S + 2a), a the ambient charge per bucket, S the signal).

    .venv/bin/python studies/systematic_error.py --out out/studies      # ~20 s on 2 cores
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

import _common as C
import tofcore
from tofcore.sensor import decode
from tofcore.sensor.modulation import ideal_raw

PULSE_WIDTH_S = 25e-9    # 20 MHz pulses as the Xtion 2 (thesis ch. 4); d_max = c t0 / 2 = 3.747 m


def environment_map(h: int = 64, w: int = 128) -> np.ndarray:
    """A dim sky (brighter towards the zenith) plus a bright window behind the camera (W m⁻² sr⁻¹)."""
    v = (np.arange(h) + 0.5) / h                       # 0 = zenith (+Z), 1 = nadir
    u = (np.arange(w) + 0.5) / w
    elev = (0.5 - v) * np.pi                           # elevation, rad
    az = (u - 0.5) * 2 * np.pi                         # Blender mapping: u = atan2(d_y, -d_x)/2π + 1/2
    E, A = np.meshgrid(elev, az, indexing="ij")
    d = np.stack([-np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1)
    sky = 0.004 + 0.01 * np.clip(np.sin(E), 0, None)
    window = np.array([0.0, -np.cos(np.radians(25)), np.sin(np.radians(25))])  # behind the camera (−y), 25° up
    blob = 0.17 * np.exp(-(1 - d @ window) / (1 - np.cos(np.radians(15))))
    return sky + blob


def big_plane() -> tofcore.Scene:
    v = np.array([[-60.0, 0, -60], [60, 0, -60], [60, 0, 60], [-60, 0, 60]])
    return tofcore.Scene.from_arrays(v, np.array([[0, 2, 1], [0, 3, 2]]), None,
                                     [tofcore.Material(name="plane", reflectance=0.8, roughness=0.5)],
                                     name="big plane")


def sensor_for(mod: tofcore.Modulation) -> tofcore.Sensor:
    cam = tofcore.Camera.from_fov(3, 3, 0.3)
    rng = (0.0, float(mod.unambiguous_range_m()) * 0.999)
    base = C.kinect()
    base = base.replace(**{"invalid.min_amplitude_e": 0.0, "invalid.invalidate_saturated": False})
    return dataclasses.replace(base, camera=cam, leds=(tofcore.LED(position_m=(0.0, 0.0, 0.0), kind="lambertian"),),
                               modulation=mod, range_m=rng)


def sweep(scene, mod, distances, ambient, spp, seed):
    sensor = sensor_for(mod)
    err, raws, secs, est = [], [], [], []
    for i, d in enumerate(distances):
        pose = tofcore.look_at((0.0, -float(d), 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
        f = tofcore.render(scene, sensor, pose, spp=spp, max_depth=2, seed=seed + i, ambient=ambient)
        err.append(float(f.distance[1, 1] - f.gt_distance[1, 1]))
        raws.append(f.raw[:, 1, 1].astype(np.float64))
        secs.append(f.stats["seconds"])
        est.append(f.stats["convergence"][-1]["est_depth_error_m"])
    return np.array(err), np.array(raws), float(np.sum(secs)), est


def main() -> None:
    args = C.parser(__doc__, spp=1024, max_depth=2).parse_args()
    started = time.perf_counter()
    scene = big_plane()
    env = tofcore.Ambient(environment=environment_map())
    sq20 = tofcore.Modulation(kind="cw_square", frequencies_hz=(20e6,), phase_steps=(4,))
    sq30 = tofcore.Modulation(kind="cw_square", frequencies_hz=(30e6,), phase_steps=(4,))
    si20 = tofcore.Modulation(kind="cw_sine", frequencies_hz=(20e6,), phase_steps=(4,))
    si30 = tofcore.Modulation(kind="cw_sine", frequencies_hz=(30e6,), phase_steps=(4,))
    pulsed = tofcore.Modulation(kind="pulsed", pulse_width_s=PULSE_WIDTH_S, exposure_s=(1e-3,))
    kinect_mod = tofcore.load_preset("kinect_v2").modulation
    d_max = float(pulsed.ambiguity_distances_m()[0])

    # ---------------- synthetic curves (single ideal return, no noise)
    dense = np.linspace(0.3, 4.9, 2301)
    syn = {name: decode.systematic_error_curve(m, dense)[0]
           for name, m in (("square 20 MHz", sq20), ("square 30 MHz", sq30), ("sine 20 MHz", si20),
                           ("sine 30 MHz", si30))}
    syn["pulsed, no ambient"] = decode.systematic_error_curve(pulsed, dense[dense < d_max])[0]
    kin = decode.decode(ideal_raw(kinect_mod, dense, 1000.0), kinect_mod, decode.DecodeSettings(range_m=(0.0, 18.0)))
    syn["Kinect v2 (80/16/120 MHz, 3 steps, unwrapped)"] = np.asarray(kin.distance) - dense

    # ---------------- rendered sweeps
    step = 0.1
    d_cw = np.round(np.arange(0.3, 4.9 + 1e-9, step), 3)
    d_pu = np.round(np.arange(0.3, d_max - 0.05, step), 3)
    rendered, timing = {}, []
    cw_spp = min(args.spp, 64)  # the CW phase does not see the (unmodulated) ambient: few samples suffice
    for name, mod, dist, amb, spp in (("square 20 MHz", sq20, d_cw, env, cw_spp), ("square 30 MHz", sq30, d_cw, env, cw_spp),
                                      ("sine 20 MHz", si20, d_cw, env, cw_spp), ("sine 30 MHz", si30, d_cw, env, cw_spp),
                                      ("pulsed, no ambient", pulsed, d_pu, None, cw_spp),
                                      ("pulsed, environment map", pulsed, d_pu, env, args.spp)):
        err, raw, secs, est = sweep(scene, mod, dist, amb, spp, args.seed)
        rendered[name] = {"distance_m": dist, "error_m": err, "raw": raw}
        timing.append({"label": f"{name}: {len(dist)} renders of 3×3 px", "seconds": round(secs, 2),
                       "spp": spp, "max_depth": 2, "pixels": 9, "rays": None,
                       "est_depth_error_mm": round(float(np.sqrt(np.mean(np.square(est)))) * C.MM, 4),
                       "convergence": []})
        print(f"{name:26s} rendered {len(dist)} distances in {secs:.1f} s; max |error| {np.abs(err).max() * C.MM:.2f} mm")

    # ---------------- agreement rendered vs synthetic (CW; pulsed without ambient)
    agree = {}
    for name, mod in (("square 20 MHz", sq20), ("square 30 MHz", sq30), ("sine 20 MHz", si20),
                      ("sine 30 MHz", si30), ("pulsed, no ambient", pulsed)):
        r = rendered[name]
        s = decode.systematic_error_curve(mod, r["distance_m"])[0]
        agree[name] = {"max_abs_difference_mm": float(np.max(np.abs(r["error_m"] - s)) * C.MM),
                       "peak_error_rendered_mm": float(np.max(np.abs(r["error_m"])) * C.MM),
                       "peak_error_synthetic_mm": float(np.max(np.abs(s)) * C.MM)}
    # Pulsed with ambient: ambient charge per bucket a = raw(with) − raw(without); signal S = Q1 + Q2 (without).
    r0, r1 = rendered["pulsed, no ambient"], rendered["pulsed, environment map"]
    assert np.array_equal(r0["distance_m"], r1["distance_m"])
    a = (r1["raw"] - r0["raw"]).mean(axis=1)
    S = r0["raw"].sum(axis=1)
    kappa = float(np.median(a / S / r1["distance_m"] ** 2))   # S ∝ 1/d², a constant → a/S = κ d²
    closed = lambda d: kappa * d**2 * (d_max - 2 * d) / (1 + 2 * kappa * d**2)  # noqa: E731
    pulsed_closed_diff = float(np.max(np.abs(r1["error_m"] - closed(r1["distance_m"]))) * C.MM)
    print(f"pulsed + environment: ambient/signal = {kappa:.4f} d²; max |rendered − closed form| {pulsed_closed_diff:.2f} mm")

    # ---------------- periods (from the dense synthetic curves)
    def period(mod):
        """Period of the wiggle: the strongest harmonic of the error over one ambiguity distance."""
        d_amb = float(mod.ambiguity_distances_m()[0])
        err = decode.systematic_error_curve(mod, np.linspace(0.0, d_amb, 20000, endpoint=False))[0]
        spec = np.abs(np.fft.rfft(err - err.mean()))
        return d_amb / int(np.argmax(spec[1:]) + 1) if spec.max() > 1e-9 else None

    mods = {"square 20 MHz": sq20, "square 30 MHz": sq30, "sine 20 MHz": si20, "sine 30 MHz": si30}

    # ---------------- plot
    fig, ax = C.plt.subplots(1, 3, figsize=(16, 4.8))
    for name, c in (("square 20 MHz", "C0"), ("square 30 MHz", "C1"), ("sine 20 MHz", "C2"), ("sine 30 MHz", "C3")):
        ax[0].plot(dense, syn[name] * C.MM, "-", color=c, lw=1, label=f"{name} (synthetic)")
        ax[0].plot(rendered[name]["distance_m"], rendered[name]["error_m"] * C.MM, "o", color=c, ms=3.5, mfc="none",
                   label=f"{name} (rendered, env. map)")
    ax[0].set_xlabel("true distance (m)")
    ax[0].set_ylabel("decoded − true distance (mm)")
    ax[0].set_title("CW, 4 phase steps")
    ax[0].set_ylim(-100, 150)
    ax[0].legend(fontsize=7, ncol=2, loc="upper center")
    ax[0].grid(alpha=0.3)
    dp = dense[dense < d_max]
    ax[1].plot(dp, syn["pulsed, no ambient"] * C.MM, "-", color="C2", lw=1, label="no ambient (synthetic)")
    ax[1].plot(r0["distance_m"], r0["error_m"] * C.MM, "o", color="C2", ms=3.5, mfc="none", label="no ambient (rendered)")
    ax[1].plot(dp, closed(dp) * C.MM, "-", color="C3", lw=1, label=f"closed form, a/S = {kappa:.3f}·d²")
    ax[1].plot(r1["distance_m"], r1["error_m"] * C.MM, "o", color="C3", ms=3.5, mfc="none",
               label="environment map (rendered)")
    ax[1].axvline(d_max / 2, color="grey", ls=":", lw=0.8)
    ax[1].set_xlabel("true distance (m)")
    ax[1].set_ylabel("decoded − true distance (mm)")
    ax[1].set_title(f"pulsed, 2 buckets, t0 = {PULSE_WIDTH_S * 1e9:.0f} ns (d_max = {d_max:.2f} m)")
    ax[1].legend(fontsize=7)
    ax[1].grid(alpha=0.3)
    ax[2].plot(dense, syn["Kinect v2 (80/16/120 MHz, 3 steps, unwrapped)"] * C.MM, "-", lw=1)
    ax[2].set_xlabel("true distance (m)")
    ax[2].set_ylabel("decoded − true distance (mm)")
    ax[2].set_title("Kinect v2 preset (synthetic): several wiggles summed")
    ax[2].grid(alpha=0.3)
    total = sum(t["seconds"] for t in timing)
    fig.suptitle(f"Systematic error against distance: {sum(len(r['distance_m']) for r in rendered.values())} renders "
                 f"(3×3 px, {cw_spp} spp CW / {args.spp} spp pulsed with ambient, max path 2) in {total:.0f} s")
    fig.tight_layout()

    numbers = {
        "experiment": "SPEC §6.4 / thesis §6.4: systematic error against true distance",
        "synthetic": {name: {"peak_abs_error_mm": float(np.max(np.abs(v)) * C.MM),
                             "period_m": period(mods[name]) if name in mods else None,
                             "ambiguity_distance_m": float(mods[name].ambiguity_distances_m()[0]) if name in mods else None}
                      for name, v in syn.items() if "pulsed" not in name},
        "rendered_vs_synthetic": agree,
        "pulsed_environment_map": {
            "ambient_over_signal_per_m2": kappa,
            "ambient_over_signal_at_1m_2m_3m": [kappa, 4 * kappa, 9 * kappa],
            "error_mm_at": {f"{d:.1f} m": float(e * C.MM) for d, e in zip(r1["distance_m"], r1["error_m"])
                            if abs(d * 10 - round(d * 10)) < 1e-6 and round(d * 10) % 5 == 0},
            "zero_crossing_m (d_max/2)": d_max / 2,
            "max_abs_rendered_minus_closed_form_mm": pulsed_closed_diff,
            "peak_abs_error_mm": float(np.max(np.abs(r1["error_m"])) * C.MM)},
        "rendered": {k: {"distance_m": v["distance_m"], "error_mm": v["error_m"] * C.MM} for k, v in rendered.items()},
        "runtime": timing,
    }
    print(C.runtime_line(timing))
    C.write_outputs(args.out, "systematic_error", fig, numbers, started)


if __name__ == "__main__":
    main()
