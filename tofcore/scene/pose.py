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


#: Margins of :func:`framed_view`: the box's far side at most this share of the sensor's longest range (the
#: LED's return falls as 1/d², so the last metres are the noisiest), its near side at least this many times
#: the shortest range.
FAR_MARGIN = 0.9
NEAR_MARGIN = 1.1


def framed_view(lo, hi, *, tan_half_fov: tuple[float, float], range_m: tuple[float, float]) -> np.ndarray:
    """4×4 ``world_from_sensor`` looking along +Y (Blender's front view) at the centre of the box [lo, hi],
    framed for a sensor: the whole box in its field of view where that keeps the box within its range,
    else as much of it as the range allows.

    The box has half extents (a_x, a_y, a_z) about its centre; the sensor sits at distance d in front of
    it, so the box's near side is at depth d − a_y and its far side at d + a_y. Its near side fills the
    field of view (half-angle tangents t_x, t_y) at

    .. math:: d_\\mathrm{fov} = a_y + \\max(a_x / t_x,\\; a_z / t_y),

    its far side is within the range [r_min, r_max] while d ≤ d_far = FAR_MARGIN·r_max − a_y, and its near
    side while d ≥ d_near = a_y + NEAR_MARGIN·r_min. The sensor takes d = max(d_fov, d_near), moved in to
    max(d_far, a_y) where that is beyond d_far: the far side's range comes first (in a room the far wall
    fills the image; what is nearer than r_min is the floor's near edge, below the field of view), and the
    sensor never enters the box. A box deeper than FAR_MARGIN·r_max keeps its far side out of range.

    Parameters
    ----------
    lo, hi : the box's corners, world frame, m.
    tan_half_fov : (t_x, t_y), tangents of the narrower half-angles of the field of view (e.g. min(c_x,
        W − c_x) / f_x).
    range_m : (r_min, r_max), the sensor's valid distances, m.
    """
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, 1e-3)
    d_fov = half[1] + max(half[0] / tan_half_fov[0], half[2] / tan_half_fov[1])
    d_near = half[1] + NEAR_MARGIN * range_m[0]
    d_far = FAR_MARGIN * range_m[1] - half[1]
    distance = max(d_fov, d_near)
    if distance > d_far:
        distance = max(d_far, half[1])
    return look_at(centre - np.array([0.0, distance, 0.0]), centre)
