"""Tests of tofcore.sensor.optics: J1, the PSF kernels, the reflecting convolution, and scattering's effect on depth.

Tolerances: kernel sums and charge conservation are float64 round-off (1e-12);
convolution paths agree with a direct sum to 1e-12 relative; J1 to its
published accuracy (1e-7); pixel-averaged taps against brute-force averages
to the midpoint rule's error (1e-6 relative).
"""

import math

import numpy as np
import pytest

from tofcore.errors import ConfigError
from tofcore.sensor.optics import (
    AIRY_FIRST_RING_PEAK, J1_ZERO_1, J1_ZERO_2, MAX_SIZE_PX, TAIL_FRACTION, _convolve_cv2, _convolve_fft, airy_profile,
    apply_scattering, bessel_j1, psf_kernel,
)

C_M_S = 299_792_458.0

KERNELS = {
    "airy-small": dict(model="airy", strength=0.05, radius_px=1.5, negative_lobe=0.03),
    "airy-wide": dict(model="airy", strength=0.2, radius_px=6.0, negative_lobe=0.1),
    "airy-plain": dict(model="airy", strength=0.1, radius_px=2.0, negative_lobe=-AIRY_FIRST_RING_PEAK),
    "airy-sized": dict(model="airy", strength=0.1, radius_px=2.0, negative_lobe=0.02, size_px=11),
    "gaussians-one": dict(model="gaussians", strength=0.3, sigmas_px=(0.7,)),
    "gaussians-mix": dict(model="gaussians", strength=0.1, sigmas_px=(0.5, 3.0, 12.0), weights=(5, 3, 2)),
}


def j1_reference(x: np.ndarray, n: int = 2000) -> np.ndarray:
    """J1(x) = (1/π) ∫_0^π cos(τ − x sin τ) dτ by the midpoint rule (spectrally accurate here)."""
    tau = (np.arange(n) + 0.5) * math.pi / n
    return np.cos(tau[None, :] - x[:, None] * np.sin(tau[None, :])).mean(axis=1)


