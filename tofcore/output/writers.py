"""Writers: one simulated :class:`~tofcore.output.frame.Frame` to files.

``write_frame(frame, out_dir)`` writes, with ``prefix`` before every name:

===================  ============  =================================================================
file                 kind          content
===================  ============  =================================================================
``frame.exr``        exr           one part, float32 channels, ZIP (lossless): ``depth``,
                                   ``distance``, ``amplitude``, ``intensity``, ``offset``,
                                   ``confidence``, ``valid`` (0/1), ``reason`` (code),
                                   ``gt_distance``, ``gt_depth``, ``direct_distance``, ``object_id``
                                   (exact below 2²⁴), ``raw.<label>`` per raw image,
                                   ``distance_k1`` … ``distance_kK``; header attributes
                                   ``tofcore`` (the JSON document below, without files and
                                   previews) and ``world_from_sensor`` (4×4 float64)
``depth_mm.png``     depth_mm      16-bit grey: depth in mm rounded to nearest (ties to even),
                                   0 where invalid, clipped to 65535 mm (65.535 m)
``depth.png``        depth         8-bit RGB: turbo-like colour map over [min, max] of the valid
                                   depth, invalid black
``intensity.png``    intensity     8-bit RGB grey: log(1 + intensity) over its finite range
``error.png``        error         8-bit RGB: depth − gt_depth in mm, blue (−) – white – red (+)
                                   over ±limit_mm, limit = max(1 mm, 99th percentile of |error|),
                                   black where invalid or without ground truth
``reason.png``       reason        8-bit RGB: one colour per :class:`Reason` (legend in the JSON)
``convergence.png``  convergence   8-bit RGB 640×400 plot of ``stats["convergence"]``: estimated RMS
                                   depth error (mm, log) against time (s, log), spp on the top axis,
                                   the actual error when the log has ``rms_error_m``; title with the
                                   final spp, time and error (:mod:`tofcore.output.convergence_plot`)
``points.ply``       ply           binary little-endian valid points, sensor frame, metres:
                                   float x y z, float amplitude (e⁻), uchar intensity (grey level
                                   of ``intensity.png``)
``depth.exr``        exr           one channel ``Y``: depth in m (NaN where invalid), the layout
                                   OpenCV (``cv2.imread(…, cv2.IMREAD_UNCHANGED)``) and EXR viewers
                                   open as a grey image; header attribute ``tofcore`` as above
``ir.png``           png           16-bit grey IR image like the Kinect's IR stream: amplitude,
                                   linear, exposed for display (the 99.5th percentile of the valid
                                   pixels at 80 % of 65535), rounded, clipped; electrons per count
                                   (``e_per_count``) are in ``frame.json``
``transient.npy``    transient     (H, W, B) float32 transient histogram (``frame.transient``); bin
                                   width and count in ``frame.json`` (only when the frame has one)
``camera_opencv.yml``  json        OpenCV ``FileStorage`` YAML: ``camera_matrix``,
                                   ``distortion_coefficients`` (k1, k2, p1, p2, k3), image size
``camera_info.yaml``   json        ROS ``sensor_msgs/CameraInfo`` YAML (``plumb_bob``)
``camera.json``      json          BOP ``camera.json``: fx, fy, cx, cy, width, height, depth_scale 1
                                   (``depth_mm.png`` is in mm); BOP has no distortion field, the
                                   coefficients are in the two YAML files
``frame.json``       json          frame metadata (with ``objects``: the ``object_id`` → object
                                   name and materials table), stats, units, preview limits, and
                                   every file above with its size and SHA-256; written last
===================  ============  =================================================================

``depth.png`` and ``error.png`` carry a colour bar with their limits on the right, ``reason.png``
its legend below the image (the image itself is the top-left ``height`` × ``width`` pixels).
Options: ``exr_half`` writes the EXR channels as 16-bit half floats (about 4 mm steps at 4 m:
for previews and compact datasets), ``exr_channels`` writes only the named channels of
``frame.exr``.

Every file is written atomically (temp file ``.name.tmp-XXXXXXXX`` in the same
directory, flush, fsync, ``os.replace``): a failure leaves the previous file or
none, never a partial one. ``frame.json`` is the frame's done record: an existing
one is removed before anything else is written, since it would describe files
about to be replaced. NaN and ±inf become ``null`` in JSON.

PNGs are encoded by :mod:`.png` (OpenCV when importable, never inside Blender: :mod:`tofcore.native`);
the EXR by tofcore's own codec (:mod:`.exr`, NumPy + zlib), so no native OpenEXR library is ever loaded.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
import math
import os
import secrets
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path, PurePath

import numpy as np

from ..errors import ExrError
from . import exr
from .convergence_plot import convergence_png
from .frame import Frame, Reason
from .legend import with_colour_bar, with_legend
from .png import DIVERGING, GREY, TURBO, apply_lut, encode_png

FORMATS = ("exr", "png", "ply", "json", "transient")

# Images written as EXR channels of the same name (all (H, W)).
_EXR_IMAGES = ("depth", "distance", "amplitude", "intensity", "offset", "confidence", "valid", "reason",
               "gt_distance", "gt_depth", "direct_distance", "object_id")

UNITS = {
    "depth": "m", "distance": "m", "render_error": "m", "gt_distance": "m", "gt_depth": "m", "direct_distance": "m",
    "distance_k<k>": "m", "amplitude": "e-", "offset": "e-", "intensity": "e-", "raw.<label>": "e-",
    "samples": "samples per pixel", "unwrap_flip": "0/1", "confidence": "1", "valid": "0/1", "reason": "Reason code", "object_id": "object index, -1 none",
    "depth_mm.png": "mm", "points.ply": "m, sensor frame (x right, y down, z forward)",
}

# One colour (8-bit RGB) per invalid-pixel reason.
_REASON_RGB = {
    Reason.VALID: (200, 200, 200), Reason.NO_RETURN: (0, 0, 0), Reason.LOW_AMPLITUDE: (40, 90, 220),
    Reason.SATURATED: (230, 30, 30), Reason.OUT_OF_RANGE: (220, 0, 220), Reason.UNWRAPPING_FAILED: (255, 160, 0),
    Reason.EDGE_FILTERED: (0, 170, 160),
}

_DEPTH_MM_MAX = 65535
_ERROR_FLOOR_MM = 1.0
_ERROR_PERCENTILE = 99.0


# --------------------------------------------------------------------------- public API

def write_frame(frame: Frame, out_dir: str | os.PathLike, formats: Iterable[str] | str = FORMATS, *,
                prefix: str = "", exr_half: bool = False,
                exr_channels: Iterable[str] | None = None) -> dict[str, Path]:
    """Write ``frame`` to ``out_dir`` (created if needed); return the files by kind.

    Parameters
    ----------
    frame : the frame to write.
    out_dir : output directory.
    formats : any of ``"exr"``, ``"png"``, ``"ply"``, ``"json"`` (a single name is accepted).
    prefix : put before every file name, e.g. ``"000042_"``; no path separators.
    exr_half : EXR channels as 16-bit half floats instead of 32-bit floats.
    exr_channels : only these channels in ``frame.exr`` (names of :func:`exr_channel_names`); None: all.

    Returns
    -------
    ``{kind: path}`` with kinds ``exr``, ``depth_exr``, ``depth_mm``, ``ir``, ``depth``, ``intensity``,
    ``error``, ``reason``, ``convergence``, ``ply``, ``transient``, ``opencv_yaml``, ``ros_yaml``,
    ``bop_camera``, ``json`` for the formats asked (see the module docstring).

    Raises
    ------
    ValueError : unknown format, bad prefix or a preview frame, before anything is written.
    TypeError : ``metadata`` or ``stats`` holds something JSON cannot hold, before anything is written.
    """
    formats = _check_formats(formats)
    if Path(prefix).name != prefix:
        raise ValueError(f"write_frame: prefix must be a plain file-name prefix, got {prefix!r}")
    if frame.distance_per_k is None or frame.direct_distance is None:
        raise ValueError("write_frame: this is a preview frame without direct_distance and distance_per_k "
                         "(render_progressive(preview_frames=True) yields them before the final pass); write the "
                         "final frame")
    channels = _exr_channels(frame) if "exr" in formats else {}
    if exr_channels is not None:
        exr_channels = tuple(exr_channels)
        unknown = [name for name in exr_channels if name not in channels]
        if unknown or not exr_channels:
            raise ValueError(f"write_frame: exr_channels must be a non-empty subset of {list(channels)}, "
                             f"got unknown {unknown!r}")
        channels = {name: channels[name] for name in exr_channels}
    document = _frame_document(frame)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / f"{prefix}frame.json"
    json_path.unlink(missing_ok=True)
    written: dict[str, Path] = {}
    previews: dict[str, dict] = {}
    if "exr" in formats:
        pose = {"world_from_sensor": np.asarray(frame.world_from_sensor, dtype=np.float64)}
        written["exr"] = _atomic_write(out / f"{prefix}frame.exr",
                                       lambda tmp: write_exr(tmp, channels, {"tofcore": document, **pose}, exr_half))
        depth = {"Y": np.ascontiguousarray(frame.depth, dtype=np.float32)}
        written["depth_exr"] = _atomic_write(out / f"{prefix}depth.exr",
                                             lambda tmp: write_exr(tmp, depth, {"tofcore": document, **pose}, exr_half))
    if "png" in formats:
        _write_pngs(frame, out, prefix, written, previews)
    if "ply" in formats:
        written["ply"] = _atomic_write(out / f"{prefix}points.ply", lambda tmp: _write_ply(tmp, frame))
    if "transient" in formats and frame.transient is not None:
        written["transient"] = _atomic_write(out / f"{prefix}transient.npy",
                                             lambda tmp: _write_npy(tmp, frame.transient))
        previews["transient"] = {"file": written["transient"].name, "shape": list(frame.transient.shape),
                                 "bin_width_m": frame.transient_bin_m, "bins": int(frame.transient.shape[-1]),
                                 "bin_centre_m": "(b + 0.5) * bin_width_m, b = 0 .. bins - 1",
                                 "quantity": "optical path length LED -> scene -> lens",
                                 "unit": "W m^-2 sr^-1 (mean radiance at the lens per bin)"}
    if "json" in formats:
        intrinsics = frame.metadata.get("intrinsics") or {}
        if all(key in intrinsics for key in ("width", "height", "fx", "fy", "cx", "cy")):
            for kind, name, text in (("opencv_yaml", "camera_opencv.yml", opencv_yaml(intrinsics)),
                                     ("ros_yaml", "camera_info.yaml", ros_camera_info_yaml(intrinsics)),
                                     ("bop_camera", "camera.json", bop_camera_json(intrinsics))):
                data = text.encode("utf-8")
                written[kind] = _atomic_write(out / f"{prefix}{name}", lambda tmp: tmp.write_bytes(data))
        text = _frame_json(document, written, previews)
        written["json"] = _atomic_write(json_path, lambda tmp: tmp.write_bytes(text))
    return written



def _write_pngs(frame: Frame, out: Path, prefix: str, written: dict, previews: dict) -> None:
    """The PNG files: depth in mm, the 16-bit IR image, the 8-bit previews (with colour bars and the reason
    legend) and the convergence plot; adds them to ``written`` and their value ranges to ``previews``."""
    png = encode_png(_depth_mm(frame))
    written["depth_mm"] = _atomic_write(out / f"{prefix}depth_mm.png", lambda tmp: tmp.write_bytes(png))
    ir, previews["ir"] = _ir16(frame)
    png = encode_png(ir)
    written["ir"] = _atomic_write(out / f"{prefix}ir.png", lambda tmp: tmp.write_bytes(png))
    previews["ir"]["file"] = written["ir"].name
    for kind, (image, limits) in _previews(frame).items():
        if kind in ("depth", "error"):
            image = with_colour_bar(image, limits["lut"], limits["low"], limits["high"], limits["label"])
        elif kind == "reason":
            image = with_legend(image, [(r.name.lower().replace("_", " "), _REASON_RGB[r]) for r in Reason])
        limits = {k: v for k, v in limits.items() if k not in ("lut", "low", "high", "label")}
        png = encode_png(image)
        written[kind] = _atomic_write(out / f"{prefix}{kind}.png", lambda tmp: tmp.write_bytes(png))
        previews[kind] = {"file": written[kind].name, **limits}
    png = convergence_png(frame.stats.get("convergence") or [])
    written["convergence"] = _atomic_write(out / f"{prefix}convergence.png", lambda tmp: tmp.write_bytes(png))


def read_exr(path: str | os.PathLike, names: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    """Channels of a ``frame.exr`` (or ``depth.exr``) as ``{name: (H, W) float32 array}`` (half floats widened);
    ``names`` picks some. A damaged file, or a channel of integers (UINT: tofcore writes FLOAT or HALF, and an
    integer depth read as metres would be silently wrong), is a one-line :class:`~tofcore.errors.ExrError`
    (a ValueError) naming the file (:func:`tofcore.output.exr.read`)."""
    channels = exr.read(path, names)
    integers = [name for name, image in channels.items() if image.dtype.kind != "f"]
    if integers:
        raise ExrError(f"{os.fsdecode(os.fspath(path))}: channels {integers} are UINT (integers); a tofcore frame's "
                       f"channels are FLOAT or HALF (metres, electrons, 0/1 masks)")
    return {name: np.asarray(image, dtype=np.float32) for name, image in channels.items()}


def exr_channel_names(raw_labels: Iterable[str], bounces: int) -> list[str]:
    """The channels ``frame.exr`` holds for a frame with these raw images and ``bounces`` distance_k images
    (what ``exr_channels`` may choose from); ``render_error``, ``samples`` and ``unwrap_flip`` come with every
    render."""
    return [*_EXR_IMAGES, *(f"raw.{label}" for label in raw_labels),
            *(f"distance_k{k}" for k in range(1, bounces + 1)), "render_error", "samples", "unwrap_flip"]


def opencv_yaml(intrinsics: Mapping) -> str:
    """OpenCV ``FileStorage`` YAML of the intrinsics (``cv2.FileStorage(path, cv2.FILE_STORAGE_READ)``):
    ``image_width``, ``image_height``, ``camera_matrix`` (3×3), ``distortion_coefficients`` (1×5: k1, k2,
    p1, p2, k3, OpenCV's order); pixel centres at integer coordinates, as in OpenCV."""
    k = _camera_matrix(intrinsics)
    dist = [float(intrinsics.get(name, 0.0)) for name in ("k1", "k2", "p1", "p2", "k3")]

    def matrix(name: str, rows: int, cols: int, data: list[float]) -> str:
        return (f"{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n"
                f"   data: [ {', '.join(repr(v) for v in data)} ]\n")

    size = f"image_width: {int(intrinsics['width'])}\nimage_height: {int(intrinsics['height'])}\n"
    return ("%YAML:1.0\n---\n" + size + matrix("camera_matrix", 3, 3, k)
            + matrix("distortion_coefficients", 1, 5, dist))


def ros_camera_info_yaml(intrinsics: Mapping, camera_name: str = "tof") -> str:
    """ROS ``sensor_msgs/CameraInfo`` YAML (camera_calibration_parsers' layout): ``plumb_bob`` distortion
    [k1, k2, p1, p2, k3], identity rectification, projection ``[K | 0]``."""
    k = _camera_matrix(intrinsics)
    dist = [float(intrinsics.get(name, 0.0)) for name in ("k1", "k2", "p1", "p2", "k3")]
    p = k[:3] + [0.0] + k[3:6] + [0.0] + k[6:] + [0.0]

    def matrix(name: str, rows: int, cols: int, data: list[float]) -> str:
        return f"{name}:\n  rows: {rows}\n  cols: {cols}\n  data: [{', '.join(repr(v) for v in data)}]\n"

    return (f"image_width: {int(intrinsics['width'])}\nimage_height: {int(intrinsics['height'])}\n"
            f"camera_name: {camera_name}\n" + matrix("camera_matrix", 3, 3, k) + "distortion_model: plumb_bob\n"
            + matrix("distortion_coefficients", 1, 5, dist)
            + matrix("rectification_matrix", 3, 3, [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])
            + matrix("projection_matrix", 3, 4, p))


def bop_camera_json(intrinsics: Mapping) -> str:
    """BOP toolkit ``camera.json``: ``cx, cy, fx, fy, width, height`` and ``depth_scale`` 1.0 (the 16-bit
    ``depth_mm.png`` times depth_scale is millimetres, as BOP reads depth images)."""
    data = {"cx": float(intrinsics["cx"]), "cy": float(intrinsics["cy"]), "depth_scale": 1.0,
            "fx": float(intrinsics["fx"]), "fy": float(intrinsics["fy"]),
            "height": int(intrinsics["height"]), "width": int(intrinsics["width"])}
    return json.dumps(data, indent=2) + "\n"


def _camera_matrix(intrinsics: Mapping) -> list[float]:
    """Row-major 3×3 K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] as 9 floats."""
    fx, fy, cx, cy = (float(intrinsics[name]) for name in ("fx", "fy", "cx", "cy"))
    return [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]


# --------------------------------------------------------------------------- files

def _check_formats(formats: Iterable[str] | str) -> tuple[str, ...]:
    """``formats`` as a tuple, or ValueError naming the unknown ones and the valid ones."""
    formats = (formats,) if isinstance(formats, str) else tuple(formats)
    unknown = [f for f in formats if f not in FORMATS]
    if unknown:
        raise ValueError(f"write_frame: formats must be among {FORMATS}, got unknown {unknown!r}")
    return formats


def _atomic_write(path: Path, write: Callable[[Path], object]) -> Path:
    """Create ``.{name}.tmp-XXXXXXXX`` beside ``path``, ``write(tmp)`` it, fsync, rename it to ``path``.

    If ``write`` raises, the temp file is removed and ``path`` is left as it was.
    """
    tmp = path.with_name(f".{path.name}.tmp-{secrets.token_hex(4)}")
    try:
        open(tmp, "xb").close()
        write(tmp)
        with open(tmp, "ab") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _file_record(kind: str, path: Path) -> dict:
    """``{kind, name, bytes, sha256}`` of a written file."""
    with open(path, "rb") as fh:
        digest = hashlib.file_digest(fh, "sha256").hexdigest()
    return {"kind": kind, "name": path.name, "bytes": path.stat().st_size, "sha256": digest}


# --------------------------------------------------------------------------- EXR

def _exr_channels(frame: Frame) -> dict[str, np.ndarray]:
    """Every EXR channel as a float32 (H, W) array."""
    if len(frame.raw_labels) != len(frame.raw) or len(set(frame.raw_labels)) != len(frame.raw_labels):
        raise ValueError(f"write_frame: raw_labels must be {len(frame.raw)} distinct names (one per raw "
                         f"image), got {frame.raw_labels!r}")
    images = {name: getattr(frame, name) for name in _EXR_IMAGES}
    images.update({f"raw.{label}": raw for label, raw in zip(frame.raw_labels, frame.raw)})
    images.update({f"distance_k{k}": d for k, d in enumerate(frame.distance_per_k, start=1)})
    images.update({name: getattr(frame, name) for name in ("render_error", "samples", "unwrap_flip")
                   if getattr(frame, name) is not None})
    for name, image in images.items():
        if np.shape(image) != (frame.height, frame.width):
            raise ValueError(f"write_frame: {name} must have shape {(frame.height, frame.width)}, "
                             f"got {np.shape(image)}")
    return {name: np.ascontiguousarray(image, dtype=np.float32) for name, image in images.items()}


def write_exr(path: str | os.PathLike, channels: Mapping[str, np.ndarray], attributes: Mapping[str, object],
              half: bool = False) -> None:
    """Write a single-part scanline EXR (ZIP, lossless) of ``channels`` ({name: (H, W) array}) to ``path``,
    by tofcore's own codec (:mod:`.exr`).

    ``attributes``: extra header attributes; a dict becomes a JSON string, an array stays an array.
    ``half``: 16-bit half-float channels instead of 32-bit floats.
    """
    header = {name: json.dumps(value, allow_nan=False) if isinstance(value, Mapping) else value
              for name, value in attributes.items()}
    dtype = np.float16 if half else np.float32
    data = exr.encode({name: np.asarray(image, dtype=dtype) for name, image in channels.items()},
                      attributes=header, compression="zip")
    with open(path, "wb") as fh:
        fh.write(data)


# --------------------------------------------------------------------------- PNG

_IR_MAX = 65535
IR_PERCENTILE = 99.5
IR_LEVEL = 0.8
"""ir.png's exposure: the IR_PERCENTILE-th percentile of the valid pixels' amplitude at IR_LEVEL × 65535."""


def _ir16(frame: Frame) -> tuple[np.ndarray, dict]:
    """(H, W) uint16 amplitude, linear, exposed for display; and its scale.

    In counts of the full well (full_well_e / 65535 e⁻ per count) a frame's amplitude filled ~1 % of the
    16 bits (a Kinect room: 922 of 65,535) and the image opened black. So the scale is the frame's own:

    .. math:: e_\\mathrm{count} = P_{99.5}(A_\\mathrm{valid}) / (0.8 \\cdot 65535),

    counts = round(A / e_count) clipped to 0..65535 (the brightest 0.5 % may clip). ``e_per_count`` in
    frame.json gives electrons back; a frame without a valid pixel with amplitude uses the full well's
    scale (1 e⁻ per count without one). The amplitude itself, unscaled, is in the EXR files.
    """
    amplitude = np.nan_to_num(np.asarray(frame.amplitude, dtype=np.float64), nan=0.0)
    lit = amplitude[np.asarray(frame.valid, dtype=bool) & (amplitude > 0)]
    if lit.size:
        e_per_count = float(np.percentile(lit, IR_PERCENTILE)) / (IR_LEVEL * _IR_MAX)
    else:
        full_well = ((frame.metadata.get("sensor") or {}).get("readout") or {}).get("full_well_e")
        e_per_count = float(full_well) / _IR_MAX if full_well else 1.0
    counts = np.clip(np.rint(amplitude / e_per_count), 0, _IR_MAX).astype(np.uint16)
    return counts, {"quantity": "amplitude", "bits": 16, "e_per_count": e_per_count,
                    "rule": f"counts = round(amplitude_e / e_per_count), clipped to 0..65535; e_per_count puts the "
                            f"{IR_PERCENTILE:g}th percentile of the valid pixels at {IR_LEVEL:g} x 65535"}


def _write_npy(path: Path, array: np.ndarray) -> None:
    """``numpy.save`` of ``array`` as float32 to ``path`` (no pickling)."""
    with open(path, "wb") as fh:
        np.save(fh, np.ascontiguousarray(array, dtype=np.float32), allow_pickle=False)


def _depth_mm(frame: Frame) -> np.ndarray:
    """(H, W) uint16 depth in millimetres, rounded, 0 where invalid, clipped to 65535 mm."""
    depth_mm = np.asarray(frame.depth, dtype=np.float64) * 1000.0
    keep = frame.valid & np.isfinite(depth_mm)
    return np.where(keep, np.clip(np.rint(depth_mm), 0, _DEPTH_MM_MAX), 0).astype(np.uint16)


def _finite_range(values: np.ndarray) -> tuple[float, float]:
    """(min, max) of the finite values, (nan, nan) if there are none."""
    finite = values[np.isfinite(values)]
    return (float(finite.min()), float(finite.max())) if finite.size else (math.nan, math.nan)


def _normalise(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(values − lo) / (hi − lo), NaN stays NaN; a constant image maps to 0."""
    return (values - lo) / (hi - lo if hi > lo else 1.0)


def _intensity_grey(frame: Frame) -> tuple[np.ndarray, dict]:
    """(H, W) uint8 grey of log(1 + intensity) over its finite range (negative clipped to 0), limits."""
    intensity = np.maximum(np.asarray(frame.intensity, dtype=np.float64), 0.0)
    lo, hi = _finite_range(intensity)
    t = _normalise(np.log1p(intensity), math.log1p(lo), math.log1p(hi))
    grey = apply_lut(t, GREY)[..., 0]
    return grey, {"colormap": "grey", "scale": "log(1 + intensity)", "min_e": lo, "max_e": hi}


def _previews(frame: Frame) -> dict[str, tuple[np.ndarray, dict]]:
    """The 8-bit RGB previews ``{kind: ((H, W, 3) uint8, colour-map limits)}``."""
    depth = np.where(frame.valid, frame.depth, np.nan).astype(np.float64)
    lo, hi = _finite_range(depth)
    grey, intensity_limits = _intensity_grey(frame)
    return {
        "depth": (apply_lut(_normalise(depth, lo, hi), TURBO),
                  {"colormap": "turbo (polynomial approximation)", "min_m": lo, "max_m": hi, "invalid": "black",
                   "colour_bar": "right of the image", "lut": TURBO, "low": lo, "high": hi, "label": "m"}),
        "intensity": (np.repeat(grey[..., None], 3, axis=2), intensity_limits),
        "error": _error_preview(frame, depth),
        "reason": _reason_preview(frame),
    }


def _error_preview(frame: Frame, depth: np.ndarray) -> tuple[np.ndarray, dict]:
    """Blue–white–red image of (depth − gt_depth) in mm over ±limit_mm, and its limits."""
    error_mm = (depth - np.asarray(frame.gt_depth, dtype=np.float64)) * 1000.0
    finite = np.abs(error_mm[np.isfinite(error_mm)])
    limit_mm = max(_ERROR_FLOOR_MM, float(np.percentile(finite, _ERROR_PERCENTILE)) if finite.size else 0.0)
    return apply_lut((error_mm / limit_mm + 1.0) / 2.0, DIVERGING), {
        "colormap": "blue-white-red", "quantity": "depth - gt_depth", "unit": "mm", "limit_mm": limit_mm,
        "rule": f"max({_ERROR_FLOOR_MM} mm, {_ERROR_PERCENTILE}th percentile of |error|), beyond saturates",
        "invalid": "black", "colour_bar": "right of the image", "lut": DIVERGING, "low": -limit_mm,
        "high": limit_mm, "label": "mm"}


def _reason_preview(frame: Frame) -> tuple[np.ndarray, dict]:
    """One colour per :class:`Reason` code, and the legend ``{name: [r, g, b]}``."""
    palette = np.array([_REASON_RGB[reason] for reason in Reason], dtype=np.uint8)
    codes = np.asarray(frame.reason).astype(np.int64)
    unknown = np.setdiff1d(codes, np.arange(len(palette)))
    if unknown.size:
        raise ValueError(f"write_frame: reason must hold Reason codes 0..{len(palette) - 1}, "
                         f"got {unknown.tolist()!r}")
    return palette[codes], {"colormap": "reason", "legend": {r.name: list(_REASON_RGB[r]) for r in Reason},
                            "legend_picture": "below the image"}


# --------------------------------------------------------------------------- PLY

_PLY_VERTEX = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("amplitude", "<f4"), ("intensity", "u1")])


def _ply_header(frame: Frame, count: int) -> bytes:
    """ASCII PLY header for ``count`` vertices of :data:`_PLY_VERTEX`, documenting the frame."""
    pose = np.asarray(frame.world_from_sensor, dtype=np.float64)
    lines = [
        "ply", "format binary_little_endian 1.0",
        "comment tofcore frame: valid pixels in image order, from the decoded radial distance",
        "comment sensor frame (OpenCV: x right, y down, z forward), metres",
        f"comment image {frame.width}x{frame.height}, depth_output {frame.depth_output}",
        *(f"comment world_from_sensor row {i}: " + " ".join(repr(float(v)) for v in pose[i]) for i in range(4)),
        "comment amplitude: modulation amplitude in electrons; intensity: grey level of intensity.png",
        f"element vertex {count}",
        *(f"property {'float' if _PLY_VERTEX[name] == np.float32 else 'uchar'} {name}" for name in _PLY_VERTEX.names),
        "end_header",
    ]
    return ("\n".join(lines) + "\n").encode("ascii")


def _ply_vertices(frame: Frame) -> np.ndarray:
    """Structured (N,) array of the valid points (sensor frame, m), amplitude (e⁻), intensity grey."""
    valid = np.asarray(frame.valid, dtype=bool)
    points = frame.points("sensor")
    vertices = np.empty(len(points), dtype=_PLY_VERTEX)
    vertices["x"], vertices["y"], vertices["z"] = points.T
    vertices["amplitude"] = np.asarray(frame.amplitude)[valid]
    vertices["intensity"] = _intensity_grey(frame)[0][valid]
    return vertices


def _write_ply(path: Path, frame: Frame) -> None:
    """Write ``points.ply`` (header, then packed 17-byte little-endian vertices) to ``path``."""
    with open(path, "wb") as fh:
        fh.write(_ply_header(frame, int(np.count_nonzero(frame.valid))))
        fh.write(_ply_vertices(frame).tobytes())


# --------------------------------------------------------------------------- JSON

def _frame_document(frame: Frame) -> dict:
    """JSON-ready description of the frame (also the EXR ``tofcore`` header attribute)."""
    return _jsonable({
        "format": "tofcore frame", "version": 1,
        "width": frame.width, "height": frame.height, "depth_output": frame.depth_output,
        "world_from_sensor": frame.world_from_sensor, "raw_labels": frame.raw_labels,
        "distance_per_k": len(frame.distance_per_k), "units": UNITS,
        "reason_codes": {r.name: int(r) for r in Reason},
        "metadata": frame.metadata, "stats": frame.stats,
    }, "frame")


def _frame_json(document: dict, written: Mapping[str, Path], previews: Mapping[str, dict]) -> bytes:
    """UTF-8 ``frame.json``: the frame document, preview limits and the written files."""
    document = {**document, "previews": _jsonable(previews, "previews"),
                "files": [_file_record(kind, path) for kind, path in written.items()]}
    return (json.dumps(document, indent=2, allow_nan=False, ensure_ascii=False) + "\n").encode("utf-8")


def _jsonable(value: object, where: str) -> object:
    """``value`` as plain JSON types: arrays → lists, NumPy scalars → Python, NaN/inf → None."""
    if isinstance(value, enum.Enum):
        return value.name
    if value is None or isinstance(value, (str, bool)):
        return value
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist(), where)
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v, f"{where}[{k!r}]") for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _jsonable(getattr(value, f.name), f"{where}.{f.name}") for f in dataclasses.fields(value)}
    if isinstance(value, PurePath):
        return str(value)
    raise TypeError(f"{where}: value must be JSON-convertible (number, string, list, dict, array, "
                    f"dataclass, path), got {type(value).__name__}")
