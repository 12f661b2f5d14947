"""Colour bars and legends drawn beside the preview PNGs, so a picture says what its colours mean.

==========================  ===================================================================
function                    what it adds
==========================  ===================================================================
:func:`with_colour_bar`     a vertical bar of the colour map on the right, its upper and lower
                            limit and the unit beside it (``depth.png``, ``error.png``)
:func:`horizontal_bar`      the same as a strip, its limits underneath (``compare.png``)
:func:`with_legend`         rows of a colour swatch and a name below the image (``reason.png``)
==========================  ===================================================================

The image keeps its place: it is the top-left ``H × W`` pixels of the result, the rest white.
Labels are drawn by OpenCV when importable, else by the NumPy 5×7 font of
:mod:`tofcore.convergence_plot` (upper case), so Blender's Python draws them too.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .convergence_plot import text_canvas

_INK = (30, 30, 30)
_WHITE = 255
_BAR_WIDTH_PX = 16
_GAP_PX = 6


def _number(value: float) -> str:
    """A limit as a short label: 3 significant digits, ``–`` when not finite."""
    return f"{value:.3g}" if math.isfinite(value) else "-"


def with_colour_bar(image: np.ndarray, lut: np.ndarray, low: float, high: float, unit: str) -> np.ndarray:
    """(H, W + bar, 3) uint8: ``image`` with a vertical bar of ``lut`` (entry 0 at the bottom, the last at
    the top) on its right, labelled ``high`` at the top, ``low`` at the bottom and ``unit`` between."""
    height, width = image.shape[:2]
    labels = [f"{_number(high)} {unit}", f"{_number(low)} {unit}"]
    probe = text_canvas(8, 8)
    label_w = max(probe.text_size(text, 1)[0] for text in labels)
    label_h = probe.text_size("0", 1)[1]
    canvas = text_canvas(width + _GAP_PX + _BAR_WIDTH_PX + _GAP_PX + label_w + _GAP_PX, max(height, 3 * label_h))
    canvas.image[:height, :width] = image
    top, bottom = 0, canvas.height
    rows = np.linspace(len(lut) - 1, 0, bottom - top).round().astype(np.intp)   # top row = highest entry
    x0 = width + _GAP_PX
    canvas.image[top:bottom, x0:x0 + _BAR_WIDTH_PX] = lut[rows][:, None, :]
    x_text = x0 + _BAR_WIDTH_PX + _GAP_PX
    canvas.text(x_text, top, labels[0], _INK, 1)
    canvas.text(x_text, bottom - label_h, labels[1], _INK, 1)
    return canvas.image


def horizontal_bar(lut: np.ndarray, width: int, low: float, high: float, unit: str) -> np.ndarray:
    """(h, ``width``, 3) uint8 white strip: ``lut`` left (``low``) to right (``high``) as a bar, the limits
    and the unit written under its ends (``compare.png``'s columns)."""
    probe = text_canvas(8, 8)
    label_h = probe.text_size("0", 1)[1]
    canvas = text_canvas(width, 4 + 12 + 4 + label_h + 4)
    columns = np.linspace(0, len(lut) - 1, width - 2 * _GAP_PX).round().astype(np.intp)
    canvas.image[4:16, _GAP_PX:width - _GAP_PX] = lut[columns][None, :, :]
    low_text, high_text = f"{_number(low)} {unit}", f"{_number(high)} {unit}"
    canvas.text(_GAP_PX, 20, low_text, _INK, 1)
    canvas.text(width - _GAP_PX - probe.text_size(high_text, 1)[0], 20, high_text, _INK, 1)
    return canvas.image


def with_legend(image: np.ndarray, entries: Sequence[tuple[str, Sequence[int]]]) -> np.ndarray:
    """(H + legend, max(W, legend width), 3) uint8: ``image`` with one row per (name, RGB) entry below it,
    a swatch with a dark outline and the name."""
    height, width = image.shape[:2]
    probe = text_canvas(8, 8)
    label_h = probe.text_size("0", 1)[1]
    row_h = max(label_h, 10) + 6
    swatch = row_h - 6
    legend_w = _GAP_PX + swatch + _GAP_PX + max(probe.text_size(name, 1)[0] for name, _ in entries) + _GAP_PX
    canvas = text_canvas(max(width, legend_w), height + _GAP_PX + row_h * len(entries))
    canvas.image[:height, :width] = image
    for i, (name, rgb) in enumerate(entries):
        y = height + _GAP_PX + i * row_h
        canvas.fill(_GAP_PX - 1, y - 1, _GAP_PX + swatch + 1, y + swatch + 1, _INK)
        canvas.fill(_GAP_PX, y, _GAP_PX + swatch, y + swatch, tuple(int(c) for c in rgb))
        canvas.text(_GAP_PX + swatch + _GAP_PX, y + (swatch - label_h) / 2, name, _INK, 1)
    return canvas.image
