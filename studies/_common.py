"""Shared helpers of the thesis studies (``studies/*.py``): sensors, cameras, outputs, run-time records.

Every study is one command, ``.venv/bin/python studies/<name>.py --out out/studies``, and writes
``<out>/<name>.png`` (plots) and ``<out>/<name>.json`` (the numbers). Only tofcore, NumPy and
matplotlib (the ``studies`` extra) are used.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import math
import os
import time
from pathlib import Path

import numpy as np

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import tofcore  # noqa: E402

DPI = 100
MM = 1000.0


def parser(doc: str, *, spp: int, max_depth: int, scale: float | None = None) -> argparse.ArgumentParser:
    """The common command line: --out, --spp, --max-depth, --seed (and --scale where the study has one)."""
    p = argparse.ArgumentParser(description=doc.strip().splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=doc)
    p.add_argument("--out", default="out/studies", help="output folder (default out/studies)")
    p.add_argument("--spp", type=int, default=spp, help=f"samples per pixel (default {spp})")
    p.add_argument("--max-depth", type=int, default=max_depth, help=f"max path length (default {max_depth})")
    p.add_argument("--seed", type=int, default=0, help="render seed (default 0)")
    if scale is not None:
        p.add_argument("--scale", type=float, default=scale,
                       help=f"resolution scale of the Kinect v2 image (default {scale})")
    return p


def kinect(*, noise: bool = False, scattering: bool = False, camera: tofcore.Camera | None = None,
           leds: tuple | None = None) -> tofcore.Sensor:
    """The Kinect v2 preset with noise and lens scattering switched on or off, optionally another camera/LEDs."""
    sensor = tofcore.load_preset("kinect_v2")
    overrides = {}
    if not noise:
        overrides["noise.model"] = "none"
    if not scattering:
        overrides["scattering.model"] = "none"
    if overrides:
        sensor = sensor.replace(**overrides)
    changes = {}
    if camera is not None:
        changes["camera"] = camera
    if leds is not None:
        changes["leds"] = tuple(leds)
    return dataclasses.replace(sensor, **changes) if changes else sensor


def scaled_camera(cam: tofcore.Camera, scale: float) -> tofcore.Camera:
    """The same lens on a sensor with ``scale`` × the pixels (fx, fy, cx, cy scaled; distortion unchanged)."""
    if scale == 1.0:
        return cam
    w, h = max(1, round(cam.width * scale)), max(1, round(cam.height * scale))
    sx, sy = w / cam.width, h / cam.height
    return dataclasses.replace(cam, width=w, height=h, fx=cam.fx * sx, fy=cam.fy * sy,
                               cx=(cam.cx + 0.5) * sx - 0.5, cy=(cam.cy + 0.5) * sy - 0.5)


def band_camera(cam: tofcore.Camera, rows: int) -> tuple[tofcore.Camera, int]:
    """Only ``rows`` image rows around the principal point (a horizontal band; same rays as the full image).

    Returns the cropped camera and the index (in the band) of the row through the principal point, the
    "middle scan line". Use it only without lens scattering (the PSF would need the rest of the image).
    """
    centre = int(round(cam.cy))
    r0 = max(0, centre - rows // 2)
    return dataclasses.replace(cam, height=rows, cy=cam.cy - r0), centre - r0


def remove_object(scene: tofcore.Scene, name: str) -> tofcore.Scene:
    """The scene without the triangles of the objects called ``name``."""
    ids = [i for i, n in enumerate(scene.object_names) if n == name]
    keep = ~np.isin(scene.object_ids, ids)
    return tofcore.Scene.from_arrays(scene.vertices, scene.triangles[keep], scene.material_ids[keep],
                                     scene.materials, object_ids=scene.object_ids[keep],
                                     object_names=scene.object_names, name=f"{scene.name} without {name}",
                                     metadata=scene.metadata)


def with_materials(scene: tofcore.Scene, materials) -> tofcore.Scene:
    """The same geometry with other materials (same indices)."""
    return tofcore.Scene.from_arrays(scene.vertices, scene.triangles, scene.material_ids, list(materials),
                                     object_ids=scene.object_ids, object_names=scene.object_names,
                                     name=scene.name, metadata=scene.metadata)


def runtime(frame: tofcore.Frame, label: str = "") -> dict:
    """Error against run time of one render: wall time, spp, estimated Monte Carlo depth error."""
    st = frame.stats
    conv = st.get("convergence", [])
    est = conv[-1]["est_depth_error_m"] if conv else None
    return {"label": label, "seconds": round(float(st["seconds"]), 3), "spp": int(st["spp"]),
            "max_depth": int(st["max_depth"]), "pixels": int(frame.width * frame.height),
            "rays": int(st["transport"]["rays"]) if "transport" in st else None,
            "est_depth_error_mm": None if est is None else round(est * MM, 3),
            "convergence": [{"seconds": round(r["seconds"], 3), "spp": r["spp"],
                             "est_depth_error_mm": None if r["est_depth_error_m"] is None
                             else round(r["est_depth_error_m"] * MM, 3)} for r in conv]}


def runtime_line(records: list[dict]) -> str:
    """One line per render: 'label: 12.3 s, 64 spp, 256×212 px, est. depth error 1.2 mm'."""
    out = []
    for r in records:
        est = "n/a" if r["est_depth_error_mm"] is None else f"{r['est_depth_error_mm']:.2f} mm"
        out.append(f"{r['label']}: {r['seconds']:.1f} s, {r['spp']} spp, max path length {r['max_depth']}, "
                   f"{r['pixels']} px, est. MC depth error (RMS, highest frequency) {est}")
    return "\n".join(out)


def _plain(x):
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return None if not math.isfinite(v) else v
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def write_outputs(out: str | os.PathLike, name: str, fig, numbers: dict, started: float, *, dpi: int = DPI,
                  colors: int = 256) -> Path:
    """Write ``<out>/<name>.png`` and ``<out>/<name>.json`` (with the script's total wall time).

    The PNG is stored with a palette of ``colors`` colours (noisy error maps need fewer to stay small).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    png = out / f"{name}.png"
    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi)
    plt.close(fig)
    # A 256-colour palette keeps the plots small (docs/images/validation/, ≤ ~150 KB) and looks the same.
    from PIL import Image
    Image.open(buf).convert("RGB").quantize(colors=colors, method=Image.Quantize.MEDIANCUT).save(png, optimize=True)
    numbers = dict(numbers)
    numbers["script_seconds"] = round(time.perf_counter() - started, 1)
    numbers["cpu_count"] = os.cpu_count()
    numbers["load_average_1_5_15min_at_end"] = [round(x, 2) for x in os.getloadavg()]
    (out / f"{name}.json").write_text(json.dumps(_plain(numbers), indent=1) + "\n")
    print(f"wrote {png} and {out / (name + '.json')} ({numbers['script_seconds']} s)")
    return png


