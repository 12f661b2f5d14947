"""Tests of tofcore.scene.camera: OpenCV distortion, exact undistortion, jitter, thin lens, field of view, validation.

OpenCV (``cv2.projectPoints``, ``cv2.undistortPointsIter``) is the reference
where it is installed; the tests that need it skip otherwise.
"""

import math

import numpy as np
import pytest

from tofcore.scene.camera import _RAY_BLOCK, Camera
from tofcore.errors import ConfigError

# Kinect-v2-sized intrinsics (512 × 424, fx ≈ 365) with strong distortion of both kinds.
KINECT_LIKE = dict(width=512, height=424, fx=365.0, fy=366.5, cx=254.9, cy=205.4)
DISTORTIONS = {
    "pincushion-then-barrel": dict(k1=0.2, k2=-0.5, p1=0.001, p2=-0.002, k3=0.3),
    "barrel+tangential": dict(k1=-0.3, k2=0.08, p1=0.01, p2=-0.01),
    "kinect-v2-typical": dict(k1=0.0905, k2=-0.268, k3=0.0951),
}


@pytest.fixture(scope="module", params=list(DISTORTIONS), ids=list(DISTORTIONS))
def distorted_camera(request) -> Camera:
    return Camera(**KINECT_LIKE, **DISTORTIONS[request.param])


def pixel_grid(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) of every pixel centre, flat, row-major (= flat pixel index order)."""
    v, u = np.divmod(np.arange(cam.width * cam.height), cam.width)
    return u.astype(np.float64), v.astype(np.float64)


def opencv_project(cv2, cam: Camera, points: np.ndarray) -> np.ndarray:
    uv, _ = cv2.projectPoints(np.ascontiguousarray(points, dtype=np.float64), np.zeros(3), np.zeros(3),
                              cam.camera_matrix, cam.distortion_coefficients)
    return uv.reshape(-1, 2)


# --- distortion against OpenCV ----------------------------------------------------------------------

def test_pixel_centre_rays_reproject_onto_their_pixel_centres(distorted_camera):
    cv2 = pytest.importorskip("cv2")
    cam = distorted_camera
    u, v = pixel_grid(cam)
    table = cam.pixel_center_directions().reshape(-1, 3)
    uv = opencv_project(cv2, cam, table)
    assert np.abs(uv[:, 0] - u).max() < 1e-3 and np.abs(uv[:, 1] - v).max() < 1e-3   # float32 table
    uv = opencv_project(cv2, cam, cam.ray_directions(u, v))
    assert np.abs(uv[:, 0] - u).max() < 1e-8 and np.abs(uv[:, 1] - v).max() < 1e-8   # float64 rays


def test_project_agrees_with_opencv(distorted_camera):
    cv2 = pytest.importorskip("cv2")
    cam = distorted_camera
    rng = np.random.default_rng(1)
    z = rng.uniform(0.3, 6.0, 20_000)
    xy = rng.uniform(-0.6, 0.6, (20_000, 2)) * z[:, None]   # about the field of view, some beyond the image
    points = np.column_stack([xy, z])
    np.testing.assert_allclose(cam.project(points), opencv_project(cv2, cam, points), rtol=0, atol=1e-6)


def test_undistort_agrees_with_opencv_run_to_convergence(distorted_camera):
    cv2 = pytest.importorskip("cv2")
    cam = distorted_camera
    u, v = pixel_grid(cam)
    u, v = u[::5], v[::5]
    ours = np.column_stack(cam.undistort((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)   # the default stops after 5 steps
    args = (np.column_stack([u, v]).reshape(-1, 1, 2), cam.camera_matrix, cam.distortion_coefficients)
    if hasattr(cv2, "undistortPointsIter"):                               # OpenCV 4
        reference = cv2.undistortPointsIter(*args, None, None, criteria)
    else:                                                                 # OpenCV 5 moved criteria here
        reference = cv2.undistortPoints(*args, R=None, P=None, criteria=criteria)
    reference = reference.reshape(-1, 2)
    np.testing.assert_allclose(ours, reference, rtol=0, atol=1e-12)


def test_undistort_inverts_distort(distorted_camera):
    cam = distorted_camera
    rng = np.random.default_rng(2)
    # Undistorted points whose images fall anywhere in the image, including its border.
    u = rng.uniform(-0.5, cam.width - 0.5, 50_000)
    v = rng.uniform(-0.5, cam.height - 0.5, 50_000)
    x, y = cam.undistort((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy)
    x, y = x + rng.normal(0, 1e-4, x.shape), y + rng.normal(0, 1e-4, y.shape)   # not the solver's own points
    x_back, y_back = cam.undistort(*cam.distort(x, y))
    assert np.abs(x_back - x).max() < 1e-10 and np.abs(y_back - y).max() < 1e-10


def test_distortion_jacobian_matches_finite_differences(distorted_camera):
    """The Jacobian drives Newton's method (quadratic convergence) and the invertibility check."""
    cam = distorted_camera
    rng = np.random.default_rng(7)
    x, y = rng.uniform(-0.7, 0.7, (2, 1000))
    h = 1e-6
    _, _, j_xx, j_xy, j_yy = cam._distort_with_jacobian(x, y)
    (xd_px, yd_px), (xd_mx, yd_mx) = cam.distort(x + h, y), cam.distort(x - h, y)
    (xd_py, yd_py), (xd_my, yd_my) = cam.distort(x, y + h), cam.distort(x, y - h)
    for analytic, numeric in [(j_xx, xd_px - xd_mx), (j_xy, yd_px - yd_mx), (j_xy, xd_py - xd_my),
                              (j_yy, yd_py - yd_my)]:
        np.testing.assert_allclose(analytic, numeric / (2 * h), rtol=0, atol=1e-8)


