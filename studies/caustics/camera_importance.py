r"""The importance of a pinhole camera: where a point lands on the image, and W_p, the density that turns
an integral over the pixel's area into one over the surfaces the pinhole sees.

The tracer's pixel value is the mean radiance over the pixel's area in (distorted) pixel coordinates,
:math:`I_p = \int_{\text{pixel } p} L(u)\, du`, pixel area 1 (``Camera.generate_rays``: uniform jitter in
the pixel). With (x, y) = (X/Z, Y/Z) the undistorted normalized coordinates of a sensor-frame point,
u = f_x x_d + c_x, v = f_y y_d + c_y, x_d = distort(x), and dx dy = dω / cos³θ (θ from the optical axis),

.. math:: I_p = \int L(y \to \text{lens})\, W_p(y)\, dA_y, \qquad
          W_p(y) = [u(y) \in p]\; \frac{f_x f_y\, |\det \partial(x_d, y_d)/\partial(x, y)|}{\cos^3\theta}\;
                   \frac{\cos\theta_y}{r^2}

(r = |y − lens|, θ_y at y between its normal and the lens). W_p is also the area density with which the
path tracer's camera ray of pixel p finds its first vertex (the p_cam of :mod:`mis`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Importance:
    """Where light-vertex connections land: flat pixel index (−1 outside the image) and W_p (1/m²)."""

    pixel: np.ndarray
    weight: np.ndarray


def camera_importance(camera, points_sensor: np.ndarray, cos_y: np.ndarray) -> Importance:
    """W_p(y) of a pinhole camera for points y (sensor frame, metres) whose surface cosine towards the
    lens is ``cos_y`` (see the module docstring); 0 behind the lens, outside the image or for cos_y ≤ 0."""
    if camera.aperture_radius_m > 0:
        raise ValueError("camera_importance: pinhole cameras only (aperture_radius_m = 0), "
                         f"got {camera.aperture_radius_m!r}")
    p = np.asarray(points_sensor, np.float64)
    r2 = (p * p).sum(axis=1)
    front = (p[:, 2] > 0) & (cos_y > 0)
    z = np.where(front, p[:, 2], 1.0)
    x, y = p[:, 0] / z, p[:, 1] / z
    uv = camera.project(np.where(front[:, None], p, [0.0, 0.0, 1.0]))
    u = np.where(np.isfinite(uv[:, 0]), np.clip(uv[:, 0], -1.0, camera.width), -1.0)
    v = np.where(np.isfinite(uv[:, 1]), np.clip(uv[:, 1], -1.0, camera.height), -1.0)
    col, row = np.floor(u + 0.5).astype(np.int64), np.floor(v + 0.5).astype(np.int64)
    inside = front & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    if camera.has_distortion:  # far outside the image the polynomial folds back in: keep true round trips only
        xu, yu = camera.undistort((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy)
        inside &= np.hypot(xu - x, yu - y) <= 1e-6 * np.maximum(1.0, np.hypot(x, y))
    cos_theta = z / np.sqrt(r2)
    det = (np.abs(camera._jacobian_determinant(x, y)) if camera.has_distortion
           else np.ones(len(p)))
    weight = np.where(inside, camera.fx * camera.fy * det / cos_theta**3 * np.maximum(cos_y, 0.0) / r2, 0.0)
    return Importance(pixel=np.where(inside, row * camera.width + col, -1), weight=weight)
