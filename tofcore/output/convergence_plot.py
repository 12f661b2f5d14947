"""Convergence plot: a frame's convergence log as a PNG.

``convergence_png(log)`` draws the log of :func:`tofcore.render_progressive`
(``frame.stats["convergence"]``, one row per progressive pass) and returns the
PNG bytes; :func:`tofcore.write_frame` writes them as ``convergence.png``.

=========================  ========  ===========================================================
row key                    unit      drawn as
=========================  ========  ===========================================================
``seconds``                s         x axis, log scale (elapsed wall time at the end of the pass)
``est_depth_error_m``      m         "estimated" curve, y axis in mm, log scale
``rms_error_m`` (optional) m         "actual" curve (RMS error against a reference), same axis
``spp``                    samples   labels on a second x axis on top, at each pass's time
=========================  ========  ===========================================================

Other keys (``pass``, ``rays``, later additions) are ignored; a value that is
missing, None, not a number, NaN, ±inf or not positive (log axes) leaves its
point out. The title line gives the final (last) row: samples per pixel,
seconds, estimated error and the actual error when there is one. An empty log
draws empty axes saying "no convergence log"; a log without any estimate says
"no estimate".

Backends (``backend="auto"`` takes the first importable one):

==============  ============================================================================
backend         drawing
==============  ============================================================================
``matplotlib``  Agg canvas (no pyplot, no global state), anti-aliased, tick labels by matplotlib
``opencv``      ``cv2.line`` / ``cv2.circle`` / ``cv2.putText`` (Hershey simplex, ASCII)
``numpy``       pure NumPy raster: axes, grid, polylines, markers and a 5×7 pixel font
                (upper case); for Blender's Python, which has neither of the others
==============  ============================================================================

The PNG is encoded by :func:`tofcore.output.png.encode_png` (OpenCV when importable, else
NumPy + zlib), as 8-bit RGB.

Example
-------
>>> png = convergence_png(frame.stats["convergence"])            # doctest: +SKIP
>>> Path("convergence.png").write_bytes(png)                      # doctest: +SKIP
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from ..native import inside_blender, optional_module
from .png import encode_png

cv2 = optional_module("cv2")

BACKENDS = ("auto", "matplotlib", "opencv", "numpy")

_MIN_WIDTH_PX, _MIN_HEIGHT_PX = 200, 150

# Colours, 8-bit RGB.
_WHITE = (255, 255, 255)
_INK = (30, 30, 30)
_GRID = (222, 222, 222)
_SPP_INK = (90, 90, 90)
_EST_RGB = (31, 119, 180)     # estimated error: blue
_RMS_RGB = (214, 39, 40)      # actual error: red

# Axis ranges (log10) when there is nothing to plot: 0.1 – 10 s, 0.1 – 100 mm.
_DEFAULT_X_LOG10 = (-1.0, 1.0)
_DEFAULT_Y_LOG10 = (-1.0, 2.0)
# A range narrower than this (decades) is widened around its centre, so a single point sits in the middle.
_MIN_SPAN_LOG10 = 0.6


# --------------------------------------------------------------------------- public API

def convergence_png(log: Iterable[Mapping] | None, *, width_px: int = 640, height_px: int = 400,
                    backend: str = "auto") -> bytes:
    """PNG bytes (8-bit RGB, ``width_px`` × ``height_px``) of the convergence log ``log``.

    Parameters
    ----------
    log : rows (mappings) of ``frame.stats["convergence"]``; keys as in the module docstring, extra keys
        ignored; None or empty draws "no convergence log".
    width_px, height_px : image size in pixels, at least 200 × 150.
    backend : ``"auto"`` (matplotlib, else OpenCV, else NumPy), ``"matplotlib"``, ``"opencv"`` or ``"numpy"``.

    Raises
    ------
    ValueError : unknown backend, image too small, or a row that is not a mapping.
    ImportError : ``"matplotlib"`` or ``"opencv"`` asked for but not importable.
    """
    if backend not in BACKENDS:
        raise ValueError(f"convergence_png: backend must be one of {BACKENDS}, got {backend!r}")
    for name, value, least in (("width_px", width_px, _MIN_WIDTH_PX), ("height_px", height_px, _MIN_HEIGHT_PX)):
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < least:
            raise ValueError(f"convergence_png: {name} must be an integer >= {least}, got {value!r}")
    curves = read_log(log)
    if backend == "auto":
        backend = "matplotlib" if _matplotlib() is not None else "opencv" if cv2 is not None else "numpy"
    if backend == "matplotlib":
        rgb = _draw_matplotlib(curves, int(width_px), int(height_px))
    else:
        if backend == "opencv" and cv2 is None:
            raise ImportError("convergence_png: backend 'opencv' needs OpenCV, which is not installed: "
                              "pip install opencv-contrib-python-headless")
        canvas = _CvCanvas(width_px, height_px) if backend == "opencv" else _NumpyCanvas(width_px, height_px)
        _draw_raster(canvas, curves)
        rgb = canvas.image
    return encode_png(np.ascontiguousarray(rgb, dtype=np.uint8))


@dataclass(frozen=True)
class Curves:
    """What the plot shows, read from a convergence log (:func:`read_log`).

    ``seconds``, ``spp``, ``est_mm``, ``rms_mm`` are aligned, one entry per row with a usable time
    (finite, > 0 s); an error that cannot be drawn (missing, None, NaN, ≤ 0) is NaN.
    """

    seconds: np.ndarray        # (N,) elapsed time, s
    spp: tuple                 # (N,) samples per pixel (int, or None)
    est_mm: np.ndarray         # (N,) estimated RMS depth error, mm
    rms_mm: np.ndarray         # (N,) actual RMS error against the reference, mm
    has_rms: bool              # whether any row has an actual error (the curve and its legend entry)
    title: str                 # the title line (ASCII)
    empty: bool                # no rows at all

    @property
    def message(self) -> str | None:
        """Text in the middle of the plot when there is no estimate curve, else None."""
        if self.empty:
            return "no convergence log"
        if not np.isfinite(self.est_mm).any():
            return "no estimate" if len(self.seconds) else "no timed passes"
        return None


def read_log(log: Iterable[Mapping] | None) -> Curves:
    """The :class:`Curves` of ``log`` (see :func:`convergence_png`); ValueError for a row that is no mapping."""
    rows = list(log or [])
    for i, row in enumerate(rows):
        if not isinstance(row, Mapping):
            raise ValueError(f"convergence_png: log[{i}] must be a mapping (one pass), got {type(row).__name__}")
    timed = [row for row in rows if _positive(row.get("seconds")) is not None]
    est_mm = [_positive(row.get("est_depth_error_m")) for row in timed]
    rms_mm = [_positive(row.get("rms_error_m")) for row in timed]
    return Curves(
        seconds=np.array([_positive(row.get("seconds")) for row in timed], dtype=np.float64),
        spp=tuple(_integer(row.get("spp")) for row in timed),
        est_mm=np.array([math.nan if v is None else v * 1000.0 for v in est_mm], dtype=np.float64),
        rms_mm=np.array([math.nan if v is None else v * 1000.0 for v in rms_mm], dtype=np.float64),
        has_rms=any(_number(row.get("rms_error_m")) is not None for row in rows),
        title=title_line(rows),
        empty=not rows,
    )


def title_line(log: list[Mapping]) -> str:
    """``"final: 32 spp, 12.3 s, est. depth error 1.23 mm, actual 1.40 mm"`` from the last row (ASCII)."""
    if not log:
        return "final: no passes"
    last = log[-1]
    spp, seconds = _integer(last.get("spp")), _number(last.get("seconds"))
    est, rms = _number(last.get("est_depth_error_m")), _number(last.get("rms_error_m"))
    parts = [f"{'?' if spp is None else spp} spp", "? s" if seconds is None else f"{_fmt_seconds(seconds)} s",
             "no estimate" if est is None else f"est. depth error {est * 1000:.3g} mm"]
    if rms is not None:
        parts.append(f"actual {rms * 1000:.3g} mm")
    return "final: " + ", ".join(parts)


# --------------------------------------------------------------------------- values

def _number(value) -> float | None:
    """``value`` as a finite float, None if it is not one (None, bool, string, NaN, inf)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _positive(value) -> float | None:
    """``value`` as a finite float > 0 (drawable on a log axis), else None."""
    value = _number(value)
    return value if value is not None and value > 0 else None


