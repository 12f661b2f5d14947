"""Sensor poses: 4×4 ``world_from_sensor`` matrices.

Sensor frame = OpenCV camera frame (x right, y down, z forward); world frame =
Blender's (right-handed, Z up, metres). A Blender camera's ``matrix_world``
maps its local frame (looking down −Z, Y up) to the world, so
``world_from_sensor = matrix_world @ diag(1, −1, −1, 1)`` (DESIGN.md).
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError

BLENDER_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Maps OpenCV camera axes to Blender camera axes (and back: it is its own inverse)."""


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``world_from_sensor`` for a sensor at ``eye`` looking at ``target`` with ``up`` pointing up in the image.

    Parameters are world-frame points/vectors in metres. Image x (right) is
    forward × up, image y (down) is forward × right.
    """
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    forward = target - eye
    if np.linalg.norm(forward) == 0:
        raise ConfigError(f"look_at: target must differ from eye, got {target.tolist()} for both")
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        raise ConfigError(f"look_at: up {up.tolist()} must not be parallel to the view direction")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose


def from_blender_matrix_world(matrix_world) -> np.ndarray:
    """``world_from_sensor`` of a Blender camera from its ``matrix_world`` (4×4)."""
    return np.asarray(matrix_world, dtype=np.float64) @ BLENDER_FROM_OPENCV


def rigid_problem(matrix: np.ndarray) -> str | None:
    """None when a finite 4×4 ``world_from_sensor`` is a rigid transform, else what is wrong (one phrase).

    Rigid: the 3×3 block R orthonormal with det R = +1 (|RRᵀ − I| ≤ 1e-6), last row 0 0 0 1 — a scale
    or shear would stretch every ray's length and so every depth.
    """
    rot = matrix[:3, :3]
    if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6):
        scale = np.sqrt(np.abs(np.diag(rot @ rot.T)))
        return f"its rotation must be orthonormal (no scale or shear), got axis lengths {np.round(scale, 6).tolist()}"
    if np.linalg.det(rot) < 0:
        return "its rotation must have determinant +1 (no mirroring)"
    if not np.allclose(matrix[3], [0, 0, 0, 1]):
        return f"its last row must be 0 0 0 1, got {matrix[3].tolist()}"
    return None
