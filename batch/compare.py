"""Sensor comparison report: one view rendered with several presets, side by side.

``tofcore-batch compare --scene room --presets kinect_v2,o3d303,xtion2 --out report/`` writes

==================  ===================================================================================
``compare.png``     rows: presets; columns: depth (turbo, one range for all rows), error against the
                    ground truth (depth − gt_depth, blue − / white / red +, one ± limit for all rows),
                    invalid pixels (colour per reason, valid light grey); colour bars with the limits
                    under the depth and error columns, the reason legend below
``compare.md``      the table below, Markdown
``compare.json``    the same numbers (metres, seconds, fractions) and the colour-map limits
``frames/``, ``index.jsonl``, ``README.md``   the frames themselves: the report folder is a dataset
                    (rerunning the same command renders nothing new)
==================  ===================================================================================

Table columns: preset, sensor resolution, spp reached, render time, valid %,
invalid % (with the reasons), RMS and median absolute depth error against the
ground truth (``depth − gt_depth`` over valid pixels), multipath error (RMS of
``distance − direct_distance`` over valid pixels: what the indirect light adds,
noise included).

``--device cpu|gpu|auto`` and ``--workers`` work as for ``tofcore-batch run``
(:mod:`batch.devices`): with ``gpu`` the presets render at once, one per GPU.

Every preset sees the same pose; its own intrinsics decide the field of view,
so the images differ in size and extent: each is scaled (nearest neighbour,
aspect kept) to the same cell width.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from .dataset import utf8_text, write_bytes_atomic, write_json_atomic

#: Width of one image cell in compare.png, pixels.
CELL_WIDTH = 320
_LABEL_WIDTH = 150
_HEADER_HEIGHT = 28
_FOOTER_HEIGHT = 26
_GAP = 4
_BACKGROUND = (40, 40, 40)
_VALID_GREY = (200, 200, 200)


def _set_data(args: argparse.Namespace) -> dict:
    """The command's arguments as a one-scene set (checked by :func:`batch.setfile.parse_set`)."""
    from .setfile import DEMO_SCENES, MESH_SUFFIXES

    scene: dict = {}
    name = args.scene
    if name in DEMO_SCENES:
        scene["demo"] = name
    elif name.endswith(".npz"):
        scene["npz"] = name
    elif name.lower().endswith(MESH_SUFFIXES):
        scene["mesh"] = name
    elif name.endswith(".blend"):
        scene["blend"] = name
    else:
        raise ValueError(f"--scene must be a demo scene {list(DEMO_SCENES)}, a .npz, mesh ({', '.join(MESH_SUFFIXES)}) "
                         f"or .blend file, got {name!r}")
    if (args.eye is None) != (args.target is None):
        raise ValueError("--eye and --target go together")
    if args.eye is not None:
        scene["poses"] = [{"eye": list(args.eye), "target": list(args.target)}]
    if args.camera is not None:
        scene["cameras"] = [args.camera]
    if args.frame is not None:
        scene["frames"] = [args.frame]
    if args.ambient is not None:
        scene["ambient_w_m2_sr"] = args.ambient
    quality = {"spp": args.spp, "max_depth": args.max_depth}
    if args.time_budget is not None:
        quality["time_budget_s"] = args.time_budget
    if args.target_error is not None:
        quality["target_error_m"] = args.target_error
    presets = [p.strip() for p in args.presets.split(",") if p.strip()]
    return {"seed": args.seed, "presets": presets, "resolution_scale": args.resolution_scale, "quality": quality,
            "output": {"formats": ["exr", "png", "json"]}, "scenes": [scene]}


# --------------------------------------------------------------------------- images

def _resize_nearest(image: np.ndarray, width: int) -> np.ndarray:
    """Nearest-neighbour resize to ``width`` columns, aspect kept."""
    h, w = image.shape[:2]
    height = max(1, round(h * width / w))
    rows = np.minimum((np.arange(height) + 0.5) * h / height, h - 1).astype(int)
    cols = np.minimum((np.arange(width) + 0.5) * w / width, w - 1).astype(int)
    return image[rows][:, cols]


