"""Fresnel reflectance of a smooth interface, unpolarised (thesis §2.1.4).

Both functions take the cosine of the angle between the incident direction and
the interface normal and return the fraction of unpolarised power that is
reflected, in [0, 1]. Light always arrives from the outside medium, air with
η₁ = 1 (surfaces are opaque, so it never leaves a material). Arrays broadcast
against each other; the maths runs in float64 whatever the input dtype.

==============  ==========  ======  =============================================
name            type        unit    meaning
==============  ==========  ======  =============================================
cos_theta_i     array       1       cosine of the incidence angle, clipped to [0, 1]
eta             array       1       real refractive index of the material (> 0)
k               array       1       extinction (absorption) coefficient (≥ 0)
==============  ==========  ======  =============================================

Example
-------
>>> round(float(fresnel_dielectric(1.0, 1.52)), 4)
0.0426
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from ..backend import asarray
from ..backend import device_twin


@device_twin(on="cos_theta_i")
def fresnel_dielectric(cos_theta_i: ArrayLike, eta: ArrayLike) -> NDArray[np.float64]:
    r"""Unpolarised Fresnel reflectance of a dielectric seen from air.

    Parameters
    ----------
    cos_theta_i : array_like
        Cosine of the incidence angle θ₁ (unitless); values outside [0, 1]
        are clipped, so a direction below the surface counts as grazing.
    eta : array_like
        Refractive index η₂ of the material (unitless, > 0); the outside
        medium has η₁ = 1.

    Returns
    -------
    numpy.ndarray
        Reflectance F_r in [0, 1] (float64), broadcast shape of the inputs.

    Notes
    -----
    Snell's law gives the refracted cosine
    :math:`\cos\theta_2 = \sqrt{1 - \sin^2\theta_1 / \eta^2}`, then

    .. math::

        r_\parallel = \frac{\eta_2\cos\theta_1 - \eta_1\cos\theta_2}
                             {\eta_2\cos\theta_1 + \eta_1\cos\theta_2}
        \quad (2.19), \qquad
        r_\perp = \frac{\eta_1\cos\theta_1 - \eta_2\cos\theta_2}
                         {\eta_1\cos\theta_1 + \eta_2\cos\theta_2}
        \quad (2.20), \qquad
        F_r = \tfrac12 (r_\parallel^2 + r_\perp^2) \quad (2.21).

    Departure from the thesis: eq. 2.20 as printed repeats the denominator of
    eq. 2.19; that is a typo (it gives :math:`r_\perp^2 = \eta^2 > 1` at
    grazing incidence). The standard denominator
    :math:`\eta_1\cos\theta_1 + \eta_2\cos\theta_2` is used [PHJ16].
    Where sin²θ₂ ≥ 1 (total internal reflection for η < 1, and the grazing
    limit cos θ₁ = 0 for η = 1) the result is 1.
    """
    cos_1 = np.clip(asarray(cos_theta_i, dtype=np.float64), 0.0, 1.0)
    eta = asarray(eta, dtype=np.float64)
    sin2_2 = (1.0 - cos_1 * cos_1) / (eta * eta)
    total_internal = sin2_2 >= 1.0
    cos_2 = np.sqrt(np.maximum(1.0 - sin2_2, 0.0))
    # Both denominators vanish only under total internal reflection at grazing
    # incidence (cos_1 = cos_2 = 0), where the result is replaced by 1 below.
    with np.errstate(divide="ignore", invalid="ignore"):
        r_parallel = (eta * cos_1 - cos_2) / (eta * cos_1 + cos_2)
        r_perpendicular = (cos_1 - eta * cos_2) / (cos_1 + eta * cos_2)
    reflectance = 0.5 * (r_parallel * r_parallel + r_perpendicular * r_perpendicular)
    return np.where(total_internal, 1.0, reflectance)


@device_twin(on="cos_theta_i")
def fresnel_conductor(
    cos_theta_i: ArrayLike, eta: ArrayLike, k: ArrayLike
) -> NDArray[np.float64]:
    r"""Unpolarised Fresnel reflectance of a conductor seen from air.

    Parameters
    ----------
    cos_theta_i : array_like
        Cosine of the incidence angle θ_i (unitless), clipped to [0, 1].
    eta : array_like
        Real part η of the complex refractive index (unitless, ≥ 0).
    k : array_like
        Extinction (absorption) coefficient k (unitless, ≥ 0).

    Returns
    -------
    numpy.ndarray
        Reflectance F_r in [0, 1] (float64), broadcast shape of the inputs.

    Notes
    -----
    With :math:`c = \cos\theta_i`,

    .. math::

        r_\parallel^2 = \frac{(\eta^2 + k^2) c^2 - 2\eta c + 1}
                               {(\eta^2 + k^2) c^2 + 2\eta c + 1} \quad (2.22),
        \qquad
        r_\perp^2 = \frac{(\eta^2 + k^2) - 2\eta c + c^2}
                           {(\eta^2 + k^2) + 2\eta c + c^2} \quad (2.23),

    averaged by eq. 2.21, :math:`F_r = \tfrac12 (r_\parallel^2 + r_\perp^2)`.
    This is the usual approximation of the exact conductor Fresnel equations
    (pbrt-v2 ``FrCond``); it is exact at normal incidence,
    :math:`((\eta-1)^2 + k^2) / ((\eta+1)^2 + k^2)`, and at grazing
    incidence (F = 1), and both numerators are sums of squares
    (:math:`\ge (\eta c - 1)^2` and :math:`\ge (\eta - c)^2`), so F ∈ [0, 1].
    The only vanishing denominator is η = k = 0 at c = 0, whose limit 1 is used.
    """
    cos_i = np.clip(asarray(cos_theta_i, dtype=np.float64), 0.0, 1.0)
    eta = asarray(eta, dtype=np.float64)
    k = asarray(k, dtype=np.float64)
    eta2_k2 = eta * eta + k * k
    two_eta_cos = 2.0 * eta * cos_i
    cos2 = cos_i * cos_i
    r_parallel2 = (eta2_k2 * cos2 - two_eta_cos + 1.0) / (eta2_k2 * cos2 + two_eta_cos + 1.0)
    perpendicular_denominator = eta2_k2 + two_eta_cos + cos2
    with np.errstate(divide="ignore", invalid="ignore"):
        r_perpendicular2 = (eta2_k2 - two_eta_cos + cos2) / perpendicular_denominator
    r_perpendicular2 = np.where(perpendicular_denominator > 0.0, r_perpendicular2, 1.0)
    return 0.5 * (r_parallel2 + r_perpendicular2)
