"""The dataset card: ``DATASET/README.md``, regenerated from the index after every run."""

from __future__ import annotations

import math
import statistics
from collections import Counter, defaultdict
from datetime import datetime, timezone

from .dataset import CARD, FRAMES, INDEX, RECORD


def _mean(values) -> float | None:
    values = [v for v in values if v is not None]
    return statistics.fmean(values) if values else None


def _fmt(value: float | None, scale: float = 1.0, digits: int = 1) -> str:
    return "–" if value is None else f"{value * scale:.{digits}f}"


def _numbers(values) -> list[float]:
    """The finite numbers among ``values`` (None, NaN and non-numbers left out: records from older runs)."""
    return [float(v) for v in values
            if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)]


def _median(values) -> float | None:
    values = _numbers(values)
    return statistics.median(values) if values else None


def _max(values) -> float | None:
    values = _numbers(values)
    return max(values) if values else None


def convergence_rows(records: list[dict]) -> list[tuple[str, int, float | None, float | None, float | None,
                                                        float | None]]:
    """Per preset (sorted), over its ok records: (preset, frames, median and max final estimated depth
    error in m, median spp, median render seconds); None where no record holds the value."""
    by_preset: dict[str, list[dict]] = defaultdict(list)
    for r in records:
        if r.get("status") == "ok":
            by_preset[r["preset"]].append(r)
    return [(preset, len(rows), _median(r.get("est_depth_error_m") for r in rows),
             _max(r.get("est_depth_error_m") for r in rows), _median(r.get("spp") for r in rows),
             _median(r.get("render_seconds") for r in rows))
            for preset, rows in sorted(by_preset.items())]


def convergence_example(records: list[dict]) -> str | None:
    """``frames/<job_id>/convergence.png`` of the first ok record (by job id) that wrote one, else None."""
    for r in sorted(records, key=lambda r: str(r.get("job_id"))):
        if r.get("status") != "ok" or not r.get("dir"):
            continue
        for entry in r.get("files") or []:
            if entry.get("kind") == "convergence":
                return f"{r['dir']}/{entry['name']}"
    return None


def _convergence_lines(records: list[dict]) -> list[str]:
    rows = convergence_rows(records)
    if not rows:
        return []
    lines = ["", "## Convergence", "",
             "The estimated RMS depth error (Monte Carlo, from the per-pixel variances) after each frame's "
             "last pass, with the samples per pixel and seconds it took; `convergence` in each record has "
             "every pass.", "",
             "| preset | frames ok | median est. depth error mm | max est. depth error mm | median spp | "
             "median render s |", "|---|---|---|---|---|---|"]
    for preset, n, error_median, error_max, spp, seconds in rows:
        lines.append(f"| {preset} | {n} | {_fmt(error_median, 1000, 2)} | {_fmt(error_max, 1000, 2)} "
                     f"| {_fmt(spp, digits=0)} | {_fmt(seconds, digits=2)} |")
    example = convergence_example(records)
    if example:
        lines += ["", f"One frame's convergence (`{example}`):", "", f"![convergence of one frame]({example})"]
    return lines


def device_rows(records: list[dict]) -> list[tuple[str, int]]:
    """(device, frames) for the ok records, most frames first: which devices rendered the dataset."""
    counts: Counter = Counter()
    for r in records:
        if r.get("status") != "ok":
            continue
        device = r.get("device") or {}
        if not device.get("description"):
            counts["not recorded (rendered before records held the device)"] += 1
            continue
        text = device["description"]
        if device.get("name") == "gpu" and r.get("cuda_visible_devices") and "CUDA_VISIBLE_DEVICES" not in text:
            text += f" (CUDA_VISIBLE_DEVICES={r['cuda_visible_devices']})"
        if device.get("fallback_reason"):
            text += f"; asked for {device.get('requested')}, fell back: {device['fallback_reason']}"
        counts[text] += 1
    return counts.most_common()


def _device_lines(rows: list[tuple[str, int]]) -> list[str]:
    if len(rows) <= 1:
        return [f"* rendered on: {rows[0][0]} ({rows[0][1]} frames)" if rows else "* rendered on: –"]
    return [f"* rendered on {len(rows)} devices:"] + [f"  * {text} — {n} frames" for text, n in rows]