def _integer(value) -> int | None:
    value = _number(value)
    return None if value is None else int(round(value))


def _fmt_seconds(seconds: float) -> str:
    return f"{seconds:.3g}" if seconds < 100 else f"{seconds:.0f}"


def _log_range(values: np.ndarray, default: tuple[float, float]) -> tuple[float, float]:
    """(lo, hi) log10 bounds around the finite positive ``values``: 5 % padding, at least 0.6 decades."""
    values = values[np.isfinite(values) & (values > 0)]
    if not values.size:
        return default
    lo, hi = math.log10(values.min()), math.log10(values.max())
    if hi - lo < _MIN_SPAN_LOG10:
        centre = 0.5 * (lo + hi)
        return centre - _MIN_SPAN_LOG10 / 2, centre + _MIN_SPAN_LOG10 / 2
    pad = 0.05 * (hi - lo)
    return lo - pad, hi + pad


def log_ticks(lo: float, hi: float, most: int = 8) -> list[float]:
    """Tick values in [10**lo, 10**hi]: decades, else 1-2-5 (fewer than three), else 1…9, at most ``most``."""
    for multiples, fewest in (((1,), 3), ((1, 2, 5), 3), (tuple(range(1, 10)), 2)):
        ticks = [m * 10.0 ** k for k in range(math.floor(lo) - 1, math.ceil(hi) + 1) for m in multiples]
        ticks = [t for t in ticks if lo - 1e-9 <= math.log10(t) <= hi + 1e-9]
        if len(ticks) >= fewest:
            step = math.ceil(len(ticks) / most)
            return ticks[::step]
    return [float(f"{10.0 ** lo:.2g}"), float(f"{10.0 ** hi:.2g}")]


