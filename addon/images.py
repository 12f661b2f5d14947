"""A :class:`tofcore.Frame` shown as Blender images, updated after every progressive pass.

=================  ====================================================================================
image              content (RGBA float, display-ready values, colour space Non-Color)
=================  ====================================================================================
``ToF Depth``      the sensor's depth, turbo colour map over [min, max] of the valid depth;
                   invalid pixels transparent black
``ToF IR``         IR intensity, grey, √(intensity / 99th percentile) (a display gamma of 2; brighter clips)
``ToF Amplitude``  modulation amplitude, grey, linear from 0 to the 99th percentile (brighter clips)
``ToF Error``      depth − ground-truth depth, blue (nearer) – white – red (farther) over ±limit,
                   limit = max(1 mm, 99th percentile of |error|); transparent where either is invalid
=================  ====================================================================================

After a render that wrote PNGs, ``ToF Convergence`` shows the final frame's
``convergence.png`` (estimated depth error against time, spp on top; drawn by
:mod:`tofcore.output.convergence_plot`), loaded from the written file
(:func:`load_convergence_image`) and reloaded from it by the next render.

Each image's custom property ``tof_device`` names the device that rendered it
(e.g. ``"CPU (NumPy 1.26.4)"``, ``"GPU 0: NVIDIA … (CuPy 13.6.0)"``).

The colour maps are NumPy only (:func:`frame_rgba`, testable without Blender);
:func:`update_images` writes them with ``image.pixels.foreach_set``, rows
flipped because Blender stores images bottom-up. The limits of every map are
returned so the UI can show them. Values are display-ready, so the images use
the Non-Color colour space (shown as stored, no view transform). The metric
values are in the written ``frame.exr``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

#: Frame quantity → Blender image name.
IMAGE_NAMES = {"depth": "ToF Depth", "intensity": "ToF IR", "amplitude": "ToF Amplitude", "error": "ToF Error"}
_ERROR_FLOOR_M = 1e-3
_PERCENTILE = 99.0

# Zucker's degree-5 polynomial fit of Google's Turbo colour map (2019), one row per channel, x in [0, 1].
_TURBO = np.array([
    [0.13572138, 4.61539260, -42.66032258, 132.13108234, -152.94239396, 59.28637943],
    [0.09140261, 2.19418839, 4.84296658, -14.18503333, 4.27729857, 2.82956604],
    [0.10667330, 12.64194608, -60.58204836, 110.36276771, -89.90310912, 27.34824973],
])
_BLUE = np.array([33.0, 102.0, 172.0]) / 255.0
_RED = np.array([178.0, 24.0, 43.0]) / 255.0


def _finite_range(values: np.ndarray) -> tuple[float, float]:
    finite = values[np.isfinite(values)]
    return (float(finite.min()), float(finite.max())) if finite.size else (math.nan, math.nan)


def _rgba(rgb: np.ndarray, defined: np.ndarray) -> np.ndarray:
    """(H, W, 4) float32: ``rgb`` where ``defined``, transparent black elsewhere."""
    out = np.zeros(defined.shape + (4,), dtype=np.float32)
    out[..., :3] = np.where(defined[..., None], rgb, 0.0)
    out[..., 3] = defined
    return out


def turbo(t: np.ndarray) -> np.ndarray:
    """(…, 3) RGB in [0, 1] of ``t`` (clipped to [0, 1]; NaN gives the colour of 0)."""
    x = np.clip(np.nan_to_num(np.asarray(t, dtype=np.float64), nan=0.0), 0.0, 1.0)
    rgb = np.stack([np.polynomial.polynomial.polyval(x, c) for c in _TURBO], axis=-1)
    return np.clip(rgb, 0.0, 1.0)


def diverging(s: np.ndarray) -> np.ndarray:
    """(…, 3) RGB of ``s`` in [−1, 1] (clipped): blue at −1, white at 0, red at +1, linear between."""
    s = np.clip(np.nan_to_num(np.asarray(s, dtype=np.float64), nan=0.0), -1.0, 1.0)[..., None]
    return 1.0 + np.abs(s) * (np.where(s < 0, _BLUE, _RED) - 1.0)


def depth_rgba(depth: np.ndarray) -> tuple[np.ndarray, dict]:
    """Turbo over [min, max] of the finite depth (metres); NaN transparent. Returns (rgba, limits)."""
    depth = np.asarray(depth, dtype=np.float64)
    lo, hi = _finite_range(depth)
    defined = np.isfinite(depth)
    t = (depth - lo) / (hi - lo) if hi > lo else np.zeros_like(depth)
    return _rgba(turbo(t), defined), {"min_m": lo, "max_m": hi}


def grey_rgba(values: np.ndarray, *, gamma: float = 1.0) -> tuple[np.ndarray, dict]:
    """Grey image (v / 99th percentile)^(1/gamma), clipped to [0, 1]; negatives → 0, NaN transparent.

    Returns (rgba, limits): ``max`` is the value shown white, in the unit of ``values``.
    """
    values = np.maximum(np.asarray(values, dtype=np.float64), 0.0)
    defined = np.isfinite(values)
    top = float(np.percentile(values[defined], _PERCENTILE)) if defined.any() else 0.0
    t = np.clip(np.nan_to_num(values / (top if top > 0 else 1.0), nan=0.0), 0.0, 1.0)
    grey = t ** (1.0 / gamma)
    scale = "linear" if gamma == 1.0 else f"(v / max)^(1/{gamma:g})"
    return _rgba(np.repeat(grey[..., None], 3, axis=-1), defined), {"scale": scale, "min": 0.0, "max": top}


def error_rgba(depth: np.ndarray, gt_depth: np.ndarray) -> tuple[np.ndarray, dict]:
    """depth − gt_depth (metres) blue–white–red over ±limit; transparent where either is NaN."""
    error = np.asarray(depth, dtype=np.float64) - np.asarray(gt_depth, dtype=np.float64)
    defined = np.isfinite(error)
    magnitude = np.abs(error[defined])
    limit = max(_ERROR_FLOOR_M, float(np.percentile(magnitude, _PERCENTILE)) if magnitude.size else 0.0)
    rms = float(np.sqrt(np.mean(np.square(error[defined])))) if magnitude.size else math.nan
    return _rgba(diverging(error / limit), defined), {"limit_m": limit, "rms_m": rms}


def frame_rgba(frame) -> dict[str, tuple[np.ndarray, dict]]:
    """``{quantity: ((H, W, 4) float32 RGBA, row 0 at the top, colour-map limits)}`` for :data:`IMAGE_NAMES`."""
    depth = np.where(frame.valid, frame.depth, np.nan)
    return {
        "depth": depth_rgba(depth),
        "intensity": grey_rgba(frame.intensity, gamma=2.0),
        "amplitude": grey_rgba(frame.amplitude),
        "error": error_rgba(depth, frame.gt_depth),
    }


# --------------------------------------------------------------------------- Blender side

def _image(name: str, width: int, height: int):
    """The float RGBA image ``name`` at ``width`` × ``height``, created or resized as needed."""
    import bpy
    image = bpy.data.images.get(name)
    if image is not None and (image.source != 'GENERATED' or not image.is_float):
        bpy.data.images.remove(image)  # a user image of that name: make room for ours
        image = None
    if image is None:
        image = bpy.data.images.new(name, width, height, alpha=True, float_buffer=True)
        image.colorspace_settings.name = 'Non-Color'
        image.alpha_mode = 'STRAIGHT'
    elif tuple(image.size) != (width, height):
        image.scale(width, height)
    return image


def set_pixels(image, rgba: np.ndarray) -> None:
    """Write (H, W, 4) RGBA, row 0 at the top, into ``image`` (Blender stores rows bottom-up)."""
    flat = np.ascontiguousarray(rgba[::-1], dtype=np.float32).reshape(-1)
    image.pixels.foreach_set(flat)
    image.update()


def read_pixels(image) -> np.ndarray:
    """(H, W, 4) float32 RGBA of ``image``, row 0 at the top."""
    width, height = image.size
    flat = np.empty(width * height * 4, dtype=np.float32)
    image.pixels.foreach_get(flat)
    return flat.reshape(height, width, 4)[::-1]


#: Custom property of the images: the device that rendered them (``frame.stats["device"]["description"]``).
DEVICE_KEY = "tof_device"


def update_images(frame) -> dict[str, dict]:
    """Show ``frame`` in the four images of :data:`IMAGE_NAMES`, each with the device that rendered it
    (custom property :data:`DEVICE_KEY`); returns the colour-map limits by image name."""
    limits = {}
    device = (frame.stats.get("device") or {}).get("description", "")
    for quantity, (rgba, quantity_limits) in frame_rgba(frame).items():
        name = IMAGE_NAMES[quantity]
        image = _image(name, frame.width, frame.height)
        set_pixels(image, rgba)
        image[DEVICE_KEY] = device
        limits[name] = quantity_limits
    return limits


#: The image of the final frame's written ``convergence.png``.
CONVERGENCE_IMAGE = "ToF Convergence"


def load_convergence_image(path, device: str = ""):
    """Show the written ``convergence.png`` at ``path`` as the image :data:`CONVERGENCE_IMAGE` (loaded
    from the file, or reloaded when it exists), with the device that rendered it (:data:`DEVICE_KEY`)."""
    import bpy
    filepath = str(Path(path).resolve())
    image = bpy.data.images.get(CONVERGENCE_IMAGE)
    if image is not None and image.source != 'FILE':
        bpy.data.images.remove(image)  # a generated image of that name: make room for ours
        image = None
    if image is None:
        image = bpy.data.images.load(filepath, check_existing=False)
        image.name = CONVERGENCE_IMAGE
    else:
        image.filepath = filepath
        image.reload()
    image[DEVICE_KEY] = device
    return image