def test_without_distortion_undistort_is_the_identity():
    cam = Camera(**KINECT_LIKE)
    xd = np.linspace(-1, 1, 7)
    x, y = cam.undistort(xd, -xd)
    assert np.array_equal(x, xd) and np.array_equal(y, -xd)
    np.testing.assert_allclose(cam.project(np.array([[0.2, -0.1, 2.0]])), [[cam.fx * 0.1 + cam.cx,
                                                                           cam.fy * -0.05 + cam.cy]])


def test_project_gives_nan_behind_the_lens():
    uv = Camera(**KINECT_LIKE, k1=0.1).project(np.array([[0.1, 0.1, -1.0], [0.1, 0.1, 0.0], [0.0, 0.0, 1.0]]))
    assert np.isnan(uv[:2]).all() and np.allclose(uv[2], [KINECT_LIKE["cx"], KINECT_LIKE["cy"]])


# --- pixel centres, jitter, thin lens ---------------------------------------------------------------

def test_pixel_center_directions_are_cached_float32_unit_vectors(distorted_camera):
    cam = distorted_camera
    table = cam.pixel_center_directions()
    assert table.shape == (cam.height, cam.width, 3) and table.dtype == np.float32
    assert table is cam.pixel_center_directions() and not table.flags.writeable
    u, v = pixel_grid(cam)
    np.testing.assert_allclose(table.reshape(-1, 3), cam.ray_directions(u, v), rtol=0, atol=1e-7)


@pytest.mark.parametrize("distortion", ["none", "pincushion-then-barrel", "barrel+tangential"])
def test_jittered_samples_stay_in_their_pixel_and_spread_uniformly(distortion):
    cam = Camera(**KINECT_LIKE, **DISTORTIONS.get(distortion, {}))
    rng = np.random.default_rng(3)
    n = 2 * _RAY_BLOCK + 123                                    # several blocks, one partial
    pixel = rng.integers(0, cam.width * cam.height, n)
    u_jitter, v_jitter, u_lens, v_lens = rng.random((4, n))
    origins, directions = cam.generate_rays(pixel, u_jitter, v_jitter, u_lens, v_lens)
    assert origins.dtype == directions.dtype == np.float64 and not origins.any()
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, rtol=0, atol=1e-14)
    row, col = np.divmod(pixel, cam.width)
    u, v = cam.project(directions).T
    # Exactly where the jitter put them (to 1e-8 px), hence inside the pixel ...
    np.testing.assert_allclose(u, col - 0.5 + u_jitter, rtol=0, atol=1e-8)
    np.testing.assert_allclose(v, row - 0.5 + v_jitter, rtol=0, atol=1e-8)
    assert (np.abs(u - col) <= 0.5 + 1e-8).all() and (np.abs(v - row) <= 0.5 + 1e-8).all()
    # ... spread uniformly around the centre: mean 0, variance 1/12 per axis (5σ bounds).
    for offset in (u - col, v - row):
        assert abs(offset.mean()) < 5 * math.sqrt(1 / 12 / n)
        assert abs(offset.var() - 1 / 12) < 5 * math.sqrt(1 / 180 / n)
    np.testing.assert_allclose(directions, cam.ray_directions(col - 0.5 + u_jitter, row - 0.5 + v_jitter),
                               rtol=0, atol=1e-13)


