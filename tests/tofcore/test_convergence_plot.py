"""Convergence plot: every backend gives a decodable PNG of the asked size; empty, single-row and None logs."""

import struct
import zlib

import numpy as np
import pytest

from tofcore.output import convergence_plot as cp

W, H = 320, 200
BACKENDS = ("numpy", "opencv", "matplotlib")


def make_log(rows: int = 6, *, rms: bool = False) -> list[dict]:
    """Passes at 1, 2, 4 … spp, doubling time, error falling as 1/√spp; an unknown extra key per row."""
    log = []
    for i in range(rows):
        row = {"pass": i + 1, "seconds": 0.25 * 2 ** i, "spp": 2 ** i, "est_depth_error_m": 0.02 / 2 ** (i / 2),
               "rays": 1000 * 2 ** i, "est_depth_error_p90_m": 0.03}
        if rms:
            row["rms_error_m"] = 0.025 / 2 ** (i / 2)
        log.append(row)
    return log


def backend_available(backend: str) -> None:
    if backend == "opencv" and cp.cv2 is None:
        pytest.skip("OpenCV not installed")
    if backend == "matplotlib" and cp._matplotlib() is None:
        pytest.skip("matplotlib not installed")


def png_header(data: bytes) -> tuple[int, int, int, int]:
    """(width, height, bit depth, colour type) from the IHDR chunk."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    width, height, bit_depth, colour_type = struct.unpack(">IIBB", data[16:26])
    return width, height, bit_depth, colour_type


def decode_rgb(data: bytes) -> np.ndarray:
    """(H, W, 3) uint8 RGB: OpenCV when importable, else the filter-0 PNGs of the NumPy encoder."""
    if cp.cv2 is not None:
        return cp.cv2.imdecode(np.frombuffer(data, np.uint8), cp.cv2.IMREAD_COLOR)[..., ::-1]
    width, height, _, _ = png_header(data)
    idat, pos = b"", 8
    while pos < len(data):
        length, tag = struct.unpack(">I4s", data[pos:pos + 8])
        idat += data[pos + 8:pos + 8 + length] if tag == b"IDAT" else b""
        pos += 12 + length
    rows = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(height, 1 + 3 * width)
    assert (rows[:, 0] == 0).all()
    return rows[:, 1:].reshape(height, width, 3)


def coloured(image: np.ndarray, rgb, tolerance: int = 40) -> int:
    """Pixels within ``tolerance`` of ``rgb`` (per channel)."""
    return int((np.abs(image.astype(int) - np.array(rgb)) <= tolerance).all(axis=-1).sum())


@pytest.mark.parametrize("backend", BACKENDS)
def test_each_backend_draws_both_curves(backend):
    backend_available(backend)
    data = cp.convergence_png(make_log(rms=True), width_px=W, height_px=H, backend=backend)
    assert png_header(data) == (W, H, 8, 2)
    image = decode_rgb(data)
    assert image.shape == (H, W, 3)
    assert coloured(image, cp._EST_RGB) > 50 and coloured(image, cp._RMS_RGB) > 50
    assert coloured(image, (255, 255, 255), 0) > W * H // 2   # mostly white background


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("log", [[], None, make_log(1), [dict(r, est_depth_error_m=None) for r in make_log(4)],
                                 [{"pass": 1}], [{"seconds": float("nan"), "spp": None, "est_depth_error_m": 0.0}]],
                         ids=["empty", "none", "one-row", "all-none", "no-keys", "nan-and-zero"])
def test_degenerate_logs_still_give_a_png(backend, log):
    backend_available(backend)
    data = cp.convergence_png(log, width_px=W, height_px=H, backend=backend)
    assert png_header(data)[:2] == (W, H)
    assert decode_rgb(data).shape == (H, W, 3)


def test_without_an_estimate_the_plot_says_so():
    assert cp.read_log([]).message == "no convergence log"
    assert cp.read_log(None).message == "no convergence log"
    assert cp.read_log([dict(r, est_depth_error_m=None) for r in make_log(3)]).message == "no estimate"
    assert cp.read_log([{"pass": 1, "spp": 1}]).message == "no timed passes"
    assert cp.read_log(make_log(2)).message is None
    # The estimated curve's colour is absent when there is no estimate.
    image = decode_rgb(cp.convergence_png([dict(r, est_depth_error_m=None) for r in make_log(3)],
                                          width_px=W, height_px=H, backend="numpy"))
    assert coloured(image, cp._EST_RGB, 10) == 0


def test_title_names_the_final_pass():
    assert cp.title_line(make_log(6)) == "final: 32 spp, 8 s, est. depth error 3.54 mm"
    assert cp.title_line(make_log(1, rms=True)) == "final: 1 spp, 0.25 s, est. depth error 20 mm, actual 25 mm"
    assert cp.title_line([{"pass": 1, "spp": 4, "seconds": 1.5, "est_depth_error_m": None}]) == \
        "final: 4 spp, 1.5 s, no estimate"
    assert cp.title_line([{}]) == "final: ? spp, ? s, no estimate"
    assert cp.title_line([]) == "final: no passes"


def test_read_log_drops_undrawable_values():
    log = make_log(3) + [{"pass": 4, "seconds": None, "spp": 8, "est_depth_error_m": 0.001},
                         {"pass": 5, "seconds": 4.0, "spp": 16, "est_depth_error_m": float("inf")},
                         {"pass": 6, "seconds": 5.0, "spp": True, "est_depth_error_m": "1 mm"}]
    curves = cp.read_log(log)
    np.testing.assert_allclose(curves.seconds, [0.25, 0.5, 1.0, 4.0, 5.0])
    assert curves.spp == (1, 2, 4, 16, None)
    np.testing.assert_allclose(curves.est_mm, [20.0, 20 / 2 ** 0.5, 10.0, np.nan, np.nan])
    assert not curves.has_rms and np.isnan(curves.rms_mm).all()


def test_log_ticks_and_labels():
    assert cp.log_ticks(-1.0, 2.0) == [0.1, 1.0, 10.0, 100.0]
    assert cp.log_ticks(np.log10(0.3), np.log10(9.0)) == [0.5, 1.0, 2.0, 5.0]
    narrow = cp.log_ticks(np.log10(1.1), np.log10(1.3))
    assert len(narrow) == 2
    assert len(cp.log_ticks(-20.0, 20.0)) <= 8
    assert [cp.tick_text(v) for v in (0.002, 5.0, 2000.0, 1e-5)] == ["0.002", "5", "2000", "1e-05"]


def test_spaced_labels_keep_the_last_and_never_overlap():
    kept = cp._spaced([0, 5, 10, 100, 104], [8, 8, 8, 8, 8], gap=2)
    assert kept == [0, 2, 4]
    assert cp._spaced([], [], gap=2) == []


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match=r"backend must be one of .*got 'svg'"):
        cp.convergence_png([], backend="svg")
    with pytest.raises(ValueError, match=r"width_px must be an integer >= 200, got 10"):
        cp.convergence_png([], width_px=10)
    with pytest.raises(ValueError, match=r"log\[1\] must be a mapping .* got list"):
        cp.convergence_png([{}, [1, 2]])


def test_forced_backend_without_its_package_names_it(monkeypatch):
    monkeypatch.setattr(cp, "cv2", None)
    with pytest.raises(ImportError, match="opencv-contrib-python-headless"):
        cp.convergence_png([], backend="opencv")
    monkeypatch.setattr(cp, "_MATPLOTLIB", [None])
    with pytest.raises(ImportError, match="pip install matplotlib"):
        cp.convergence_png([], backend="matplotlib")
    # auto falls back to the NumPy drawing, which still encodes a PNG.
    assert png_header(cp.convergence_png(make_log(), width_px=W, height_px=H))[:2] == (W, H)


def test_numpy_font_covers_the_texts_it_draws():
    texts = [cp.title_line(make_log(3, rms=True)), "no convergence log", "no estimate", "no timed passes",
             "samples per pixel", "time (s)", "estimated, mm", "actual vs reference, mm", "1e-05",
             "RMS depth error (mm)", "valid", "no return", "low amplitude", "saturated", "out of range",
             "unwrapping failed", "4.12 m", "-263 mm", "1e+03 mm"]
    assert {c for text in texts for c in text.upper()} <= set(cp._GLYPHS)
    assert all(glyph.shape == (7, 5) for glyph in cp._GLYPHS.values()) and cp._UNKNOWN_GLYPH.shape == (7, 5)


@pytest.mark.parametrize("backend", ["numpy", "opencv"])
def test_the_raster_plots_have_a_turned_y_axis_title(backend):
    """matplotlib writes "RMS depth error (mm)" beside the y axis; the raster backends now do too: a column of
    ink, taller than wide, left of the tick labels."""
    backend_available(backend)
    image = decode_rgb(cp.convergence_png(make_log(), width_px=W, height_px=H, backend=backend))
    canvas = cp._NumpyCanvas(4, 4) if backend == "numpy" else cp._CvCanvas(4, 4)
    _, text_h = canvas.text_size("RMS depth error (mm)", 1)
    strip = (image[:, :6 + text_h + 2] < 128).any(axis=-1)
    rows, cols = np.nonzero(strip)
    assert rows.size > 20 and np.ptp(rows) > 4 * max(1, np.ptp(cols))
    flat = type(canvas)(200, 40)
    cp._turned_text(flat, 0, 20, "RMS", cp._INK)
    ink_rows, ink_cols = np.nonzero((flat.image < 128).any(axis=-1))
    assert np.ptp(ink_rows) > np.ptp(ink_cols)
