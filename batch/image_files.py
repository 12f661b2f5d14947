"""Grey images from files, for randomized textures and environment maps: ``.npy``, ``.exr``, ``.png``/``.jpg``.

=========  ======================================================================================
suffix     read as
=========  ======================================================================================
``.npy``   a (H, W) array as is, or (H, W, C≥3) turned to luminance
``.exr``   :func:`tofcore.read_exr`: channel ``Y``, else the luminance of ``R``, ``G``, ``B``,
           else the first channel
``.png``,  OpenCV (``pip install opencv-python-headless``), 8 or 16 bit, divided by 255 or 65535;
``.jpg``   colour turned to luminance (sRGB values taken as they are: a texture is a pattern here)
=========  ======================================================================================

Luminance :math:`Y = 0.2126 R + 0.7152 G + 0.0722 B` (as :mod:`tofcore.scene.mesh_files`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tofcore.errors import ConfigError

SUFFIXES = (".npy", ".exr", ".png", ".jpg", ".jpeg")
_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def read_grey(path: Path) -> np.ndarray:
    """(H, W) float32 image of ``path``; ConfigError naming the file when it cannot be read."""
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            data = np.load(path, allow_pickle=False)
        elif suffix == ".exr":
            from tofcore.output.writers import read_exr

            channels = read_exr(path)
            if "Y" in channels:
                data = channels["Y"]
            elif all(c in channels for c in "RGB"):
                data = np.stack([channels[c] for c in "RGB"], axis=-1)
            else:
                data = next(iter(channels.values()))
        else:
            try:
                import cv2
            except ImportError:
                raise ConfigError(f"{path}: reading {suffix} images needs OpenCV: pip install "
                                  f"opencv-python-headless (or give .npy / .exr files)") from None
            raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if raw is None:
                raise ConfigError(f"{path}: not a readable image")
            scale = 65535.0 if raw.dtype == np.uint16 else 255.0
            data = raw.astype(np.float64) / scale
            if data.ndim == 3:
                data = data[..., 2::-1] if data.shape[2] >= 3 else data[..., 0]  # OpenCV's BGR(A) → RGB
    except (OSError, ValueError) as err:
        raise ConfigError(f"{path}: cannot be read as an image ({err})") from None
    data = np.asarray(data, dtype=np.float64)
    if data.ndim == 3 and data.shape[2] >= 3:
        data = data[..., :3] @ _LUMINANCE
    if data.ndim != 2 or not data.size or not np.isfinite(data).all():
        raise ConfigError(f"{path}: must hold a finite (H, W) or (H, W, 3) image, got shape {data.shape}")
    return data.astype(np.float32)