def tick_text(value: float) -> str:
    """Short tick label: ``0.002``, ``5``, ``2000``, ``1e-05``."""
    return f"{value:g}" if 1e-3 <= value < 1e5 else f"{value:.0e}"


def _spaced(positions: list[float], widths: list[float], gap: float) -> list[int]:
    """Indices of labels (centred at ``positions``, ``widths`` wide) kept left to right without overlap;
    the last label is always kept, dropping earlier ones in its way."""
    kept: list[int] = []
    right = -math.inf
    for i, (x, w) in enumerate(zip(positions, widths)):
        if x - w / 2 >= right + gap:
            kept.append(i)
            right = x + w / 2
    if positions and kept[-1] != len(positions) - 1:
        last = len(positions) - 1
        left = positions[last] - widths[last] / 2
        kept = [i for i in kept if positions[i] + widths[i] / 2 + gap <= left] + [last]
    return kept


# --------------------------------------------------------------------------- matplotlib

_MATPLOTLIB: list = []


def _matplotlib():
    """(Figure, FigureCanvasAgg), or None when matplotlib is not importable or this is Blender's process
    (:mod:`tofcore.native`; checked once)."""
    if not _MATPLOTLIB and inside_blender():
        _MATPLOTLIB.append(None)
    if not _MATPLOTLIB:
        try:
            from matplotlib.backends.backend_agg import FigureCanvasAgg
            from matplotlib.figure import Figure
            _MATPLOTLIB.append((Figure, FigureCanvasAgg))
        except ImportError:
            _MATPLOTLIB.append(None)
    return _MATPLOTLIB[0]