def test_thin_lens_rays_of_one_pixel_position_meet_on_the_focus_plane():
    focus_m, radius_m = 1.7, 0.004
    cam = Camera(**KINECT_LIKE, **DISTORTIONS["barrel+tangential"], aperture_radius_m=radius_m,
                 focus_distance_m=focus_m)
    rng = np.random.default_rng(4)
    n = 5000
    pixel = np.full(n, 300 * cam.width + 17)                  # one pixel position near the left edge ...
    u_jitter, v_jitter = np.full(n, 0.25), np.full(n, 0.8)
    origins, directions = cam.generate_rays(pixel, u_jitter, v_jitter, *rng.random((2, n)))   # ... many lens points
    assert (origins[:, 2] == 0).all() and (np.hypot(origins[:, 0], origins[:, 1]) <= radius_m).all()
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, rtol=0, atol=1e-14)
    on_focus_plane = origins + directions * ((focus_m - origins[:, 2]) / directions[:, 2])[:, None]
    pinhole = cam.ray_directions(17 - 0.5 + 0.25, 300 - 0.5 + 0.8)
    np.testing.assert_allclose(on_focus_plane, np.broadcast_to(pinhole * focus_m / pinhole[2], (n, 3)),
                               rtol=0, atol=1e-12)


def test_thin_lens_focused_at_infinity_keeps_pinhole_directions_and_pinhole_ignores_lens_samples():
    rng = np.random.default_rng(5)
    pixel = rng.integers(0, 512 * 424, 1000)
    jitter = rng.random((2, 1000))
    _, pinhole = Camera(**KINECT_LIKE).generate_rays(pixel, *jitter, *rng.random((2, 1000)))
    origins, at_infinity = Camera(**KINECT_LIKE, aperture_radius_m=0.01).generate_rays(
        pixel, *jitter, *rng.random((2, 1000)))
    assert np.array_equal(at_infinity, pinhole) and origins[:, :2].any()


# --- field of view ----------------------------------------------------------------------------------

@pytest.mark.parametrize("hfov_deg, vfov_deg", [(70.0, 60.0), (60.0, None), (120.0, 20.0)])
def test_from_fov_spans_the_requested_field_of_view(hfov_deg, vfov_deg):
    cam = Camera.from_fov(512, 424, hfov_deg, vfov_deg)
    assert (cam.cx, cam.cy) == (255.5, 211.5)
    left, right = cam.ray_directions([-0.5, cam.width - 0.5], [cam.cy, cam.cy])
    assert math.degrees(math.acos(left @ right)) == pytest.approx(hfov_deg, abs=1e-9)
    top, bottom = cam.ray_directions([cam.cx, cam.cx], [-0.5, cam.height - 0.5])
    if vfov_deg is None:
        assert cam.fy == cam.fx
    else:
        assert math.degrees(math.acos(top @ bottom)) == pytest.approx(vfov_deg, abs=1e-9)


def test_from_fov_passes_the_other_fields_on():
    cam = Camera.from_fov(352, 264, 60.0, 45.0, k1=0.05, aperture_radius_m=0.001, focus_distance_m=2.0)
    assert (cam.k1, cam.aperture_radius_m, cam.focus_distance_m) == (0.05, 0.001, 2.0)


# --- validation -------------------------------------------------------------------------------------

