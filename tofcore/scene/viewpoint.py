"""Camera views around a point of interest: an orbit eye, and whether it sees the point.

The eye sits on a sphere of radius :math:`d` about the target :math:`\\mathbf t`, at azimuth
:math:`\\phi` (from +X towards +Y) and elevation :math:`\\theta` above the horizontal:

.. math::

    \\mathbf e = \\mathbf t + d\\,(\\cos\\theta\\cos\\phi,\\ \\cos\\theta\\sin\\phi,\\ \\sin\\theta)

and looks at the target (:func:`tofcore.scene.pose.look_at`, Z up). :func:`sees` tests the line of
sight with the scene's BVH: the first surface along eye → target must be the object of interest (or
nothing before the target), seen from its front — a first hit on a back face means the eye is inside a
closed object or outside a room.
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
