"""Training labels of a frame for multipath correction: ``labels.npz`` in the frame's folder.

Written when the set's ``[output]`` has ``labels = true``; listed in the record's files (checked by
``tofcore-batch verify``) and read by :meth:`tofcore.output.dataset.FrameRef.load`.

=====================  =========  =======  ==================================================================
array                  shape      dtype    content
=====================  =========  =======  ==================================================================
``multipath_error``    (H, W)     float32  measured depth − ground-truth depth (m), the sensor's depth output
                                           (radial or z); NaN where invalid or without a surface. Holds
                                           multipath, noise, scattering and wrapping errors together
``direct_depth``       (H, W)     float32  depth decoded from the k = 1 bucket only (direct light, no noise,
                                           no scattering), in the sensor's depth output (m)
``normal``             (H, W, 3)  float32  first-hit geometric normal in the **sensor** frame (OpenCV axes:
                                           x right, y down, z forward), facing the camera; NaN where none
``material_id``        (H, W)     int32    first-hit material, −1 none; names in the record's ``materials``
``object_id``          (H, W)     int32    first-hit object, −1 none; names in the record's ``objects``
=====================  =========  =======  ==================================================================

Per-bounce distances stay in ``frame.exr`` (``distance_k<K>``), the depth error of the direct light
alone is ``direct_depth − gt_depth``. The file is a deflated ``.npz`` with fixed member times, so the
same frame gives the same bytes.
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np

from .dataset import write_bytes_atomic

LABELS = "labels.npz"
NAMES = ("multipath_error", "direct_depth", "normal", "material_id", "object_id")


def _as_depth(distance: np.ndarray, directions: np.ndarray, depth_output: str) -> np.ndarray:
    """Radial distance → the sensor's depth output: z = r · d_z for unit pixel directions d."""
    return distance * directions[..., 2] if depth_output == "z" else distance  # tofcore.sensor.decode.radial_to_z


def frame_labels(frame) -> dict[str, np.ndarray]:
    """The label arrays of a rendered :class:`tofcore.Frame` (see the module docstring)."""
    shape = frame.depth.shape
    error = np.where(np.asarray(frame.valid, bool), frame.depth.astype(np.float32) - frame.gt_depth, np.nan)
    direct = (np.full(shape, np.nan, np.float32) if frame.direct_distance is None else
              _as_depth(np.asarray(frame.direct_distance, np.float32), np.asarray(frame.ray_directions, np.float32),
                        frame.depth_output))
    normal = np.full(shape + (3,), np.nan, np.float32)
    if frame.normal is not None:
        rotation = np.asarray(frame.world_from_sensor, np.float64)[:3, :3]
        normal = (np.asarray(frame.normal, np.float64) @ rotation).astype(np.float32)  # n_s = Rᵀ n_w
    material = (np.full(shape, -1, np.int32) if frame.material_id is None
                else np.asarray(frame.material_id, np.int32))
    return {"multipath_error": error.astype(np.float32), "direct_depth": np.asarray(direct, np.float32),
            "normal": normal, "material_id": material, "object_id": np.asarray(frame.object_id, np.int32)}


def encode_npz(arrays: dict[str, np.ndarray]) -> bytes:
    """A deflated ``.npz`` whose bytes depend on the arrays only (member times fixed to 1980-01-01)."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, array in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, np.ascontiguousarray(array), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, member.getvalue())
    return out.getvalue()


def write_labels(frame, folder: Path) -> Path:
    """Write ``folder/labels.npz`` (temporary file, fsync, rename) and return its path."""
    return write_bytes_atomic(Path(folder) / LABELS, encode_npz(frame_labels(frame)))


def material_table(scene) -> list[dict]:
    """What the ``material_id`` values mean: ``[{"id", "name"}]`` in the scene's material order."""
    return [{"id": i, "name": m.name} for i, m in enumerate(scene.materials)]
