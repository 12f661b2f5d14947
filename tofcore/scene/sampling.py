"""Warps from uniform random numbers to disks, directions and microfacet normals.

Every ``sample_*`` function is paired with a ``pdf_*`` function that returns the
density of exactly what it produces, so an estimator can divide by it and a test
can check the pair (the pdf integrates to one, the histogram of samples follows
the pdf). All warps are vectorised: the uniforms are (N,) arrays in [0, 1),
directions are (N, 3) unit vectors in the local shading frame (z = normal).
Inputs may be float32; the maths runs in float64.

=====================================  ==========================================
pair                                   density
=====================================  ==========================================
``sample_concentric_disk``             1/π per unit area on the unit disk
``sample_cosine_hemisphere``           cos θ / π per steradian
``sample_beckmann_normal``             D(m) cos θ_m per steradian (eq. 2.26)
``sample_vcavity_visible_normal``      G₁(ω_o, m) (ω_o·m) D(m) / cos θ_o per sr
=====================================  ==========================================

The Beckmann distribution D itself (`beckmann_distribution`) lives here because
it is what the microfacet warps sample; `tofcore.scene.bsdf` evaluates it from here.

Example
-------
>>> import numpy as np
>>> u1, u2 = np.random.default_rng(0).random((2, 4))
>>> wi = sample_cosine_hemisphere(u1, u2)
>>> pdf = pdf_cosine_hemisphere(wi[:, 2])
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from ..backend import asarray

FloatArray = NDArray[np.float64]


def _as_float64(values: ArrayLike) -> FloatArray:
    return asarray(values, dtype=np.float64)


def sample_concentric_disk(u1: ArrayLike, u2: ArrayLike) -> tuple[FloatArray, FloatArray]:
    r"""Map the unit square to the unit disk, uniformly by area (Shirley–Chiu).

    Parameters
    ----------
    u1, u2 : array_like
        Uniform random numbers in [0, 1) (unitless).

    Returns
    -------
    x, y : numpy.ndarray
        Points on the unit disk (unitless; scale by the aperture radius in
        metres for lens sampling).

    Notes
    -----
    With :math:`a = 2u_1 - 1`, :math:`b = 2u_2 - 1`: if :math:`|a| > |b|`,
    :math:`r = a`, :math:`\phi = \frac{\pi}{4}\frac{b}{a}`; otherwise
    :math:`r = b`, :math:`\phi = \frac{\pi}{2} - \frac{\pi}{4}\frac{a}{b}`;
    :math:`(x, y) = r(\cos\phi, \sin\phi)`. The map preserves area up to the
    factor π/4, so the density is 1/π (`pdf_concentric_disk`), and it keeps
    strata compact, which a polar map does not.
    """
    a = 2.0 * _as_float64(u1) - 1.0
    b = 2.0 * _as_float64(u2) - 1.0
    a_dominant = np.abs(a) > np.abs(b)
    radius = np.where(a_dominant, a, b)
    # radius == 0 only at the disk centre, where the angle does not matter.
    safe_radius = np.where(radius == 0.0, 1.0, radius)
    phi = np.where(
        a_dominant, 0.25 * np.pi * b / safe_radius, 0.5 * np.pi - 0.25 * np.pi * a / safe_radius
    )
    return radius * np.cos(phi), radius * np.sin(phi)


def pdf_concentric_disk(x: ArrayLike, y: ArrayLike) -> FloatArray:
    """Area density of `sample_concentric_disk`: 1/π inside the unit disk, else 0.

    Parameters
    ----------
    x, y : array_like
        Point coordinates (unitless).

    Returns
    -------
    numpy.ndarray
        Density per unit area (1/unit²).
    """
    x = _as_float64(x)
    y = _as_float64(y)
    return np.where(x * x + y * y <= 1.0, 1.0 / np.pi, 0.0)


def sample_cosine_hemisphere(u1: ArrayLike, u2: ArrayLike) -> FloatArray:
    r"""Cosine-weighted directions on the upper hemisphere (Malley's method).

    Parameters
    ----------
    u1, u2 : array_like
        Uniform random numbers in [0, 1) (unitless).

    Returns
    -------
    numpy.ndarray
        (N, 3) unit vectors with z ≥ 0.

    Notes
    -----
    A uniform point :math:`(x, y)` on the disk is lifted to
    :math:`z = \sqrt{1 - x^2 - y^2}`; the density is
    :math:`p(\omega) = \cos\theta / \pi` (`pdf_cosine_hemisphere`).
    """
    x, y = sample_concentric_disk(u1, u2)
    z = np.sqrt(np.maximum(1.0 - x * x - y * y, 0.0))
    return np.stack([x, y, z], axis=-1)


def pdf_cosine_hemisphere(cos_theta: ArrayLike) -> FloatArray:
    """Solid-angle density of `sample_cosine_hemisphere`.

    Parameters
    ----------
    cos_theta : array_like
        Cosine of the angle to the normal (unitless).

    Returns
    -------
    numpy.ndarray
        max(cos θ, 0) / π (1/sr).
    """
    return np.maximum(_as_float64(cos_theta), 0.0) / np.pi


def sample_beckmann_normal(alpha: ArrayLike, u1: ArrayLike, u2: ArrayLike) -> FloatArray:
    r"""Microfacet normals distributed as D(m) cos θ_m for the Beckmann D.

    Parameters
    ----------
    alpha : array_like
        Beckmann roughness α = √2 σ (unitless, > 0; σ in radians).
    u1, u2 : array_like
        Uniform random numbers in [0, 1) (unitless).

    Returns
    -------
    numpy.ndarray
        (N, 3) unit normals with z > 0.

    Notes
    -----
    The Beckmann distribution (eq. 2.26) projected onto the macro surface has
    the marginal :math:`\tan^2\theta_m = -\alpha^2 \ln(1 - u_1)` and a uniform
    azimuth :math:`\phi_m = 2\pi u_2`; the density is
    :math:`D(m)\cos\theta_m` (`pdf_beckmann_normal`).
    """
    alpha = _as_float64(alpha)
    tan2_theta = -alpha * alpha * np.log1p(-_as_float64(u1))
    cos_theta = 1.0 / np.sqrt(1.0 + tan2_theta)
    sin_theta = np.sqrt(tan2_theta) * cos_theta
    phi = 2.0 * np.pi * _as_float64(u2)
    return np.stack([sin_theta * np.cos(phi), sin_theta * np.sin(phi), cos_theta], axis=-1)


def beckmann_distribution(cos_theta_m: ArrayLike, alpha: ArrayLike) -> FloatArray:
    r"""Beckmann microfacet distribution D (eq. 2.26).

    Parameters
    ----------
    cos_theta_m : array_like
        Cosine of the angle between the microfacet normal and the macro normal
        (unitless).
    alpha : array_like
        Beckmann roughness α = √2 σ (unitless, > 0; σ in radians).

    Returns
    -------
    numpy.ndarray
        D (1/sr); 0 where cos θ_m ≤ 10⁻¹², and 0 where α ≤ 10⁻⁵⁰ (a mirror,
        whose D is a Dirac delta that callers treat separately).

    Notes
    -----
    .. math::

        D(\omega_h) = \frac{\exp(-\tan^2\theta_h / \alpha^2)}
                           {\pi\alpha^2\cos^4\theta_h},
        \qquad \alpha = \sqrt{2}\,\sigma \quad (2.26)

    normalised as :math:`\int D(m)\cos\theta_m\,\mathrm{d}\omega_m = 1`.
    Below cos θ_m = 10⁻¹² the exponential is exactly 0 in float64 for every
    α < 10¹⁰, so returning 0 there changes nothing; together with α > 10⁻⁵⁰ it
    keeps every intermediate finite (no 0/0 from an underflowing denominator).
    """
    cos_theta = _as_float64(cos_theta_m)
    alpha = _as_float64(alpha)
    valid = (cos_theta > 1e-12) & (alpha > 1e-50)
    cos2 = np.where(valid, cos_theta * cos_theta, 1.0)
    alpha2 = np.where(valid, alpha * alpha, 1.0)
    tan2_theta = (1.0 - cos2) / cos2
    density = np.exp(-tan2_theta / alpha2) / (np.pi * alpha2 * cos2 * cos2)
    return np.where(valid, density, 0.0)


def pdf_beckmann_normal(m: ArrayLike, alpha: ArrayLike) -> FloatArray:
    """Solid-angle density of `sample_beckmann_normal`.

    Parameters
    ----------
    m : array_like
        (N, 3) unit microfacet normals.
    alpha : array_like
        Beckmann roughness α (unitless, > 0).

    Returns
    -------
    numpy.ndarray
        D(m) cos θ_m (1/sr), see `beckmann_distribution`.
    """
    cos_theta = _as_float64(m)[..., 2]
    return beckmann_distribution(cos_theta, alpha) * np.maximum(cos_theta, 0.0)


def _mirror_azimuth(m: FloatArray) -> FloatArray:
    """The other facet of m's V-cavity: (−m_x, −m_y, m_z)."""
    return np.stack([-m[..., 0], -m[..., 1], m[..., 2]], axis=-1)


def sample_vcavity_visible_normal(
    wo: ArrayLike, alpha: ArrayLike, u1: ArrayLike, u2: ArrayLike, u_swap: ArrayLike
) -> FloatArray:
    r"""Microfacet normals visible from ω_o in the V-cavity model (Beckmann D).

    Parameters
    ----------
    wo : array_like
        (N, 3) unit direction towards the viewer, local frame.
    alpha : array_like
        Beckmann roughness α (unitless, > 0).
    u1, u2, u_swap : array_like
        Uniform random numbers in [0, 1) (unitless).

    Returns
    -------
    numpy.ndarray
        (N, 3) unit normals with z > 0 and, if cos θ_o > 0, ω_o·m > 0.

    Notes
    -----
    Heitz & d'Eon 2014 (§5): draw m from :math:`D(m)\cos\theta_m`, form the
    other facet of its V-cavity :math:`m' = (-m_x, -m_y, m_z)` and keep m with
    probability :math:`\langle\omega_o, m\rangle / (\langle\omega_o, m\rangle +
    \langle\omega_o, m'\rangle)` (⟨·,·⟩ clamped at 0), else take m'. The
    result has the density of visible normals of the V-cavity model,

    .. math::

        D_{\omega_o}(m) = \frac{G_1(\omega_o, m)\,\langle\omega_o, m\rangle
                                D(m)}{\cos\theta_o},
        \qquad G_1(\omega_o, m) = \min\left(1,
            \frac{2\cos\theta_m\cos\theta_o}{\omega_o\cdot m}\right),

    whose G₁ is the masking half of the V-cavity G of eq. 2.27. Sampling it
    makes the specular weight F G / G₁(ω_o) ≤ 1.
    """
    wo = _as_float64(wo)
    m = sample_beckmann_normal(alpha, u1, u2)
    m_other = _mirror_azimuth(m)
    visible = np.maximum(np.sum(wo * m, axis=-1), 0.0)
    visible_other = np.maximum(np.sum(wo * m_other, axis=-1), 0.0)
    swap = _as_float64(u_swap) * (visible + visible_other) >= visible
    swap &= visible_other > 0.0
    return np.where(swap[..., None], m_other, m)


def pdf_vcavity_visible_normal(wo: ArrayLike, m: ArrayLike, alpha: ArrayLike,
                               distribution: ArrayLike | None = None) -> FloatArray:
    r"""Solid-angle density of `sample_vcavity_visible_normal`.

    Parameters
    ----------
    wo : array_like
        (N, 3) unit direction towards the viewer, local frame.
    m : array_like
        (N, 3) unit microfacet normals.
    alpha : array_like
        Beckmann roughness α (unitless, > 0).
    distribution : array_like, optional
        D(m) = `beckmann_distribution` (m_z, α) where the caller has it already (1/sr).

    Returns
    -------
    numpy.ndarray
        Density per steradian of m (1/sr); 0 where ω_o·m ≤ 0.

    Notes
    -----
    m and m' have the same Beckmann density :math:`p_0`, and m results either
    from drawing m and keeping it or from drawing m' and swapping, so

    .. math::

        p(m) = \frac{2\,p_0(m)\,\langle\omega_o, m\rangle}
                    {\langle\omega_o, m\rangle + \langle\omega_o, m'\rangle},

    which equals :math:`G_1(\omega_o, m)\langle\omega_o, m\rangle D(m) /
    \cos\theta_o` because :math:`\omega_o\cdot m + \omega_o\cdot m' =
    2\cos\theta_o\cos\theta_m`.
    """
    wo = _as_float64(wo)
    m = _as_float64(m)
    visible = np.maximum(np.sum(wo * m, axis=-1), 0.0)
    visible_other = np.maximum(np.sum(wo * _mirror_azimuth(m), axis=-1), 0.0)
    total = visible + visible_other
    share = visible / np.where(total > 0.0, total, 1.0)
    if distribution is None:
        normal_density = pdf_beckmann_normal(m, alpha)
    else:
        normal_density = _as_float64(distribution) * np.maximum(m[..., 2], 0.0)
    return 2.0 * normal_density * share