def _draw_matplotlib(curves: Curves, width_px: int, height_px: int) -> np.ndarray:
    """(H, W, 3) uint8 RGB drawn by matplotlib's Agg canvas (no pyplot)."""
    classes = _matplotlib()
    if classes is None:
        raise ImportError("convergence_png: backend 'matplotlib' needs matplotlib, which is not installed: "
                          "pip install matplotlib")
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter, NullLocator

    figure_class, canvas_class = classes
    dpi = 100
    figure = figure_class(figsize=(width_px / dpi, height_px / dpi), dpi=dpi, layout="constrained")
    canvas = canvas_class(figure)
    ax = figure.add_subplot()
    x_lo, x_hi = _log_range(curves.seconds, _DEFAULT_X_LOG10)
    y_lo, y_hi = _log_range(np.concatenate([curves.est_mm, curves.rms_mm]), _DEFAULT_Y_LOG10)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(10 ** x_lo, 10 ** x_hi)
    ax.set_ylim(10 ** y_lo, 10 ** y_hi)
    for axis, (lo, hi) in ((ax.xaxis, (x_lo, x_hi)), (ax.yaxis, (y_lo, y_hi))):  # the raster backends' ticks
        axis.set_major_locator(FixedLocator(log_ticks(lo, hi)))
        axis.set_major_formatter(FuncFormatter(lambda value, _position: tick_text(value)))
        axis.set_minor_formatter(NullFormatter())
    ax.grid(True, which="major", color="0.85", linewidth=0.8)
    ax.grid(True, which="minor", color="0.93", linewidth=0.5)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("RMS depth error (mm)")
    est = np.isfinite(curves.est_mm)
    if est.any():
        ax.plot(curves.seconds[est], curves.est_mm[est], "o-", color=np.array(_EST_RGB) / 255, markersize=4,
                label="estimated (Monte Carlo)")
    rms = np.isfinite(curves.rms_mm)
    if rms.any():
        ax.plot(curves.seconds[rms], curves.rms_mm[rms], "s--", color=np.array(_RMS_RGB) / 255, markersize=4,
                label="actual (vs reference)")
    if est.any() or rms.any():
        ax.legend(loc="upper right", fontsize=8)
    if curves.message:
        ax.text(0.5, 0.5, curves.message, transform=ax.transAxes, ha="center", va="center", fontsize=12,
                color="0.3")
    top = ax.twiny()
    top.set_xscale("log")
    top.set_xlim(ax.get_xlim())
    top.xaxis.set_minor_locator(NullLocator())
    with_spp = [i for i, spp in enumerate(curves.spp) if spp is not None]
    if with_spp:
        span_px = figure.get_figwidth() * dpi * 0.8
        positions = [(math.log10(curves.seconds[i]) - x_lo) / (x_hi - x_lo) * span_px for i in with_spp]
        keep = _spaced(positions, [7.0 * len(str(curves.spp[i])) for i in with_spp], gap=6.0)
        top.set_xticks([curves.seconds[with_spp[k]] for k in keep])
        top.set_xticklabels([str(curves.spp[with_spp[k]]) for k in keep], fontsize=8)
    else:
        top.set_xticks([])
    top.set_xlabel("samples per pixel", fontsize=9)
    figure.suptitle(curves.title, fontsize=10)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    if rgba.shape[:2] != (height_px, width_px):  # rounding of figsize × dpi: pad or crop to the size asked
        out = np.full((height_px, width_px, 4), 255, np.uint8)
        h, w = min(height_px, rgba.shape[0]), min(width_px, rgba.shape[1])
        out[:h, :w] = rgba[:h, :w]
        rgba = out
    return rgba[..., :3].copy()


# --------------------------------------------------------------------------- raster backends

class _RasterCanvas:
    """A white (H, W, 3) uint8 RGB image and the drawing primitives the raster plot needs.

    Both implementations draw in pixel coordinates (x right, y down); ``text`` places the top-left
    corner of the text at (x, y); ``size`` is 1 (labels) or 2 (title, messages).
    """

    def __init__(self, width_px: int, height_px: int) -> None:
        self.width, self.height = int(width_px), int(height_px)
        self.image = np.full((self.height, self.width, 3), 255, np.uint8)

    def line(self, x0: float, y0: float, x1: float, y1: float, rgb, thickness: int = 1) -> None:
        raise NotImplementedError

    def marker(self, x: float, y: float, rgb, radius: int = 3) -> None:
        raise NotImplementedError

    def text(self, x: float, y: float, text: str, rgb, size: int = 1) -> None:
        raise NotImplementedError

    def text_size(self, text: str, size: int = 1) -> tuple[int, int]:
        """(width, height) in pixels of ``text``."""
        raise NotImplementedError

    def fill(self, x0: int, y0: int, x1: int, y1: int, rgb) -> None:
        """Fill the rectangle [x0, x1) × [y0, y1), clipped to the image."""
        x0, x1 = max(0, int(x0)), min(self.width, int(x1))
        y0, y1 = max(0, int(y0)), min(self.height, int(y1))
        if x0 < x1 and y0 < y1:
            self.image[y0:y1, x0:x1] = rgb