@pytest.mark.parametrize("change, message", [
    (dict(fx=-3.0), r"Camera: fx must be > 0, got -3\.0"),
    (dict(fy=0), r"Camera: fy must be > 0, got 0\.0"),
    (dict(width=0), r"Camera: width must be a positive integer \(pixels\), got 0"),
    (dict(height=424.5), r"Camera: height must be a positive integer \(pixels\), got 424\.5"),
    (dict(k2=float("nan")), r"Camera: k2 must be finite, got nan"),
    (dict(cx=float("inf")), r"Camera: cx must be finite, got inf"),
    (dict(p1="0.1"), r"Camera: p1 must be a number, got '0\.1'"),
    (dict(aperture_radius_m=-0.001), r"Camera: aperture_radius_m must be >= 0, got -0\.001"),
    (dict(focus_distance_m=0.0), r"Camera: focus_distance_m must be > 0 \(inf allowed\), got 0\.0"),
])
def test_invalid_fields_raise_config_error_naming_field_and_value(change, message):
    with pytest.raises(ConfigError, match=message):
        Camera(**{**KINECT_LIKE, **change})


@pytest.mark.parametrize("distortion", [
    dict(k1=-0.8),              # barrel so strong that the image corners have no preimage at all
    dict(k1=-2.0, k3=3.0),      # folds over and back: three preimages for part of the image
    dict(p1=0.3),               # tangential term folding the image
])
def test_non_invertible_distortion_raises_config_error_naming_the_coefficients(distortion):
    coefficients = {"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "k3": 0.0, **distortion}
    message = ", ".join(f"{name}={value!r}" for name, value in coefficients.items())
    with pytest.raises(ConfigError, match=rf"Camera: distortion \({message}\) must be invertible over the 512x424"):
        Camera(**KINECT_LIKE, **distortion)


def test_invalid_field_of_view_raises_config_error():
    with pytest.raises(ConfigError, match=r"Camera: hfov_deg must be in \(0, 180\) degrees, got 180\.0"):
        Camera.from_fov(512, 424, 180.0)
    with pytest.raises(ConfigError, match=r"Camera: vfov_deg must be in \(0, 180\) degrees, got -5"):
        Camera.from_fov(512, 424, 70.0, -5)


def test_generate_rays_rejects_pixel_indices_outside_the_image():
    cam = Camera(**KINECT_LIKE)
    zeros = np.zeros(2)
    with pytest.raises(ValueError, match=r"pixel_index must be in \[0, 217088\), got values in \[-1, 3\]"):
        cam.generate_rays(np.array([-1, 3]), zeros, zeros, zeros, zeros)


def test_the_undistortion_table_built_in_blocks_equals_newton_over_the_whole_image():
    """The table is built in cache-sized blocks that take the same Newton steps as the whole image: bit for bit
    what :meth:`Camera._newton_undistort` gives over all pixel centres at once."""
    cam = Camera(width=97, height=211, fx=90.0, fy=88.0, cx=47.3, cy=104.6, k1=-0.3, k2=0.08, p1=0.01, p2=-0.01,
                 k3=0.002)  # 20,467 pixels: three blocks, the last one short
    xd, yd = cam._distorted_centres()
    x, y = cam._newton_undistort(xd, yd, xd, yd)
    _, _, j_xx, j_xy, j_yy = cam._distort_with_jacobian(x, y)
    inv_det = 1.0 / (j_xx * j_yy - j_xy * j_xy)
    whole = (x, y, j_yy * inv_det, -j_xy * inv_det, j_xx * inv_det)
    for built, expected in zip(cam._build_centre_table(), whole):
        np.testing.assert_array_equal(built.view(np.int64), expected.view(np.int64))


def test_equal_cameras_share_one_undistortion_table_and_check():
    """A batch worker builds its preset's sensor for every frame, a set's check builds it again for overrides:
    equal cameras are checked once per process and share the (read-only) table."""
    fields = dict(width=64, height=48, fx=60.0, fy=60.0, cx=31.5, cy=23.5, k1=0.11, k2=-0.07, p1=0.001)
    a, b = Camera(**fields), Camera(**fields)
    assert all(ta is tb for ta, tb in zip(a._centre_table, b._centre_table))
    assert not a._centre_table[0].flags.writeable
    other = Camera(**{**fields, "k1": 0.12})
    assert other._centre_table[0] is not a._centre_table[0]
    bad = dict(fields, k1=-2.0)
    for _ in range(2):  # the second refusal comes from the shared check, with the same message
        with pytest.raises(ConfigError, match=r"^Camera: distortion \(k1=-2.0, .* must be invertible over the 64x48"):
            Camera(**bad)