def direct_convolution(image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """The naive reference: Σ_ij K(i, j) image(y − i, x − j) over a symmetric-reflected image, tap by tap."""
    hy, hx = kernel.shape[0] // 2, kernel.shape[1] // 2
    height, width = image.shape
    padded = np.pad(image, ((hy, hy), (hx, hx)), mode="symmetric")
    out = np.zeros_like(image)
    for i in range(kernel.shape[0]):
        for j in range(kernel.shape[1]):
            out += kernel[i, j] * padded[2 * hy - i:2 * hy - i + height, 2 * hx - j:2 * hx - j + width]
    return out


# 1. J1 and the Airy profile

def test_bessel_j1_matches_its_integral_representation():
    x = np.concatenate([np.linspace(-10.0, 10.0, 2001), np.linspace(10.0, 300.0, 5801)])
    np.testing.assert_allclose(bessel_j1(x), j1_reference(x), rtol=0, atol=1e-7)
    np.testing.assert_allclose(bessel_j1(np.array([J1_ZERO_1, J1_ZERO_2])), 0.0, atol=1e-7)


def test_airy_profile_dark_ring_and_negative_ring_depth():
    r0 = 4.0
    assert airy_profile(np.array(0.0), radius_px=r0, negative_lobe=0.07) == 1.0
    assert abs(airy_profile(np.array(r0), radius_px=r0, negative_lobe=0.07)) < 1e-12
    r = np.linspace(r0, r0 * J1_ZERO_2 / J1_ZERO_1, 20001)  # from the first to the second dark ring
    for lobe in (0.07, -AIRY_FIRST_RING_PEAK):  # a negative ring; the plain Airy pattern's bright ring
        ring = airy_profile(r, radius_px=r0, negative_lobe=lobe)
        extreme = np.argmax(np.abs(ring))
        assert ring[extreme] == pytest.approx(-lobe, rel=1e-6)
        assert r[extreme] == pytest.approx(1.3403 * r0, rel=1e-3)  # x = 5.1356, the first zero of J2
    np.testing.assert_array_equal(airy_profile(r[1:-1], radius_px=r0, negative_lobe=0.0), 0.0)


# 2. Kernels

@pytest.mark.parametrize("params", KERNELS.values(), ids=KERNELS.keys())
def test_kernel_sums_to_one_is_odd_symmetric_float64(params):
    kernel = psf_kernel(**params)
    assert kernel.dtype == np.float64 and kernel.ndim == 2
    assert kernel.shape[0] == kernel.shape[1] and kernel.shape[0] % 2 == 1
    assert abs(kernel.sum() - 1.0) < 1e-12
    for mirrored in (kernel[::-1, :], kernel[:, ::-1], kernel.T):
        np.testing.assert_array_equal(kernel, mirrored)


@pytest.mark.parametrize("params", [dict(model="none", strength=0.0), dict(model="none", strength=0.5),
                                    dict(model="airy", strength=0.0, radius_px=2.0, negative_lobe=0.1),
                                    dict(model="gaussians", strength=0.0, sigmas_px=(2.0,))])
def test_identity_for_none_or_zero_strength(params):
    np.testing.assert_array_equal(psf_kernel(**params), [[1.0]])
    delta = psf_kernel(**params, size_px=5)
    assert delta.shape == (5, 5) and delta[2, 2] == 1.0 and delta.sum() == 1.0


def test_airy_kernel_has_a_negative_ring_where_requested():
    strength, r0, lobe = 0.2, 6.0, 0.05
    kernel = psf_kernel("airy", strength=strength, radius_px=r0, negative_lobe=lobe)
    centre = kernel.shape[0] // 2
    scattered = kernel.copy()
    scattered[centre, centre] -= 1.0 - strength
    y, x = np.indices(kernel.shape) - centre
    r = np.hypot(x, y)
    ring = (r > 1.1 * r0) & (r < 1.6 * r0)
    assert kernel[ring].max() < 0.0
    assert kernel[r < 0.9 * r0].min() > 0.0
    # Pixel averaging flattens the continuous extreme −lobe a little: within 5 % at 6 px.
    assert scattered.min() / scattered[centre, centre] == pytest.approx(-lobe, rel=0.05)
    assert r[np.unravel_index(np.argmin(kernel), kernel.shape)] == pytest.approx(1.34 * r0, abs=1.0)
    for no_negative in (0.0, -AIRY_FIRST_RING_PEAK):
        assert psf_kernel("airy", strength=strength, radius_px=r0, negative_lobe=no_negative).min() >= 0.0


@pytest.mark.parametrize("r0", [0.7, 1.5, 4.0])
def test_airy_taps_are_pixel_averages_of_the_profile(r0):
    lobe = 0.04
    kernel = psf_kernel("airy", strength=1.0, radius_px=r0, negative_lobe=lobe, size_px=9)
    sub = (np.arange(301) + 0.5) / 301 - 0.5
    pos = (np.arange(-4, 5)[:, None] + sub[None, :]).ravel()
    profile = airy_profile(np.hypot(pos[:, None], pos[None, :]), radius_px=r0, negative_lobe=lobe)
    reference = profile.reshape(9, 301, 9, 301).mean(axis=(1, 3))
    reference /= reference.sum()
    # The kernel's coarse midpoint rule (SUBSAMPLES_PER_RADIUS) promises taps to ~1e-3 of the largest.
    np.testing.assert_allclose(kernel, reference, rtol=0, atol=1.5e-3 * reference.max())


def test_gaussians_kernel_equals_directly_computed_mixture():
    sigmas, weights, strength = (0.6, 2.5), (1.0, 3.0), 0.4
    kernel = psf_kernel("gaussians", strength=strength, sigmas_px=sigmas, weights=weights)
    half = kernel.shape[0] // 2
    assert half == math.ceil(math.sqrt(2 * math.log(1 / TAIL_FRACTION)) * max(sigmas))
    sub = (np.arange(201) + 0.5) / 201 - 0.5
    pos = (np.arange(-half, half + 1)[:, None] + sub[None, :]).ravel()
    mixture = np.zeros(kernel.shape)
    for sigma, w in zip(sigmas, weights):
        g = np.exp(-0.5 * (pos / sigma) ** 2)
        g2 = np.outer(g, g).reshape(2 * half + 1, 201, 2 * half + 1, 201).mean(axis=(1, 3))
        mixture += w / sum(weights) * g2 / g2.sum()
    expected = strength * mixture
    expected[half, half] += 1.0 - strength
    # Exact pixel integrals (erf) against a 201 × 201 midpoint rule: error ~(1/201)²/24 of the curvature.
    np.testing.assert_allclose(kernel, expected, rtol=0, atol=1e-6)


def test_automatic_size_holds_the_tail_and_is_capped():
    r0 = 2.0
    kernel = psf_kernel("airy", strength=1.0, radius_px=r0)
    half = kernel.shape[0] // 2
    assert half == math.ceil(r0 * (8 / (math.pi * TAIL_FRACTION)) ** (1 / 3) / J1_ZERO_1)
    envelope = 8 / (math.pi * (J1_ZERO_1 * half / r0) ** 3)
    assert envelope <= TAIL_FRACTION
    assert psf_kernel("airy", strength=0.1, radius_px=200.0).shape == (MAX_SIZE_PX, MAX_SIZE_PX)
    assert psf_kernel("gaussians", strength=0.1, sigmas_px=(500.0,)).shape == (MAX_SIZE_PX, MAX_SIZE_PX)
    assert psf_kernel("gaussians", strength=0.1, sigmas_px=(0.1,)).shape == (3, 3)


@pytest.mark.parametrize("params, match", [
    (dict(model="airy", strength=-0.1, radius_px=2.0), "strength must be a number in \\[0, 1\\], got -0.1"),
    (dict(model="airy", strength=1.5, radius_px=2.0), "strength .* got 1.5"),
    (dict(model="lorentz", strength=0.1), "model must be one of \\['none', 'airy', 'gaussians'\\], got 'lorentz'"),
    (dict(model="airy", strength=0.1), "radius_px must be .* got 0.0"),
    (dict(model="airy", strength=0.1, radius_px=2.0, negative_lobe=float("nan")), "negative_lobe .* got nan"),
    (dict(model="airy", strength=0.1, radius_px=2.0, negative_lobe=0.5), "negative_lobe must leave .* got 0.5"),
    (dict(model="gaussians", strength=0.1), "sigmas_px must be .* got \\(\\)"),
    (dict(model="gaussians", strength=0.1, sigmas_px=(1.0, -2.0)), "sigmas_px .* got \\(1.0, -2.0\\)"),
    (dict(model="gaussians", strength=0.1, sigmas_px=(1.0, 2.0), weights=(1.0,)),
     "weights must be empty or 2 .* got \\(1.0,\\)"),
    (dict(model="gaussians", strength=0.1, sigmas_px=(1.0,), weights=(0.0,)), "weights .* got \\(0.0,\\)"),
    (dict(model="gaussians", strength=0.1, sigmas_px=(1.0,), size_px=4), "size_px must be .* got 4"),
])
def test_bad_parameters_raise_config_error_naming_them(params, match):
    with pytest.raises(ConfigError, match=f"psf_kernel: {match}"):
        psf_kernel(**params)


def test_parameters_of_the_other_model_are_ignored():
    a = psf_kernel("gaussians", strength=0.2, sigmas_px=(1.0,))
    b = psf_kernel("gaussians", strength=0.2, sigmas_px=(1.0,), radius_px=3.0, negative_lobe=0.1)
    np.testing.assert_array_equal(a, b)


# 3. Convolution

CONVOLUTION_CASES = [((5, 7), 3), ((5, 7), 9), ((6, 4), 21), ((3, 3), 31), ((1, 6), 5), ((40, 33), 15)]


@pytest.mark.parametrize("shape, size", CONVOLUTION_CASES)
def test_convolution_paths_match_the_direct_sum_for_any_sizes(shape, size):
    rng = np.random.default_rng(size)
    images = rng.random((2, *shape)) * 1e3
    kernel = rng.random((size, size + 2)) - 0.2  # asymmetric, non-square, with negative taps
    expected = np.stack([direct_convolution(image, kernel) for image in images])
    paths = [_convolve_fft] + ([_convolve_cv2] if _has_cv2() else [])
    for convolve in paths:
        np.testing.assert_allclose(convolve(images, kernel), expected, rtol=1e-12, atol=1e-12 * 1e3 * size)
    np.testing.assert_allclose(apply_scattering(images, kernel), expected, rtol=1e-12, atol=1e-12 * 1e3 * size)


def _has_cv2() -> bool:
    """Whether tofcore.sensor.optics uses OpenCV here (installed, and this process has no Blender loaded)."""
    from tofcore.sensor import optics
    return optics.cv2 is not None


@pytest.mark.parametrize("params", KERNELS.values(), ids=KERNELS.keys())
@pytest.mark.parametrize("shape", [(3, 48, 40), (2, 7, 5)], ids=["larger-than-kernel", "smaller-than-kernel"])
def test_reflecting_edges_conserve_total_charge(params, shape):
    raw = np.random.default_rng(7).random(shape) * 1e4
    out = apply_scattering(raw, psf_kernel(**params))
    np.testing.assert_allclose(out.sum(axis=(1, 2)), raw.sum(axis=(1, 2)), rtol=1e-12)


def test_uniform_image_stays_uniform_and_shapes_are_kept():
    kernel = psf_kernel("airy", strength=0.3, radius_px=2.0, negative_lobe=0.05)
    np.testing.assert_allclose(apply_scattering(np.full((10, 12), 250.0), kernel), 250.0, rtol=1e-12)
    raw = np.random.default_rng(1).random((2, 3, 10, 12))
    assert apply_scattering(raw, kernel).shape == raw.shape
    np.testing.assert_array_equal(apply_scattering(raw, psf_kernel("none", strength=0.0)), raw)


def test_bad_kernel_or_raw_raise_config_error():
    with pytest.raises(ConfigError, match="apply_scattering: kernel must be .* got shape \\(4, 3\\)"):
        apply_scattering(np.ones((5, 5)), np.ones((4, 3)))
    with pytest.raises(ConfigError, match="apply_scattering: raw must have shape .* got \\(5,\\)"):
        apply_scattering(np.ones(5), np.ones((3, 3)))


# 4. Scattering's effect on depth: a bright near plane beside a dark far plane (§4.0.6, Fig. 4.16)

F_HZ = 20e6            # d_amb = 7.5 m: both planes unambiguous
HEIGHT, WIDTH, BOUNDARY = 32, 96, 48


def two_plane_raw(signal_near: float = 1e5, signal_far: float = 1e3) -> tuple[np.ndarray, np.ndarray]:
    """4-bucket sine raw_k = S (1 + cos(φ − k π/2)) / 2, φ = 4π f d / c; near (1 m) left, far (3 m) right."""
    near = np.arange(WIDTH) < BOUNDARY
    distance = np.broadcast_to(np.where(near, 1.0, 3.0), (HEIGHT, WIDTH))
    signal = np.broadcast_to(np.where(near, signal_near, signal_far), (HEIGHT, WIDTH))
    phi = 4 * math.pi * F_HZ * distance / C_M_S
    return np.stack([signal * (1 + np.cos(phi - k * math.pi / 2)) / 2 for k in range(4)]), distance


def decode_distance(raw: np.ndarray) -> np.ndarray:
    phi = np.mod(np.arctan2(raw[1] - raw[3], raw[0] - raw[2]), 2 * math.pi)
    return C_M_S * phi / (4 * math.pi * F_HZ)


def test_unscattered_scene_decodes_exactly():
    raw, distance = two_plane_raw()
    np.testing.assert_allclose(decode_distance(raw), distance, atol=1e-9)


def test_scattering_pulls_the_dark_far_plane_towards_the_bright_near_plane():
    raw, distance = two_plane_raw()
    kernel = psf_kernel("gaussians", strength=0.1, sigmas_px=(2.0,))
    half = kernel.shape[0] // 2
    decoded = decode_distance(apply_scattering(raw, kernel))
    far_error = decoded[:, BOUNDARY:] - distance[:, BOUNDARY:]
    np.testing.assert_allclose(far_error, np.broadcast_to(far_error[:1], far_error.shape), atol=1e-12)  # rows alike
    pull = -far_error[HEIGHT // 2]
    reached = pull[:half]  # far columns within the kernel's reach of a near column
    assert np.all(reached > 0) and np.all(decoded[:, BOUNDARY:BOUNDARY + half] > 1.0)
    assert np.all(np.diff(reached) < 0), f"pull must fall with distance from the boundary: {reached}"
    assert reached[0] > 1.0  # at the boundary the far pixel is a flying pixel far in front of its plane
    np.testing.assert_allclose(pull[half:], 0.0, atol=1e-9)  # beyond the kernel: untouched
    near_error = np.abs(decoded[:, :BOUNDARY] - 1.0)
    assert near_error.max() < 1e-3 * reached[0]  # the bright plane hardly notices the dark one


def test_negative_ring_pushes_pixels_at_its_radius_away_from_the_near_plane():
    raw, distance = two_plane_raw()
    kernel = psf_kernel("airy", strength=0.05, radius_px=3.0, negative_lobe=0.1)
    error = (decode_distance(apply_scattering(raw, kernel)) - distance)[HEIGHT // 2, BOUNDARY:]
    assert error[0] < -0.5  # the boundary pixel is pulled forward by the central disc
    assert np.all(error[1:4] > 0.3)  # the negative ring subtracts near light: pushed behind the far plane
    plain = psf_kernel("airy", strength=0.05, radius_px=3.0, negative_lobe=0.0)
    plain_error = (decode_distance(apply_scattering(raw, plain)) - distance)[HEIGHT // 2, BOUNDARY:]
    assert np.all(plain_error[:kernel.shape[0] // 2] < 0)  # without the ring: pulled forward everywhere


def test_a_render_makes_the_scattering_kernel_once_per_table_read_only():
    """render.frame_setup takes the kernel of a sensor's scattering table from a cache (it cost 1.6 ms a frame):
    the same array for an equal table, psf_kernel's values, and read-only, so no caller can change it for
    the next frame."""
    import importlib

    from tofcore import load_preset

    render_module = importlib.import_module("tofcore.render")
    table = load_preset("kinect_v2").scattering
    kernel = render_module.scattering_kernel(table)
    assert render_module.scattering_kernel(load_preset("kinect_v2").scattering) is kernel
    assert not kernel.flags.writeable
    np.testing.assert_array_equal(kernel, psf_kernel(table.model, strength=table.strength, radius_px=table.radius_px,
                                                     negative_lobe=table.negative_lobe))