def dataset_card(records: list[dict], *, set_file: str | None, description: str = "",
                 jobs_in_set: int | None = None) -> str:
    """Markdown text of the card for ``records`` (the index, one record per job)."""
    ok = [r for r in records if r.get("status") == "ok"]
    failed = [r for r in records if r.get("status") == "failed"]
    scenes = Counter(r["scene"] for r in records)
    views = {(r["scene"], r["view"]["label"]) for r in records}
    by_preset: dict[str, list[dict]] = defaultdict(list)
    for r in records:
        by_preset[r["preset"]].append(r)
    settings = Counter(
        tuple((k, r["settings"].get(k)) for k in ("spp", "max_depth", "time_budget_s", "target_error_m",
                                                   "resolution_scale", "ambient_w_m2_sr"))
        for r in records)
    formats = sorted({f for r in records for f in r["settings"].get("formats", [])})
    lines = [
        "# ToF dataset",
        "",
        f"Generated by `tofcore-batch` (tofcore) — last updated "
        f"{datetime.now(timezone.utc).isoformat(timespec='seconds')}."
        + (f" Set file: `{set_file}`." if set_file else ""),
        "",
    ]
    if description:
        lines += [description, ""]
    lines += [
        "## Contents",
        "",
        f"* frames: **{len(records)}** ({len(ok)} ok, {len(failed)} failed)"
        + (f"; the set defines {jobs_in_set}" if jobs_in_set is not None else ""),
        f"* scenes: {len(scenes)} — " + ", ".join(f"{name} ({n} frames)" for name, n in sorted(scenes.items())),
        f"* views: {len(views)}",
        f"* formats: {', '.join(formats) or '–'}",
        *_device_lines(device_rows(records)),
        "",
        "| preset | sensor | resolution | frames ok | failed | mean render s | mean spp | "
        "mean RMS error vs GT mm | mean multipath RMS mm | mean valid % |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for preset, rows in sorted(by_preset.items()):
        good = [r for r in rows if r.get("status") == "ok"]
        sizes = sorted({f"{r['settings']['width']}×{r['settings']['height']}" for r in rows})
        lines.append(
            f"| {preset} | {', '.join(sorted({str(r.get('sensor_name')) for r in rows}))} | {', '.join(sizes)} "
            f"| {len(good)} | {len(rows) - len(good)} | {_fmt(_mean(r.get('render_seconds') for r in good))} "
            f"| {_fmt(_mean(r.get('spp') for r in good), digits=0)} "
            f"| {_fmt(_mean(r.get('rms_depth_error_m') for r in good), 1000)} "
            f"| {_fmt(_mean(r.get('multipath_rms_m') for r in good), 1000)} "
            f"| {_fmt(_mean(r.get('valid_fraction') for r in good), 100)} |")
    lines += _convergence_lines(records)
    lines += ["", "## Settings", "", "| spp | max_depth | time_budget_s | target_error_m | resolution_scale | "
              "ambient W/(m² sr) | frames |", "|---|---|---|---|---|---|---|"]
    for key, n in settings.most_common():
        values = dict(key)
        lines.append("| " + " | ".join("–" if values[k] is None else str(values[k]) for k in
                                        ("spp", "max_depth", "time_budget_s", "target_error_m", "resolution_scale",
                                         "ambient_w_m2_sr")) + f" | {n} |")
    lines += [
        "",
        "Each frame's render seed is derived from the set seed and the frame's job id (a hash of the scene "
        "file's content, the view, the full sensor description, the quality, the ambient light, the formats "
        "and the set seed), so the same set gives the same frames on any executor and worker count — "
        "except with a time budget, which depends on the machine's speed. The device is not part of the "
        "job: CPU and GPU give the same frame within float32 rounding; `device` in each record says which "
        "rendered it.",
        "",
        "## Layout",
        "",
        "```",
        f"{INDEX}              one JSON record per frame (scene, view, pose, preset, seed, settings, files",
        "                         with SHA-256, render time, convergence, error vs ground truth, status)",
        f"{CARD}                this card",
        f"{FRAMES}/<job_id>/         frame.exr (all channels, float32), depth_mm.png (16-bit mm), previews",
        "                         (depth, intensity, error, reason .png), convergence.png (error against",
        "                         time), points.ply, frame.json,",
        f"                         {RECORD} (the frame's index record; written before the folder appears)",
        "```",
        "",
        "A frame folder appears only when complete (it is written under a temporary name and renamed). "
        "Rerunning `tofcore-batch run` on the same set skips frames whose files match their checksums.",
        "",
        "## Loading",
        "",
        "```python",
        "import json",
        "from pathlib import Path",
        "import tofcore",
        "",
        'root = Path("path/to/this/dataset")',
        f'for line in open(root / "{INDEX}"):',
        "    record = json.loads(line)",
        '    if record["status"] != "ok":',
        "        continue",
        '    folder = root / record["dir"]',
        '    channels = tofcore.read_exr(folder / "frame.exr")   # {name: (H, W) float32}',
        '    depth, gt_depth, valid = channels["depth"], channels["gt_depth"], channels["valid"] > 0',
        '    meta = json.loads((folder / "frame.json").read_text())   # sensor, intrinsics, pose, stats',
        '    world_from_sensor = record["world_from_sensor"]',
        "```",
        "",
        "Depth is the sensor's output (`radial` or `z` per preset), in metres, NaN where invalid (`reason` "
        "says why); `gt_depth` is the noise-free first-hit ground truth, `direct_distance` the distance "
        "without multipath, `distance_k<K>` the distance with paths of at most K bounces.",
    ]
    if failed:
        lines += ["", "## Failed frames", "", "| job | scene/view/preset | error |", "|---|---|---|"]
        for r in failed[:50]:
            error = str(r.get("error", "")).replace("|", "\\|").replace("\n", " ")[:200]
            lines.append(f"| {r['job_id']} | {r['scene']}/{r['view']['label']}/{r['preset']} | {error} |")
        if len(failed) > 50:
            lines.append(f"| … | {len(failed) - 50} more in {INDEX} | |")
        lines += ["", "Retry them with `tofcore-batch run SET.toml --out DATASET --retry-failed`."]
    return "\n".join(lines) + "\n"