def rms(x) -> float:
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def x_z(frame: tofcore.Frame, distance: np.ndarray, row: int) -> tuple[np.ndarray, np.ndarray]:
    """Top-down view of one scan line: sensor-frame x and z (m) of the points at ``distance`` along the rays."""
    d = frame.ray_directions[row].astype(np.float64)
    return d[:, 0] * distance[row], d[:, 2] * distance[row]


def segment_hits_box(p: np.ndarray, q: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N,) True where the segment p → q (N, 3) passes through the axis-aligned box (slab test)."""
    d = q - p
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - p) / d
        t2 = (hi - p) / d
    t_near = np.nanmax(np.minimum(t1, t2), axis=1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=1)
    return (t_near <= t_far) & (t_far > 1e-9) & (t_near < 1 - 1e-9)


def led_shadow(frame: tofcore.Frame, sensor: tofcore.Sensor, lo, hi) -> np.ndarray:
    """(H, W) True where the first-hit point is hidden from the LED by the box [lo, hi]."""
    pose = frame.world_from_sensor
    pts_s = frame.ray_directions.astype(np.float64) * frame.gt_distance[..., None].astype(np.float64)
    pts_w = pts_s.reshape(-1, 3) @ pose[:3, :3].T + pose[:3, 3]
    led_w = np.asarray(sensor.leds[0].position_m) @ pose[:3, :3].T + pose[:3, 3]
    ok = np.isfinite(pts_w).all(axis=1)
    out = np.zeros(len(pts_w), bool)
    out[ok] = segment_hits_box(pts_w[ok], np.broadcast_to(led_w, pts_w[ok].shape), np.asarray(lo), np.asarray(hi))
    return out.reshape(frame.gt_distance.shape)


def box_bounds(scene: tofcore.Scene, name: str = "box") -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (lo, hi) of the object called ``name``."""
    ids = [i for i, n in enumerate(scene.object_names) if n == name]
    v = scene.vertices[scene.triangles[np.isin(scene.object_ids, ids)]].reshape(-1, 3).astype(np.float64)
    return v.min(axis=0), v.max(axis=0)
