"""Camera model: pinhole intrinsics, OpenCV lens distortion, thin lens, camera rays.

========================  ====  =======  ================================================================
name                      unit  default  meaning
========================  ====  =======  ================================================================
``width``                 px    –        image width (number of pixel columns), > 0
``height``                px    –        image height (number of pixel rows), > 0
``fx``, ``fy``            px    –        focal lengths of the camera matrix (thesis eq. 4.1), > 0
``cx``, ``cy``            px    –        principal point; the centre of pixel column i is at u = i
``k1``, ``k2``, ``k3``    –     0.0      radial distortion coefficients (thesis eq. 4.2, OpenCV's order
                                         k1, k2, p1, p2, k3)
``p1``, ``p2``            –     0.0      tangential distortion coefficients
``aperture_radius_m``     m     0.0      thin-lens aperture radius; 0 is a pinhole
``focus_distance_m``      m     inf      distance of the plane in focus, along +z
========================  ====  =======  ================================================================

Frames and conventions
----------------------
* Sensor frame = OpenCV camera frame: x right, y down, z forward, metres; the
  lens centre (pinhole) is the origin.
* Pixel coordinates (u, v) are continuous, OpenCV style: the centre of pixel
  (column i, row j) is at (u, v) = (i, j), so pixel (i, j) covers
  [i - 1/2, i + 1/2) × [j - 1/2, j + 1/2) and the image spans
  [-1/2, width - 1/2) × [-1/2, height - 1/2). Flat pixel index = j · width + i.
* Pixel coordinates are *distorted* (what the sensor sees); a point
  (X, Y, Z) of the sensor frame has *normalized undistorted* coordinates
  (x, y) = (X/Z, Y/Z) and *normalized distorted* coordinates (x_d, y_d) =
  :meth:`Camera.distort` (x, y). Camera rays leave through the undistorted
  position of each (jittered) pixel position, as in the thesis (§5.1.1, eq. 4.3).

A :class:`Camera` with distortion checks at construction that the distortion
can be inverted over the whole image (the thesis used calibrated
coefficients; a polynomial pushed outside its calibrated range folds over)
and caches the undistorted positions of all pixel centres; jittered samples
start Newton's method there, which makes exact ray generation cheap.

Example
-------
>>> cam = Camera.from_fov(512, 424, 70.6, k1=0.09, k2=-0.27, k3=0.09)
>>> pixel = np.repeat(np.arange(cam.width * cam.height), 4)       # 4 samples per pixel
>>> u_jitter, v_jitter, u_lens, v_lens = np.random.default_rng(0).random((4, pixel.size))
>>> origins, directions = cam.generate_rays(pixel, u_jitter, v_jitter, u_lens, v_lens)
>>> directions.shape
(868352, 3)
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .. import limits
from ..backend import asarray, device_copy, namespace
from ..errors import ConfigError
from .sampling import sample_concentric_disk

#: Newton's method for the inverse distortion stops when every step is
#: smaller than this (normalized image units). Convergence is quadratic, so
#: the error left after the last step is of the order of its square.
_NEWTON_STEP_TOL = 1e-10
#: Iteration limit; positions that have not converged by then become NaN.
_NEWTON_MAX_ITER = 50
#: Rays generated per block: small enough for the temporaries to stay in cache.
_RAY_BLOCK = 16384
#: Pixel centres per block while the undistortion table is built (temporaries stay in cache).
_TABLE_BLOCK = 8192
#: Distinct cameras whose undistortion table and invertibility check a process keeps (40 bytes a
#: pixel each): a batch parent checks a preset, then its overrides and scaling; a batch worker or the
#: add-on builds the same camera for every frame. Equal cameras share the table (it is read-only).
_TABLE_CACHE_SIZE = 4


@dataclass(frozen=True, kw_only=True)
class Camera:
    """Intrinsics, OpenCV distortion and thin lens of the ToF sensor; see the module docstring.

    All fields are keyword-only and checked in ``__post_init__``; a distorted
    camera is also checked for invertibility over the image (see
    :meth:`undistort`). Derived tables are cached per instance.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    aperture_radius_m: float = 0.0
    focus_distance_m: float = math.inf

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            try:
                as_int = operator.index(value)
            except TypeError:
                as_int = None
            if as_int is None or isinstance(value, bool) or as_int <= 0:
                raise ConfigError(f"Camera: {name} must be a positive integer (pixels), got {value!r}")
            object.__setattr__(self, name, as_int)
        # Before any per-pixel table is built (the distortion check below makes 40 bytes a pixel).
        limits.MAX_PIXELS.check(self.width * self.height, "Camera", "width x height",
                                f"{self.width} x {self.height} = {self.width * self.height:,}")
        for name in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "aperture_radius_m",
                     "focus_distance_m"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise ConfigError(f"Camera: {name} must be a number, got {value!r}")
            object.__setattr__(self, name, float(value))
        for name in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "aperture_radius_m"):
            if not math.isfinite(getattr(self, name)):
                raise ConfigError(f"Camera: {name} must be finite, got {getattr(self, name)!r}")
        for name in ("fx", "fy"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"Camera: {name} must be > 0, got {getattr(self, name)!r}")
        if self.aperture_radius_m < 0:
            raise ConfigError(f"Camera: aperture_radius_m must be >= 0, got {self.aperture_radius_m!r}")
        if not self.focus_distance_m > 0:  # also rejects NaN; +inf is focus at infinity
            raise ConfigError(f"Camera: focus_distance_m must be > 0 (inf allowed), got {self.focus_distance_m!r}")
        if 0 < self.aperture_radius_m and not self.aperture_radius_m < self.focus_distance_m:
            raise ConfigError(f"Camera: aperture_radius_m must be less than focus_distance_m (a thin lens focuses "
                              f"at a distance beyond its own radius), got {self.aperture_radius_m!r} with "
                              f"focus_distance_m {self.focus_distance_m!r}")
        if self.has_distortion:
            # An extreme focal length (fx = 1e-300) overflows the distortion polynomial: the NaN it gives
            # fails the check, which is the one line to say; NumPy's warnings about it are not.
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                self._check_invertible()

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, vfov_deg: float | None = None,
                 **kw: float) -> Camera:
        """A camera whose image spans the given field of view, principal point at the image centre.

        Parameters
        ----------
        width, height : int
            Image size in pixels.
        hfov_deg : float
            Horizontal field of view in degrees, 0 < hfov_deg < 180: the angle
            between the rays through the left (u = -1/2) and right
            (u = width - 1/2) image edges at the principal point's row.
        vfov_deg : float, optional
            Vertical field of view in degrees (top to bottom edge); None gives
            square pixels (fy = fx).
        **kw
            The remaining fields (distortion, aperture, focus). The field of
            view is that of the pinhole model: distortion changes it.

        Notes
        -----
        .. math:: f_x = \\frac{w/2}{\\tan(\\mathrm{hfov}/2)}, \\quad
                  c_x = \\frac{w - 1}{2}, \\quad c_y = \\frac{h - 1}{2}
        """
        for name, fov in (("hfov_deg", hfov_deg), ("vfov_deg", vfov_deg)):
            if fov is not None and not 0.0 < fov < 180.0:  # NaN fails too
                raise ConfigError(f"Camera: {name} must be in (0, 180) degrees, got {fov!r}")
        fx = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
        fy = fx if vfov_deg is None else 0.5 * height / math.tan(math.radians(vfov_deg) / 2)
        return cls(width=width, height=height, fx=fx, fy=fy, cx=(width - 1) / 2, cy=(height - 1) / 2, **kw)

    # --- derived quantities ------------------------------------------------------------------------

    @property
    def has_distortion(self) -> bool:
        """True if any distortion coefficient is non-zero."""
        return any((self.k1, self.k2, self.p1, self.p2, self.k3))

    @property
    def camera_matrix(self) -> NDArray[np.float64]:
        """The 3×3 camera matrix K of thesis eq. 4.1, as OpenCV expects it."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distortion_coefficients(self) -> NDArray[np.float64]:
        """(k1, k2, p1, p2, k3): the 5-tuple of thesis eq. 4.2, OpenCV's order."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    # --- distortion -------------------------------------------------------------------------------

    def distort(self, x: ArrayLike, y: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Normalized undistorted → normalized distorted image coordinates (OpenCV's model).

        Parameters
        ----------
        x, y : array_like
            Normalized undistorted coordinates X/Z, Y/Z (sensor frame); broadcast together.

        Returns
        -------
        xd, yd : ndarray of float64

        Notes
        -----
        OpenCV's 5-coefficient model, as used by the thesis (eq. 4.1–4.3):

        .. math::
            r^2 &= x^2 + y^2 \\\\
            x_d &= x\\,(1 + k_1 r^2 + k_2 r^4 + k_3 r^6) + 2 p_1 x y + p_2 (r^2 + 2 x^2) \\\\
            y_d &= y\\,(1 + k_1 r^2 + k_2 r^4 + k_3 r^6) + p_1 (r^2 + 2 y^2) + 2 p_2 x y

        and pixel coordinates :math:`u = f_x x_d + c_x, v = f_y y_d + c_y`.
        """
        xd, yd, *_ = self._distort_with_jacobian(asarray(x, dtype=np.float64),
                                                 asarray(y, dtype=np.float64))
        return xd, yd

    def _distort_with_jacobian(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> tuple[
            NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64],
            NDArray[np.float64]]:
        """:meth:`distort` and its Jacobian ∂(x_d, y_d)/∂(x, y), which is symmetric for this model.

        Returns ``xd, yd, j_xx, j_xy, j_yy`` with ``j_xy = ∂x_d/∂y = ∂y_d/∂x``.
        """
        k1, k2, k3, p1, p2 = self.k1, self.k2, self.k3, self.p1, self.p2
        x2 = x * x
        y2 = y * y
        xy = x * y
        r2 = x2 + y2
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        radial_d = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r²
        xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2)
        yd = y * radial + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy
        j_xx = radial + 2.0 * x2 * radial_d + 2.0 * p1 * y + 6.0 * p2 * x
        j_xy = 2.0 * xy * radial_d + 2.0 * p1 * x + 2.0 * p2 * y
        j_yy = radial + 2.0 * y2 * radial_d + 6.0 * p1 * y + 2.0 * p2 * x
        return xd, yd, j_xx, j_xy, j_yy

    def _newton_undistort(self, xd: NDArray[np.float64], yd: NDArray[np.float64],
                          x: NDArray[np.float64], y: NDArray[np.float64]) -> tuple[NDArray[np.float64],
                                                                                   NDArray[np.float64]]:
        """Solve distort(x, y) = (xd, yd) by Newton's method from the start (x, y); NaN where it fails."""
        for _ in range(_NEWTON_MAX_ITER):
            fxd, fyd, j_xx, j_xy, j_yy = self._distort_with_jacobian(x, y)
            rx = fxd - xd
            ry = fyd - yd
            with np.errstate(divide="ignore", invalid="ignore"):
                inv_det = 1.0 / (j_xx * j_yy - j_xy * j_xy)
                step_x = (j_yy * rx - j_xy * ry) * inv_det
                step_y = (j_xx * ry - j_xy * rx) * inv_det
            x = x - step_x
            y = y - step_y
            step = np.maximum(np.abs(step_x), np.abs(step_y))
            if step.size == 0 or step.max() < _NEWTON_STEP_TOL:  # NaN never compares below: not converged
                return x, y
        failed = ~(step < _NEWTON_STEP_TOL)
        return np.where(failed, np.nan, x), np.where(failed, np.nan, y)

    def undistort(self, xd: ArrayLike, yd: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Normalized distorted → normalized undistorted coordinates: the exact inverse of :meth:`distort`.

        Parameters
        ----------
        xd, yd : array_like
            Normalized distorted coordinates, :math:`x_d = (u - c_x)/f_x,
            y_d = (v - c_y)/f_y` (thesis eq. 4.3); broadcast together.

        Returns
        -------
        x, y : ndarray of float64
            The solution of ``distort(x, y) == (xd, yd)`` to ~1e-12 or better,
            on the branch connected to the principal point. NaN where Newton's
            method does not converge (possible only far outside the image).

        Notes
        -----
        OpenCV's ``cv2.undistortPoints`` runs a fixed-point iteration that
        stops after 5 steps by default: pixels off at the corners of a strongly
        distorted image (2.4 px for k1 = -0.3, k2 = 0.08, p1 = -p2 = 0.01 at
        512 × 424, fx = 365). This runs vectorised Newton iterations in
        float64, started from the cached undistorted centre of the nearest
        pixel, until the step is below 1e-10 (the error left is about its
        square). The camera was checked at construction to be invertible over
        the image: Newton converged at every pixel centre and on the image
        border, the Jacobian determinant is positive there, and the
        undistorted centres keep the pixel order along every row and column.
        """
        xd, yd = np.broadcast_arrays(asarray(xd, dtype=np.float64), asarray(yd, dtype=np.float64))
        if not self.has_distortion:
            return xd.copy(), yd.copy()
        col = np.clip(np.rint(xd * self.fx + self.cx), 0, self.width - 1).astype(np.int64)
        row = np.clip(np.rint(yd * self.fy + self.cy), 0, self.height - 1).astype(np.int64)
        return self._undistort_near(xd, yd, row, col)

    def _undistort_near(self, xd: NDArray[np.float64], yd: NDArray[np.float64], row: NDArray[np.int64],
                        col: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Undistort positions that lie in or near the pixels (row, col).

        Newton's method starts from the first-order prediction around the
        pixel centre: undistorted centre + inverse Jacobian × offset.
        """
        x_c, y_c, inv_xx, inv_xy, inv_yy = (device_copy(namespace(xd), t) for t in self._centre_table)
        i = row * self.width + col
        dxd = xd - (col - self.cx) / self.fx
        dyd = yd - (row - self.cy) / self.fy
        inv_xy_i = inv_xy[i]
        x0 = x_c[i] + inv_xx[i] * dxd + inv_xy_i * dyd
        y0 = y_c[i] + inv_xy_i * dxd + inv_yy[i] * dyd
        return self._newton_undistort(xd, yd, x0, y0)

    @cached_property
    def _centre_table(self) -> tuple[NDArray[np.float64], ...]:
        """Per pixel centre, flat (height·width,) read-only arrays: x, y and the inverse Jacobian.

        ``x, y`` are the undistorted normalized coordinates (Newton's method
        started at the distorted position itself; NaN where it did not
        converge, which the construction check rejects); ``inv_xx, inv_xy,
        inv_yy`` are the entries of the (symmetric) inverse of
        ∂(x_d, y_d)/∂(x, y) there. Built once per process for equal cameras
        (:func:`_shared_centre_table`).
        """
        return _shared_centre_table(self)

    def _build_centre_table(self) -> tuple[NDArray[np.float64], ...]:
        """:attr:`_centre_table`, computed: Newton's method over the pixel centres in cache-sized blocks.

        Every block takes the same steps as the whole image would (the iterations stop when the largest
        step of all pixels is below the tolerance), so the table does not depend on the block size.
        """
        xd, yd = self._distorted_centres()
        n = xd.size
        x, y = xd.copy(), yd.copy()
        blocks = [slice(i, min(i + _TABLE_BLOCK, n)) for i in range(0, n, _TABLE_BLOCK)]
        step = np.empty(n)
        for _ in range(_NEWTON_MAX_ITER):
            for b in blocks:  # the steps of _newton_undistort, block by block
                fxd, fyd, j_xx, j_xy, j_yy = self._distort_with_jacobian(x[b], y[b])
                rx = fxd - xd[b]
                ry = fyd - yd[b]
                with np.errstate(divide="ignore", invalid="ignore"):
                    inv_det = 1.0 / (j_xx * j_yy - j_xy * j_xy)
                    step_x = (j_yy * rx - j_xy * ry) * inv_det
                    step_y = (j_xx * ry - j_xy * rx) * inv_det
                x[b] = x[b] - step_x
                y[b] = y[b] - step_y
                step[b] = np.maximum(np.abs(step_x), np.abs(step_y))
            if n == 0 or step.max() < _NEWTON_STEP_TOL:  # NaN never compares below: not converged
                break
        else:
            failed = ~(step < _NEWTON_STEP_TOL)
            x, y = np.where(failed, np.nan, x), np.where(failed, np.nan, y)
        _, _, j_xx, j_xy, j_yy = self._distort_with_jacobian(x, y)
        with np.errstate(divide="ignore"):  # det = 0 only for a camera the construction check rejects
            inv_det = 1.0 / (j_xx * j_yy - j_xy * j_xy)
        table = (x, y, j_yy * inv_det, -j_xy * inv_det, j_xx * inv_det)
        for a in table:
            a.setflags(write=False)
        return table

    def _distorted_centres(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Normalized distorted (xd, yd) of every pixel centre, flat (height·width,) arrays."""
        xd = (np.arange(self.width, dtype=np.float64) - self.cx) / self.fx
        yd = (np.arange(self.height, dtype=np.float64) - self.cy) / self.fy
        return np.tile(xd, self.height), np.repeat(yd, self.width)

    def _check_invertible(self) -> None:
        """Raise ConfigError unless the distortion maps a region one-to-one onto the whole image.

        Checked on the pixel grid, at every pixel centre and on the image border (pixel edges):
        Newton converged, the Jacobian determinant is positive, and undistorted
        centres are strictly increasing in x along each row and in y down each column.
        Checked once per process for equal cameras (:func:`_shared_invertibility_problem`).
        """
        problem = _shared_invertibility_problem(self)
        if problem is not None:
            raise ConfigError(problem)

    def _invertibility_problem(self) -> str | None:
        """The message of :meth:`_check_invertible`'s error, or None when the distortion is invertible."""
        w, h = self.width, self.height
        x, y, *_ = self._centre_table
        det_centres = self._jacobian_determinant(x, y)
        grid_x, grid_y = x.reshape(h, w), y.reshape(h, w)
        order_ok = bool(np.all(np.diff(grid_x, axis=1) > 0) and np.all(np.diff(grid_y, axis=0) > 0))  # NaN fails
        # The border: every pixel corner on the image outline, distorted coordinates.
        edge_u = np.arange(w + 1, dtype=np.float64) - 0.5
        edge_v = np.arange(h + 1, dtype=np.float64) - 0.5
        border_u = np.concatenate([edge_u, edge_u, np.full(h + 1, -0.5), np.full(h + 1, w - 0.5)])
        border_v = np.concatenate([np.full(w + 1, -0.5), np.full(w + 1, h - 0.5), edge_v, edge_v])
        bxd, byd = (border_u - self.cx) / self.fx, (border_v - self.cy) / self.fy
        bx, by = self.undistort(bxd, byd)
        det_border = self._jacobian_determinant(bx, by)
        bad_centre = ~(det_centres > 0)
        bad_border = ~(det_border > 0)
        if bad_centre.any() or bad_border.any() or not order_ok:
            if bad_border.any():
                i = int(np.argmax(bad_border))
                where = f"at the image border (u={border_u[i]:g}, v={border_v[i]:g})"
            elif bad_centre.any():
                i = int(np.argmax(bad_centre))
                where = f"at pixel (u={i % w}, v={i // w})"
            else:
                where = "inside the image (undistorted pixel centres out of order)"
            return (f"Camera: distortion (k1={self.k1!r}, k2={self.k2!r}, p1={self.p1!r}, p2={self.p2!r}, "
                    f"k3={self.k3!r}) must be invertible over the {w}x{h} image "
                    f"(fx={self.fx:g}, fy={self.fy:g}, cx={self.cx:g}, cy={self.cy:g}), "
                    f"but it folds over or has no inverse {where}")
        return None

    def _jacobian_determinant(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        """det ∂(x_d, y_d)/∂(x, y) at undistorted normalized positions (NaN in, NaN out)."""
        _, _, j_xx, j_xy, j_yy = self._distort_with_jacobian(x, y)
        return j_xx * j_yy - j_xy * j_xy

    # --- projection and rays ----------------------------------------------------------------------

    def project(self, points_sensor: ArrayLike) -> NDArray[np.float64]:
        """Pixel coordinates (u, v) of points in the sensor frame, distortion included.

        Parameters
        ----------
        points_sensor : array_like, shape (..., 3)
            Points (X, Y, Z) in the sensor frame, metres (x right, y down, z forward).

        Returns
        -------
        ndarray of float64, shape (..., 2)
            (u, v) per :meth:`distort` with (x, y) = (X/Z, Y/Z); the same as
            ``cv2.projectPoints`` with zero rotation and translation. NaN for
            points with Z <= 0 (behind the lens or in its plane).
        """
        p = asarray(points_sensor, dtype=np.float64)
        if p.shape[-1:] != (3,):
            raise ValueError(f"Camera.project: points_sensor must have shape (..., 3), got {p.shape}")
        z = np.where(p[..., 2] > 0, p[..., 2], np.nan)
        xd, yd = self.distort(p[..., 0] / z, p[..., 1] / z)
        return np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=-1)

    def ray_directions(self, u: ArrayLike, v: ArrayLike) -> NDArray[np.float64]:
        """Unit directions (sensor frame) of the pinhole rays through continuous pixel positions.

        Parameters
        ----------
        u, v : array_like
            Distorted pixel coordinates (the centre of pixel column i is u = i); broadcast together.

        Returns
        -------
        ndarray of float64, shape (..., 3)
            :math:`(x, y, 1) / \\sqrt{x^2 + y^2 + 1}` with (x, y) =
            :meth:`undistort` ((u - c_x)/f_x, (v - c_y)/f_y) (thesis eq. 4.3).
        """
        xd = (asarray(u, dtype=np.float64) - self.cx) / self.fx
        yd = (asarray(v, dtype=np.float64) - self.cy) / self.fy
        return _unit_directions(*self.undistort(xd, yd))

    def pixel_center_directions(self) -> NDArray[np.float32]:
        """Unit ray directions through every pixel centre, shape (height, width, 3), float32, read-only.

        Computed once per camera and cached; the array is shared, hence read-only.
        For point clouds: radial distance × direction = point in the sensor frame.
        """
        return self._pixel_center_directions

    @cached_property
    def _pixel_center_directions(self) -> NDArray[np.float32]:
        x, y = self._centre_table[:2] if self.has_distortion else self._distorted_centres()
        directions = _unit_directions(x, y).astype(np.float32).reshape(self.height, self.width, 3)
        directions.setflags(write=False)
        return directions

    def generate_rays(self, pixel_index: ArrayLike, u_jitter: ArrayLike, v_jitter: ArrayLike,
                      u_lens: ArrayLike, v_lens: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Camera rays for N samples, in the sensor frame.

        Parameters
        ----------
        pixel_index : array_like of int, shape (N,)
            Flat pixel index ``row * width + column``, 0 <= index < width·height.
        u_jitter, v_jitter : array_like of float, shape (N,)
            Uniform numbers in [0, 1) placing the sample uniformly within its
            pixel: u = column - 1/2 + u_jitter, v = row - 1/2 + v_jitter.
        u_lens, v_lens : array_like of float, shape (N,)
            Uniform numbers in [0, 1) choosing the point on the aperture disk
            (concentric mapping); ignored by a pinhole camera, so that the
            random streams do not depend on the camera.

        Returns
        -------
        origins : ndarray of float64, shape (N, 3)
            Metres, sensor frame: all zero for a pinhole; the sampled point
            (x_lens, y_lens, 0) on the aperture disk for a thin lens.
        directions : ndarray of float64, shape (N, 3)
            Unit vectors. Pinhole: through the undistorted sample position
            (as :meth:`ray_directions`). Thin lens: from the lens point towards
            the point where the pinhole ray of that sample meets the focus
            plane z = focus_distance_m, so all lens samples of one pixel
            position meet there; parallel to the pinhole ray when the focus is
            at infinity.

        Notes
        -----
        Thin lens (pbrt): with the undistorted sample position (x, y), lens
        point :math:`(l_x, l_y, 0)` and focus distance F, the direction is
        proportional to :math:`(x - l_x/F,\\; y - l_y/F,\\; 1)`.
        Samples are processed in blocks of a few thousand so that temporaries
        stay in cache; the result does not depend on the block size.
        """
        pixel_index, u_jitter, v_jitter, u_lens, v_lens = np.broadcast_arrays(
            asarray(pixel_index, dtype=np.int64), *(asarray(a, dtype=np.float64)
                                                       for a in (u_jitter, v_jitter, u_lens, v_lens)))
        n_pixels = self.width * self.height
        if pixel_index.ndim != 1:
            raise ValueError(f"Camera.generate_rays: the arguments must be 1-D arrays, got shape {pixel_index.shape}")
        if pixel_index.size and (pixel_index.min() < 0 or pixel_index.max() >= n_pixels):
            raise ValueError(f"Camera.generate_rays: pixel_index must be in [0, {n_pixels}), "
                             f"got values in [{pixel_index.min()}, {pixel_index.max()}]")
        xp = namespace(pixel_index)
        origins = xp.empty((pixel_index.size, 3))
        directions = xp.empty((pixel_index.size, 3))
        block_size = _RAY_BLOCK if xp is np else max(pixel_index.size, 1)  # a GPU takes all rays at once
        for start in range(0, pixel_index.size, block_size):
            block = slice(start, start + block_size)
            origins[block], directions[block] = self._ray_block(
                pixel_index[block], u_jitter[block], v_jitter[block], u_lens[block], v_lens[block])
        return origins, directions

    def _ray_block(self, pixel_index: NDArray[np.int64], u_jitter: NDArray[np.float64],
                   v_jitter: NDArray[np.float64], u_lens: NDArray[np.float64],
                   v_lens: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """:meth:`generate_rays` for one block of validated 1-D arrays."""
        row, col = np.divmod(pixel_index, self.width)
        xd = (col + (u_jitter - 0.5 - self.cx)) / self.fx
        yd = (row + (v_jitter - 0.5 - self.cy)) / self.fy
        x, y = self._undistort_near(xd, yd, row, col) if self.has_distortion else (xd, yd)
        origins = namespace(pixel_index).zeros((pixel_index.size, 3))
        if self.aperture_radius_m > 0.0:
            lens_x, lens_y = sample_concentric_disk(u_lens, v_lens)
            origins[:, 0] = lens_x * self.aperture_radius_m
            origins[:, 1] = lens_y * self.aperture_radius_m
            x = x - origins[:, 0] / self.focus_distance_m  # aim at the focus-plane point (x F, y F, F);
            y = y - origins[:, 1] / self.focus_distance_m  # F = inf leaves the pinhole direction
        return origins, _unit_directions(x, y)


def _unit_directions(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """(x, y, 1) normalized to unit length: the direction of normalized image position (x, y)."""
    inv_norm = 1.0 / np.sqrt(x * x + y * y + 1.0)
    return np.stack([x * inv_norm, y * inv_norm, inv_norm], axis=-1)


@lru_cache(maxsize=_TABLE_CACHE_SIZE)
def _shared_centre_table(camera: Camera) -> tuple[NDArray[np.float64], ...]:
    """The undistortion table of ``camera``, built once per process for equal cameras (read-only arrays)."""
    return camera._build_centre_table()


@lru_cache(maxsize=_TABLE_CACHE_SIZE)
def shared_centre_rows(camera: Camera) -> NDArray[np.float64]:
    """``camera._centre_table`` as one (5, height·width) array, built once per process for equal cameras: the
    compiled tracer's camera table (tofcore.compiled.setup.camera_table), the same array for every render, so a
    GPU render finds it on the device already (stacking and uploading it took ≈ 2 ms of a 512 × 424 preview
    frame). Shared, so never written; left writeable because numba compiles its kernels for writeable arrays
    (a read-only one would be another signature, compiled again)."""
    return np.stack(camera._centre_table)


@lru_cache(maxsize=_TABLE_CACHE_SIZE)
def _shared_invertibility_problem(camera: Camera) -> str | None:
    """:meth:`Camera._invertibility_problem`, once per process for equal cameras."""
    return camera._invertibility_problem()
