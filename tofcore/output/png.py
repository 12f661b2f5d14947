"""8-bit previews as PNG: the colour maps (turbo, diverging, grey) and the PNG encoder.

OpenCV encodes when importable and this is not Blender's process (:mod:`tofcore.native`), else NumPy +
zlib do; both give the same pixels. Used by the frame writers, the convergence plot and ``batch compare``.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from ..native import optional_module

cv2 = optional_module("cv2")


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of (H, W) uint16 grey or (H, W, 3) uint8 RGB, by OpenCV if importable."""
    if cv2 is None:
        return encode_png_numpy(image)
    ok, buffer = cv2.imencode(".png", image[..., ::-1] if image.ndim == 3 else image)
    if not ok:
        raise RuntimeError(f"encode_png: OpenCV could not encode a {image.dtype} {image.shape} PNG")
    return buffer.tobytes()


def encode_png_numpy(image: np.ndarray) -> bytes:
    """PNG bytes by NumPy + zlib: IHDR (grey 16-bit or RGB 8-bit), one IDAT (filter 0 rows), IEND."""
    height, width = image.shape[:2]
    colour_type = 0 if image.ndim == 2 else 2
    rows = image.astype(image.dtype.newbyteorder(">")).reshape(height, -1).view(np.uint8)
    scanlines = np.hstack([np.zeros((height, 1), np.uint8), rows]).tobytes()
    ihdr = struct.pack(">IIBBBBB", width, height, 8 * image.dtype.itemsize, colour_type, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", zlib.compress(scanlines, 6))
            + _png_chunk(b"IEND", b""))


def _png_chunk(tag: bytes, data: bytes) -> bytes:
    """One PNG chunk: length, tag, data, CRC-32 of tag + data."""
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))


def _turbo_lut() -> np.ndarray:
    """(256, 3) uint8 turbo-like map: Zucker's degree-5 polynomial fit of Google's Turbo (2019)."""
    coefficients = np.array([
        [0.13572138, 4.61539260, -42.66032258, 132.13108234, -152.94239396, 59.28637943],
        [0.09140261, 2.19418839, 4.84296658, -14.18503333, 4.27729857, 2.82956604],
        [0.10667330, 12.64194608, -60.58204836, 110.36276771, -89.90310912, 27.34824973],
    ])
    x = np.linspace(0.0, 1.0, 256)
    rgb = np.stack([np.polynomial.polynomial.polyval(x, c) for c in coefficients], axis=-1)
    return np.rint(np.clip(rgb, 0.0, 1.0) * 255).astype(np.uint8)


def _diverging_lut() -> np.ndarray:
    """(256, 3) uint8 map from blue (entry 0) through white (middle) to red (entry 255), linear in RGB."""
    s = np.linspace(-1.0, 1.0, 256)[:, None]
    white, blue, red = np.array([255.0] * 3), np.array([33.0, 102.0, 172.0]), np.array([178.0, 24.0, 43.0])
    rgb = white + np.abs(s) * (np.where(s < 0, blue, red) - white)
    return np.rint(rgb).astype(np.uint8)


TURBO = _turbo_lut()
DIVERGING = _diverging_lut()
GREY = np.repeat(np.arange(256, dtype=np.uint8)[:, None], 3, axis=1)


def apply_lut(t: np.ndarray, lut: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 colours of ``t`` in [0, 1] (clipped); non-finite → black."""
    finite = np.isfinite(t)
    index = np.rint(np.clip(np.where(finite, t, 0.0), 0.0, 1.0) * (len(lut) - 1)).astype(np.intp)
    return np.where(finite[..., None], lut[index], 0).astype(np.uint8)