class _CvCanvas(_RasterCanvas):
    """Drawing by OpenCV (anti-aliased lines, Hershey simplex text)."""

    _FONT_SCALE = {1: 0.4, 2: 0.5}

    def line(self, x0, y0, x1, y1, rgb, thickness=1):
        cv2.line(self.image, (round(x0), round(y0)), (round(x1), round(y1)), rgb, thickness, cv2.LINE_AA)

    def marker(self, x, y, rgb, radius=3):
        cv2.circle(self.image, (round(x), round(y)), radius, rgb, -1, cv2.LINE_AA)

    def text(self, x, y, text, rgb, size=1):
        (_, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, self._FONT_SCALE[size], 1)
        cv2.putText(self.image, text, (round(x), round(y) + h), cv2.FONT_HERSHEY_SIMPLEX, self._FONT_SCALE[size],
                    rgb, 1, cv2.LINE_AA)

    def text_size(self, text, size=1):
        (w, h), baseline = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, self._FONT_SCALE[size], 1)
        return w, h + baseline


# 5×7 pixel glyphs, one string of 5 bits per row, top row first. Lower case is drawn as upper case.
_GLYPH_ROWS = {
    "0": "01110 10001 10011 10101 11001 10001 01110", "1": "00100 01100 00100 00100 00100 00100 01110",
    "2": "01110 10001 00001 00010 00100 01000 11111", "3": "11111 00010 00100 00010 00001 10001 01110",
    "4": "00010 00110 01010 10010 11111 00010 00010", "5": "11111 10000 11110 00001 00001 10001 01110",
    "6": "00110 01000 10000 11110 10001 10001 01110", "7": "11111 00001 00010 00100 01000 01000 01000",
    "8": "01110 10001 10001 01110 10001 10001 01110", "9": "01110 10001 10001 01111 00001 00010 01100",
    ".": "00000 00000 00000 00000 00000 01100 01100", ",": "00000 00000 00000 00000 01100 00100 01000",
    "-": "00000 00000 00000 11111 00000 00000 00000", "+": "00000 00100 00100 11111 00100 00100 00000",
    ":": "00000 01100 01100 00000 01100 01100 00000", "/": "00001 00010 00010 00100 01000 01000 10000",
    "(": "00010 00100 01000 01000 01000 00100 00010", ")": "01000 00100 00010 00010 00010 00100 01000",
    "?": "01110 10001 00001 00010 00100 00000 00100", " ": "00000 00000 00000 00000 00000 00000 00000",
    "A": "01110 10001 10001 11111 10001 10001 10001", "B": "11110 10001 10001 11110 10001 10001 11110",
    "C": "01110 10001 10000 10000 10000 10001 01110", "D": "11110 10001 10001 10001 10001 10001 11110",
    "E": "11111 10000 10000 11110 10000 10000 11111", "F": "11111 10000 10000 11110 10000 10000 10000",
    "G": "01110 10001 10000 10111 10001 10001 01111", "H": "10001 10001 10001 11111 10001 10001 10001",
    "I": "01110 00100 00100 00100 00100 00100 01110", "K": "10001 10010 10100 11000 10100 10010 10001",
    "L": "10000 10000 10000 10000 10000 10000 11111", "M": "10001 11011 10101 10101 10001 10001 10001",
    "N": "10001 10001 11001 10101 10011 10001 10001", "O": "01110 10001 10001 10001 10001 10001 01110",
    "P": "11110 10001 10001 11110 10000 10000 10000", "R": "11110 10001 10001 11110 10100 10010 10001",
    "S": "01111 10000 10000 01110 00001 00001 11110", "T": "11111 00100 00100 00100 00100 00100 00100",
    "U": "10001 10001 10001 10001 10001 10001 01110", "V": "10001 10001 10001 10001 10001 01010 00100",
    "W": "10001 10001 10001 10101 10101 10101 01010", "X": "10001 10001 01010 00100 01010 10001 10001",
    "Y": "10001 10001 01010 00100 00100 00100 00100",
}
_GLYPHS = {char: np.array([[bit == "1" for bit in row] for row in rows.split()], dtype=bool)
           for char, rows in _GLYPH_ROWS.items()}
_UNKNOWN_GLYPH = np.pad(np.ones((5, 3), bool), 1) & ~np.pad(np.ones((3, 1), bool), ((2, 2), (2, 2)))  # a box


