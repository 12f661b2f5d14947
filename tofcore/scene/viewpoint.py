"""Camera views around a point of interest: an orbit eye, and whether it sees the point.

The eye sits on a sphere of radius :math:`d` about the target :math:`\\mathbf t`, at azimuth
:math:`\\phi` (from +X towards +Y) and elevation :math:`\\theta` above the horizontal:

.. math::

    \\mathbf e = \\mathbf t + d\\,(\\cos\\theta\\cos\\phi,\\ \\cos\\theta\\sin\\phi,\\ \\sin\\theta)

and looks at the target (:func:`tofcore.scene.pose.look_at`, Z up). :func:`sees` tests the line of
sight with the scene's BVH: the first surface along eye → target must be the object of interest (or
nothing before the target), seen from its front — a first hit on a back face means the eye is inside a
closed object or outside a room. :func:`clear` keeps the eye away from every surface: a camera 1 cm
from a wall has its LEDs (centimetres beside the lens) behind the wall, and sees nothing.
"""

from __future__ import annotations

import numpy as np

from .scene import Scene


def orbit_eye(target_m, distance_m: float, azimuth_rad: float, elevation_rad: float) -> np.ndarray:
    """World-frame eye position on the orbit (see the module docstring), metres."""
    ce = np.cos(elevation_rad)
    return np.asarray(target_m, np.float64) + distance_m * np.array(
        [ce * np.cos(azimuth_rad), ce * np.sin(azimuth_rad), np.sin(elevation_rad)])


def sees(scene: Scene, eye_m, target_m, object_id: int | None = None, tolerance_m: float = 0.02) -> bool:
    """Whether the eye sees the target: the first hit along eye → target is a front face of object
    ``object_id`` (any object when None), or lies within ``tolerance_m`` of the target or beyond it."""
    origin = np.asarray(scene.origin_m)
    eye, target = np.asarray(eye_m, np.float64) - origin, np.asarray(target_m, np.float64) - origin
    d = target - eye
    length = float(np.linalg.norm(d))
    d /= length
    hit = scene.bvh.intersect(eye[None].astype(np.float32), d[None].astype(np.float32), workers=1)
    prim = int(hit.prim[0])
    if prim < 0:
        return True
    if float(scene.face_normals[prim] @ d) > 0:  # a back face: inside something
        return False
    if object_id is not None and int(scene.object_ids[prim]) == object_id:
        return True
    return float(hit.t[0]) >= length - tolerance_m


#: Directions :func:`clear` tests: the 6 axes and the 8 diagonals (unit vectors).
_CLEARANCE_DIRECTIONS = np.concatenate([np.vstack([np.eye(3), -np.eye(3)]),
                                        np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
                                        / np.sqrt(3.0)])


def clear(scene: Scene, eye_m, clearance_m: float) -> bool:
    """Whether no surface lies within ``clearance_m`` of the eye along 14 directions (the axes and the
    diagonals). Every direction is within 36.2° of one of them (the worst, found on a 2001² grid of the
    octant: (0.591, 0, 0.807), cos = 0.807), so a plane (a wall, the floor, a table) nearer than
    0.80 · ``clearance_m`` is always found."""
    origin = np.asarray(eye_m, np.float64) - np.asarray(scene.origin_m)
    n = len(_CLEARANCE_DIRECTIONS)
    blocked = scene.bvh.occluded(np.repeat(origin[None], n, axis=0).astype(np.float32),
                                 _CLEARANCE_DIRECTIONS.astype(np.float32), np.full(n, clearance_m, np.float32),
                                 workers=1)
    return not bool(blocked.any())
