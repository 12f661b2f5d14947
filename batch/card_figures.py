"""The dataset card's pictures of a randomized set: histograms of what was drawn and of what came out.

For a dataset whose frames were drawn by ``[scenes.randomize]`` (records with ``randomization``),
:func:`diversity_section` writes ``DATASET/card/<name>.png`` — one histogram per drawn number
(:func:`batch.randomize.scalar_draws`: camera distance and angles, object count and sizes, each
material class's parameters, ambient radiance, each sensor-unit key) and per frame figure (valid
fraction, RMS multipath error, RMS depth error against the ground truth) — and returns the card's
Markdown lines that show them. Other datasets get no section and no folder.

A histogram has :data:`BINS` equal bins between the smallest and the largest value; its title gives
the count, the mean and the range.
"""

from __future__ import annotations

import math
import re
import statistics
from pathlib import Path

import numpy as np

from .dataset import CARD_FIGURES as FIGURES
from .dataset import write_bytes_atomic

BINS = 20
#: (record key, title, scale, unit) of the per-frame figures.
_FRAME_FIGURES = (("valid_fraction", "valid fraction", 1.0, ""),
                  ("multipath_rms_m", "RMS multipath error", 1000.0, "mm"),
                  ("rms_depth_error_m", "RMS depth error vs GT", 1000.0, "mm"))


def histogram_png(values: list[float], title: str, unit: str = "", width_px: int = 360,
                  height_px: int = 200) -> np.ndarray:
    """(H, W, 3) uint8 picture of the histogram of ``values`` (see the module docstring)."""
    from tofcore.output.convergence_plot import text_canvas

    canvas = text_canvas(width_px, height_px)
    data = np.asarray(values, dtype=np.float64)
    lo, hi = float(data.min()), float(data.max())
    if hi <= lo:
        lo, hi = lo - 0.5 * (abs(lo) or 1.0), hi + 0.5 * (abs(hi) or 1.0)
    counts, edges = np.histogram(data, bins=BINS, range=(lo, hi))
    left, right, top, bottom = 40, width_px - 10, 34, height_px - 24
    canvas.text(6, 4, title, (0, 0, 0))
    canvas.text(6, 18, f"n {len(data)}  mean {_g(data.mean())}  {_g(data.min())} .. {_g(data.max())} {unit}".rstrip(),
                (90, 90, 90))
    peak = max(int(counts.max()), 1)
    bar = (right - left) / BINS
    for i, n in enumerate(counts):
        h = (bottom - top) * n / peak
        canvas.fill(left + i * bar + 1, bottom - h, left + (i + 1) * bar, bottom, (70, 110, 190))
    canvas.line(left, bottom, right, bottom, (0, 0, 0))
    canvas.line(left, top, left, bottom, (0, 0, 0))
    canvas.text(left, bottom + 6, _g(edges[0]), (0, 0, 0))
    end = _g(edges[-1])
    canvas.text(right - canvas.text_size(end)[0], bottom + 6, end, (0, 0, 0))
    canvas.text(4, top, str(peak), (0, 0, 0))
    return canvas.image


def _g(value: float) -> str:
    return f"{value:.3g}"


def _file_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name) + ".png"


def diversity_section(records: list[dict], root: Path) -> list[str]:
    """Write the histograms of the randomized frames among ``records`` into ``root/card/`` and return the
    card's lines; [] (nothing written) when no ok record holds ``randomization``."""
    from tofcore.output.png import encode_png

    from .randomize import scalar_draws

    ok = [r for r in records if r.get("status") == "ok" and isinstance(r.get("randomization"), dict)]
    if not ok:
        return []
    folder = Path(root) / FIGURES
    if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
        return ["", "## Diversity", "", f"(pictures not written: {folder} is not a folder)"]
    folder.mkdir(exist_ok=True)
    draws: dict[str, list[float]] = {}
    for record in ok:
        for name, values in scalar_draws(record["randomization"]).items():
            draws.setdefault(name, []).extend(values)
    lines = ["", "## Diversity", "",
             f"{len(ok)} randomized frames. What each frame drew is its record's `randomization` (and "
             f"`frame.json`); the pictures are histograms over the frames ({BINS} bins, `{FIGURES}/`).", "",
             "| figure | frames | mean | min | max |", "|---|---|---|---|---|"]
    pictures = []
    for key, title, scale, unit in _FRAME_FIGURES:
        values = [r[key] * scale for r in ok if isinstance(r.get(key), (int, float)) and math.isfinite(r[key])]
        if values:
            pictures.append((f"frame.{key}", values, title, unit))
    pictures += [(name, values, name, "") for name, values in sorted(draws.items())]
    for name, values, title, unit in pictures:
        write_bytes_atomic(folder / _file_name(name), encode_png(histogram_png(values, title, unit)))
        lines.append(f"| {title}{(' (' + unit + ')') if unit else ''} | {len(values)} | {_g(statistics.fmean(values))} "
                     f"| {_g(min(values))} | {_g(max(values))} |")
    lines += [""] + [f"![{title}]({FIGURES}/{_file_name(name)})" for name, _, title, _ in pictures]
    return lines