class _NumpyCanvas(_RasterCanvas):
    """Drawing in pure NumPy: 1-pixel-per-step lines, square markers, the 5×7 font (scaled by ``size``)."""

    def _dot(self, xs: np.ndarray, ys: np.ndarray, rgb, thickness: int) -> None:
        offsets = np.arange(thickness) - thickness // 2
        xs = (np.rint(xs).astype(np.int64)[:, None] + offsets).ravel()
        ys = np.rint(ys).astype(np.int64)
        for dy in offsets:
            yy = np.repeat(ys + dy, thickness)
            keep = (xs >= 0) & (xs < self.width) & (yy >= 0) & (yy < self.height)
            self.image[yy[keep], xs[keep]] = rgb

    def line(self, x0, y0, x1, y1, rgb, thickness=1):
        steps = int(max(abs(x1 - x0), abs(y1 - y0))) + 1
        self._dot(np.linspace(x0, x1, steps + 1), np.linspace(y0, y1, steps + 1), rgb, thickness)

    def marker(self, x, y, rgb, radius=3):
        self.fill(round(x) - radius + 1, round(y) - radius + 1, round(x) + radius, round(y) + radius, rgb)

    def text(self, x, y, text, rgb, size=1):
        x, y = int(round(x)), int(round(y))
        for i, char in enumerate(text.upper()):
            glyph = np.kron(_GLYPHS.get(char, _UNKNOWN_GLYPH), np.ones((size, size), bool))
            gx = x + i * 6 * size
            rows, cols = np.nonzero(glyph)
            rows, cols = rows + y, cols + gx
            keep = (cols >= 0) & (cols < self.width) & (rows >= 0) & (rows < self.height)
            self.image[rows[keep], cols[keep]] = rgb

    def text_size(self, text, size=1):
        return max(0, len(text) * 6 - 1) * size, 7 * size


def text_canvas(width_px: int, height_px: int) -> _RasterCanvas:
    """A white raster canvas for labels: OpenCV's when importable, else the NumPy one."""
    return _CvCanvas(width_px, height_px) if cv2 is not None else _NumpyCanvas(width_px, height_px)


def _turned_text(canvas: _RasterCanvas, x: float, y_centre: float, text: str, rgb) -> None:
    """``text`` turned 90° counter-clockwise (read bottom to top), left edge at ``x``, centred on ``y_centre``."""
    w, h = canvas.text_size(text, 1)
    flat = type(canvas)(w + 2, h + 2)
    flat.text(1, 1, text, rgb, 1)
    turned = np.rot90(flat.image)                      # (w + 2, h + 2, 3)
    x0, y0 = int(round(x)), int(round(y_centre - turned.shape[0] / 2))
    region = canvas.image[max(0, y0):y0 + turned.shape[0], max(0, x0):x0 + turned.shape[1]]
    part = turned[max(0, -y0):max(0, -y0) + region.shape[0], max(0, -x0):max(0, -x0) + region.shape[1]]
    ink = (part != 255).any(axis=-1)
    region[ink] = part[ink]