def _put_text(canvas: np.ndarray, text: str, x: int, y: int, scale: float = 0.5) -> None:
    """Label the PNG when OpenCV is there (the Markdown table lists the rows either way)."""
    try:
        import cv2
    except ImportError:
        return
    bgr = np.ascontiguousarray(canvas[..., ::-1])
    cv2.putText(bgr, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    canvas[...] = bgr[..., ::-1]


def comparison_image(rows: list[tuple[str, dict[str, np.ndarray]]]) -> tuple[np.ndarray, dict]:
    """(H, W, 3) uint8 side-by-side image and its colour-map limits.

    ``rows``: (label, EXR channels) per preset; the channels used are depth,
    gt_depth, valid and reason.
    """
    from tofcore.output.frame import Reason
    from tofcore.output.legend import horizontal_bar
    from tofcore.output.png import DIVERGING, TURBO, apply_lut
    from tofcore.output.writers import _REASON_RGB

    depths = [np.where(ch["valid"] > 0, ch["depth"], np.nan).astype(np.float64) for _, ch in rows]
    finite = np.concatenate([d[np.isfinite(d)] for d in depths]) if depths else np.array([])
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    errors = [(d - ch["gt_depth"].astype(np.float64)) * 1000.0 for d, (_, ch) in zip(depths, rows)]
    abs_err = np.concatenate([np.abs(e[np.isfinite(e)]) for e in errors]) if errors else np.array([])
    limit_mm = max(1.0, float(np.percentile(abs_err, 99.0)) if abs_err.size else 0.0)
    palette = np.array([_VALID_GREY if r == Reason.VALID else _REASON_RGB[r] for r in Reason], dtype=np.uint8)
    cells = []
    for (label, ch), depth, error in zip(rows, depths, errors):
        depth_rgb = apply_lut((depth - lo) / (hi - lo if hi > lo else 1.0), TURBO)
        error_rgb = apply_lut((error / limit_mm + 1.0) / 2.0, DIVERGING)
        codes = np.clip(reason_codes(ch["reason"]), -1, len(palette) - 1)  # -1 (NaN): the background colour
        shown = np.concatenate([palette, np.array([_BACKGROUND], np.uint8)])[codes]
        cells.append((label, [_resize_nearest(img, CELL_WIDTH) for img in (depth_rgb, error_rgb, shown)]))
    row_heights = [max(img.shape[0] for img in imgs) for _, imgs in cells]
    bars = [horizontal_bar(TURBO, CELL_WIDTH, lo, hi, "m"),
            horizontal_bar(DIVERGING, CELL_WIDTH, -limit_mm, limit_mm, "mm")]
    width = _LABEL_WIDTH + 3 * (CELL_WIDTH + _GAP)
    height = _HEADER_HEIGHT + sum(h + _GAP for h in row_heights) + bars[0].shape[0] + _GAP + _FOOTER_HEIGHT
    canvas = np.empty((height, width, 3), np.uint8)
    canvas[...] = _BACKGROUND
    titles = ("depth", f"depth - ground truth (+-{limit_mm:.0f} mm)", "invalid pixels (reason)")
    for i, title in enumerate(titles):
        _put_text(canvas, title, _LABEL_WIDTH + i * (CELL_WIDTH + _GAP) + 6, 19)
    y = _HEADER_HEIGHT
    for (label, imgs), row_height in zip(cells, row_heights):
        _put_text(canvas, label, 8, y + 20)
        for i, img in enumerate(imgs):
            x = _LABEL_WIDTH + i * (CELL_WIDTH + _GAP)
            canvas[y:y + img.shape[0], x:x + img.shape[1]] = img
        y += row_height + _GAP
    for i, bar in enumerate(bars):  # colour bars under the depth and error columns
        x = _LABEL_WIDTH + i * (CELL_WIDTH + _GAP)
        canvas[y:y + bar.shape[0], x:x + bar.shape[1]] = bar
    y += bars[0].shape[0] + _GAP
    x = 8  # legend of the reason colours
    for r in Reason:
        canvas[y + 8:y + 20, x:x + 12] = palette[int(r)]
        label = r.name.lower().replace("_", " ")
        _put_text(canvas, label, x + 16, y + 19, 0.42)
        x += 16 + 8 * len(label) + 14
    limits = {"depth_m": [lo, hi], "error_limit_mm": limit_mm,
              "reason_colours": {r.name: list(map(int, palette[int(r)])) for r in Reason}}
    return canvas, limits


def reason_codes(reason: np.ndarray) -> np.ndarray:
    """The ``reason`` channel as int64 codes; -1 where it is NaN (damaged frame data: no reason to show or count),
    without NumPy's warning about casting NaN."""
    codes = np.full(reason.shape, -1, np.int64)
    finite = np.isfinite(reason)
    codes[finite] = reason[finite].astype(np.int64)
    return codes


# --------------------------------------------------------------------------- tables

def _mm(value: float | None) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{value * 1000:.1f}"


def table_rows(records: list[dict], channels: list[dict[str, np.ndarray]]) -> list[dict]:
    """One dict per preset: the figures of the module docstring (metres, seconds, fractions)."""
    from tofcore.output.frame import Reason

    rows = []
    for record, ch in zip(records, channels):
        reason = reason_codes(ch["reason"])
        n = reason.size
        rows.append({
            "preset": record["preset"], "sensor": record.get("sensor_name"),
            "width": record["settings"]["width"], "height": record["settings"]["height"],
            "spp": record.get("spp"), "render_seconds": record.get("render_seconds"),
            "valid_fraction": record.get("valid_fraction"),
            "invalid_fraction": 1.0 - record["valid_fraction"] if record.get("valid_fraction") is not None else None,
            "invalid_by_reason": {r.name: float(np.count_nonzero(reason == int(r)) / n) for r in Reason
                                  if r != Reason.VALID and np.any(reason == int(r))},
            "rms_depth_error_m": record.get("rms_depth_error_m"),
            "median_abs_depth_error_m": record.get("median_abs_depth_error_m"),
            "multipath_rms_m": record.get("multipath_rms_m"),
            "job_id": record["job_id"], "dir": record["dir"],
        })
    return rows


def markdown_table(rows: list[dict], title: str) -> str:
    lines = [f"# {title}", "",
             "| preset | resolution | spp | time s | valid % | invalid % | RMS error mm | median abs error mm "
             "| multipath RMS mm | invalid by reason |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        reasons = ", ".join(f"{name.lower()} {100 * f:.1f} %" for name, f in r["invalid_by_reason"].items()) or "–"
        lines.append(
            f"| {r['preset']} | {r['width']}×{r['height']} | {r['spp']} | {r['render_seconds']:.1f} "
            f"| {100 * r['valid_fraction']:.1f} | {100 * r['invalid_fraction']:.1f} | {_mm(r['rms_depth_error_m'])} "
            f"| {_mm(r['median_abs_depth_error_m'])} | {_mm(r['multipath_rms_m'])} | {reasons} |")
    lines += ["", "Errors over valid pixels: depth − ground-truth depth (first hit, noise-free); multipath = "
              "distance − direct-only distance (k = 1). compare.png: one row per preset, in this table's order; "
              "columns: depth, depth − ground truth, invalid pixels (reason); colour bars under the first two."]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- the command

def compare(args: argparse.Namespace) -> int:
    """``tofcore-batch compare``: render, then write compare.png, compare.md and compare.json."""
    import sys

    import tofcore

    from .jobs import expand, group_by_view
    from .run import run_jobs, summary
    from .setfile import parse_set

    from .setfile import FLAG_OF_KEY, flag_error

    try:
        spec = parse_set(_set_data(args), path=None)
    except ValueError as err:
        raise tofcore.ConfigError(flag_error(str(err), FLAG_OF_KEY)) from None
    expansion = expand(spec)
    view = group_by_view(expansion.jobs)[0]  # one view: the first camera of a .blend without --camera
    jobs = list(view.jobs)
    result = run_jobs(jobs, args.out, workers=args.workers, threads_per_worker=args.threads_per_worker,
                      scheduler=args.scheduler, dask_local=args.dask == "local", device=args.device,
                      quiet=args.quiet,
                      description=f"Sensor comparison: {view.label}, presets {', '.join(j.preset for j in jobs)}")
    if result.interrupted is not None:
        raise result.interrupted
    out = Path(args.out)
    records_by_id, _ = _read_index(out)
    records = [records_by_id[j.job_id] for j in jobs if records_by_id.get(j.job_id, {}).get("status") == "ok"]
    if not records:
        print(summary(result, out), file=sys.stderr)
        print("error: no preset rendered; nothing to compare", file=sys.stderr)
        return 1
    channels = [tofcore.read_exr(out / r["dir"] / "frame.exr") for r in records]
    image, limits = comparison_image([(r["preset"], ch) for r, ch in zip(records, channels)])
    from tofcore.output.png import encode_png

    write_bytes_atomic(out / "compare.png", encode_png(image))
    rows = table_rows(records, channels)
    title = f"Sensor comparison: {view.label}"
    write_bytes_atomic(out / "compare.md", utf8_text(markdown_table(rows, title)))
    write_json_atomic(out / "compare.json", {
        "title": title, "scene": view.scene, "view": view.view, "world_from_sensor": records[0]["world_from_sensor"],
        "quality": jobs[0].quality, "set_seed": spec.seed, "rows": rows, "image": "compare.png",
        "image_columns": ["depth", "depth - gt_depth", "invalid pixels (reason)"], "limits": limits,
        "failed": [{"preset": f["preset"], "error": f.get("error")} for f in result.failures]})
    print(markdown_table(rows, title))
    print(f"wrote {out / 'compare.png'}, compare.md, compare.json", file=sys.stderr)
    return result.exit_code


def _read_index(out: Path) -> tuple[dict, dict]:
    from .dataset import Dataset

    return Dataset(out).read_index()
