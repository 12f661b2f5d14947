r"""Light tracing against a closed form: a Lambertian wall lit by the Kinect v2's LED, seen by its camera.

The wall (ρ = 0.8, σ = 0, η = 1: f = ρ/π exactly, no specular lobe) lies 2 m in front of the sensor
(``tofcore.demo_scene("plane")``'s geometry and pose); the LED is the preset's Lambertian emitter 2.5 cm
beside the lens (I(θ) = I₀ cos θ, thesis eq. 2.9). Each pixel's exact value is the pixel-area mean of

.. math:: L(x) = \frac{\rho}{\pi}\, \frac{I_0 \cos\theta_{LED}\, \cos\theta_x}{|x - l|^2}, \qquad
          \tau(x) = (|x - l| + |x - \text{lens}|)/c

over the point x each pixel position sees, by a 12 × 12 midpoint rule through the camera's own
(distorted) ray directions: the integrand is smooth over a pixel, so the rule's error is O(h²) ≈ 1e-6
relative, far below the test's Monte Carlo tolerance. The light tracer (``light_tracer.trace_light``,
bucket k = 1) estimates Σw and Σw·τ per pixel; over ``--seeds`` independent runs the per-pixel means
are compared in blocks of 8 × 8 pixels: every block's z-score (difference over the standard error from
the spread over seeds) must be below 4.5 (with ~50 blocks, a correct estimator exceeds it with probability
< 1e-3), and the frame total within 4 standard errors. The camera's distortion enters through the
Jacobian of W_p; the same check with the Jacobian left out fails (``--no-jacobian``, for the record).

    .venv/bin/python studies/caustics/check_plane.py          # ≈ 1 min on one core
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import tofcore  # noqa: E402
from tofcore.constants import SPEED_OF_LIGHT_M_S  # noqa: E402
from tofcore.scene.demo import suggested_pose  # noqa: E402
from tofcore.tracer.setup import TraceSettings, make_setup  # noqa: E402
from tofcore import backend  # noqa: E402

import light_tracer  # noqa: E402
from frames import sensor_at  # noqa: E402

RHO = 0.8
SUB = 12      # midpoint rule: SUB × SUB positions per pixel
BLOCK = 8     # pixels per block side for the z-scores


def lambert_wall() -> tofcore.Scene:
    """The demo plane's geometry with a pure Lambertian material (σ = 0, η = 1: no Fresnel, no specular)."""
    plane = tofcore.demo_scene("plane")
    wall = tofcore.Material(name="lambert", reflectance=RHO, roughness=0.0, ior=1.0)
    return tofcore.Scene.from_arrays(plane.vertices, plane.triangles, plane.material_ids, [wall],
                                     name="lambert wall", metadata=plane.metadata)


def exact(sensor, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) exact pixel means of the radiance and of radiance × delay (see the module docstring)."""
    cam, led = sensor.camera, sensor.leds[0]
    h, w = cam.height, cam.width
    s = (np.arange(SUB) + 0.5) / SUB - 0.5
    col, row = np.meshgrid(np.arange(w), np.arange(h))
    full = (h, w, SUB, SUB)
    u = np.broadcast_to(col[..., None, None] + s[None, None, :, None], full).ravel()
    v = np.broadcast_to(row[..., None, None] + s[None, None, None, :], full).ravel()
    d_world = cam.ray_directions(u, v) @ pose[:3, :3].T
    lens = pose[:3, 3]
    t = -lens[1] / d_world[:, 1]                       # the wall is the plane y = 0, normal −y
    x = lens + t[:, None] * d_world
    led_pos = pose[:3, 3] + pose[:3, :3] @ np.asarray(led.position_m)
    to_led = led_pos - x
    dist = np.linalg.norm(to_led, axis=1)
    cos_x = -to_led[:, 1] / dist                       # normal (0, −1, 0) faces the sensor
    cos_axis = -(to_led / dist[:, None]) @ pose[:3, 2]
    radiance = RHO / np.pi * led.intensity(cos_axis) * cos_x / dist**2
    tau = (dist + np.linalg.norm(x - lens, axis=1)) / SPEED_OF_LIGHT_M_S
    per_pixel = (h, w, SUB * SUB)
    return radiance.reshape(per_pixel).mean(axis=2), (radiance * tau).reshape(per_pixel).mean(axis=2)


def block_means(images: np.ndarray) -> np.ndarray:
    """(S, H, W) → (S, B) means over BLOCK × BLOCK pixel blocks (partial blocks at the edges dropped)."""
    s, h, w = images.shape
    hb, wb = h // BLOCK, w // BLOCK
    return images[:, :hb * BLOCK, :wb * BLOCK].reshape(s, hb, BLOCK, wb, BLOCK).mean(axis=(2, 4)).reshape(s, -1)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scale", type=float, default=0.125, help="Kinect v2 resolution factor (default 0.125)")
    ap.add_argument("--paths", type=int, default=400_000, help="light paths per seed (default 400000)")
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--no-jacobian", action="store_true", help="leave the distortion Jacobian out (must fail)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    sensor = sensor_at(args.scale)
    scene = lambert_wall()
    pose = suggested_pose(scene)
    ref_l, ref_lt = exact(sensor, pose)
    if args.no_jacobian:
        cam = sensor.camera
        original = type(cam)._jacobian_determinant
        type(cam)._jacobian_determinant = lambda self, x, y: np.ones_like(x)
    shape = (sensor.camera.height, sensor.camera.width)
    radiance, delay = [], []
    for seed in range(args.seeds):
        settings = TraceSettings(world_from_sensor=pose, correlations=[lambda tau: tau], seed=seed, max_depth=1,
                                 sampler="independent")
        setup = make_setup(scene, sensor.camera, sensor.leds, settings, backend.select_device("cpu"))
        sums = light_tracer.trace_light(setup, 0, args.paths)
        radiance.append(sums.signal[0, 0].reshape(shape) / args.paths)
        delay.append(sums.correlation[0, 0, 0].reshape(shape) / args.paths)
    if args.no_jacobian:
        type(sensor.camera)._jacobian_determinant = original
    result = {"scale": args.scale, "paths": args.paths, "seeds": args.seeds, "jacobian": not args.no_jacobian}
    ok = True
    for name, images, ref in (("radiance", np.array(radiance), ref_l), ("radiance x delay", np.array(delay), ref_lt)):
        est = block_means(images)
        truth = block_means(ref[None])[0]
        se = est.std(axis=0, ddof=1) / np.sqrt(len(est))
        z = (est.mean(axis=0) - truth) / se
        total = images.sum(axis=(1, 2))
        z_total = (total.mean() - ref.sum()) / (total.std(ddof=1) / np.sqrt(len(total)))
        rel = total.mean() / ref.sum() - 1.0
        passed = bool(np.abs(z).max() < 4.5 and abs(z_total) < 4.0)
        ok &= passed
        result[name] = {"blocks": len(truth), "max_abs_z": float(np.abs(z).max()), "frame_rel_error": float(rel),
                        "frame_z": float(z_total), "block_rel_se": float(np.median(se / truth)), "passed": passed}
        print(f"{name:17s}: {len(truth)} blocks, max |z| {np.abs(z).max():.2f}, frame total {rel * 100:+.3f} % "
              f"(z {z_total:+.2f}), block standard error {np.median(se / truth) * 100:.2f} %  "
              f"{'ok' if passed else 'FAILED'}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