def _draw_raster(canvas: _RasterCanvas, curves: Curves) -> None:
    """The plot on ``canvas``: title, spp axis on top, log–log axes with grid and tick labels, curves,
    legend, and the message when there is no estimate."""
    width, height = canvas.width, canvas.height
    _, label_h = canvas.text_size("0", 1)
    _, title_h = canvas.text_size("0", 2)
    x_lo, x_hi = _log_range(curves.seconds, _DEFAULT_X_LOG10)
    y_lo, y_hi = _log_range(np.concatenate([curves.est_mm, curves.rms_mm]), _DEFAULT_Y_LOG10)
    y_ticks = log_ticks(y_lo, y_hi)
    y_labels = [tick_text(t) for t in y_ticks]
    y_title = "RMS depth error (mm)"
    _, y_title_h = canvas.text_size(y_title, 1)
    # Plot area [left, right] × [top, bottom] in pixels; the y-axis title, turned, left of the tick labels.
    left = 6 + y_title_h + 8 + max(canvas.text_size(s, 1)[0] for s in y_labels) + 8
    right = width - 16
    top = 8 + title_h + 10 + label_h + 4 + label_h + 8
    bottom = height - (6 + label_h + 8 + label_h + 8)

    def px(seconds: float) -> float:
        return left + (math.log10(seconds) - x_lo) / (x_hi - x_lo) * (right - left)

    def py(error_mm: float) -> float:
        return bottom - (math.log10(error_mm) - y_lo) / (y_hi - y_lo) * (bottom - top)

    # Title, centred; the small font when the large one does not fit.
    title_size = 2 if canvas.text_size(curves.title, 2)[0] <= width - 8 else 1
    title_w, _ = canvas.text_size(curves.title, title_size)
    canvas.text(max(4, (width - title_w) / 2), 8, curves.title, _INK, title_size)
    # Grid and tick labels.
    for tick, label in zip(y_ticks, y_labels):
        y = py(tick)
        canvas.line(left, y, right, y, _GRID)
        w, h = canvas.text_size(label, 1)
        canvas.text(left - 6 - w, y - h / 2, label, _INK, 1)
    for tick in log_ticks(x_lo, x_hi):
        x = px(tick)
        canvas.line(x, top, x, bottom, _GRID)
        canvas.line(x, bottom, x, bottom + 4, _INK)
        label = tick_text(tick)
        w, _ = canvas.text_size(label, 1)
        canvas.text(x - w / 2, bottom + 6, label, _INK, 1)
    _turned_text(canvas, 6, (top + bottom) / 2, y_title, _INK)
    axis_label = "time (s)"
    w, _ = canvas.text_size(axis_label, 1)
    canvas.text((left + right - w) / 2, bottom + 6 + label_h + 8, axis_label, _INK, 1)
    # The spp axis on top: a tick and the samples per pixel at each pass's time.
    with_spp = [i for i, spp in enumerate(curves.spp) if spp is not None]
    positions = [px(curves.seconds[i]) for i in with_spp]
    texts = [str(curves.spp[i]) for i in with_spp]
    spp_y = top - 4 - label_h
    for k in _spaced(positions, [canvas.text_size(s, 1)[0] for s in texts], gap=6):
        canvas.line(positions[k], top, positions[k], top - 3, _SPP_INK)
        w, _ = canvas.text_size(texts[k], 1)
        canvas.text(positions[k] - w / 2, spp_y, texts[k], _SPP_INK, 1)
    spp_label = "samples per pixel" if with_spp else "samples per pixel: -"
    canvas.text(left, spp_y - label_h - 4, spp_label, _SPP_INK, 1)
    # The frame.
    for x0, y0, x1, y1 in ((left, top, right, top), (left, bottom, right, bottom), (left, top, left, bottom),
                           (right, top, right, bottom)):
        canvas.line(x0, y0, x1, y1, _INK)
    # Curves.
    entries = []
    for values, rgb, label in ((curves.est_mm, _EST_RGB, "estimated, mm"), (curves.rms_mm, _RMS_RGB,
                                                                             "actual vs reference, mm")):
        drawn = np.isfinite(values)
        if not drawn.any():
            continue
        points = [(px(t), py(v)) for t, v in zip(curves.seconds[drawn], values[drawn])]
        for (xa, ya), (xb, yb) in zip(points, points[1:]):
            canvas.line(xa, ya, xb, yb, rgb, 2)
        for x, y in points:
            canvas.marker(x, y, rgb, 3)
        entries.append((label, rgb))
    # Legend, top right inside the plot.
    if entries:
        text_w = max(canvas.text_size(label, 1)[0] for label, _ in entries)
        box_w, row_h = 6 + 22 + 6 + text_w + 6, label_h + 8
        x0, y0 = right - 6 - box_w, top + 6
        canvas.fill(x0, y0, x0 + box_w, y0 + row_h * len(entries) + 4, _WHITE)
        for j, (label, rgb) in enumerate(entries):
            y = y0 + 4 + j * row_h + label_h / 2
            canvas.line(x0 + 6, y, x0 + 28, y, rgb, 2)
            canvas.marker(x0 + 17, y, rgb, 3)
            canvas.text(x0 + 34, y - label_h / 2, label, _INK, 1)
    if curves.message:
        w, h = canvas.text_size(curves.message, 2)
        canvas.text((left + right - w) / 2, (top + bottom - h) / 2, curves.message, _SPP_INK, 2)
