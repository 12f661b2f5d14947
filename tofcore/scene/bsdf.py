r"""Surface reflection: Oren–Nayar diffuse plus Torrance–Sparrow specular (§2.1.4).

The contract
------------
All functions work on N surface points at once, in the **local shading frame**
(z = shading normal). Directions are (N, 3) unit vectors pointing **away** from
the surface: ``wo`` towards the viewer / previous path vertex, ``wi`` towards
the light / next vertex. Parameters are a `SurfaceParams` of (N,) arrays.

* ``eval_bsdf(params, wo, wi)`` returns the BRDF value f_r (1/sr) **without**
  the cosine factor; 0 where either direction is at or below the surface.
  Delta (mirror) lobes are not included: their f_r is a Dirac delta.
* ``pdf_bsdf(params, wo, wi)`` returns the solid-angle density (1/sr) with which
  ``sample_bsdf`` produces ``wi`` through its non-delta lobes (the full
  one-sample-MIS mixture over lobes). Over the upper hemisphere it integrates
  to 1 minus the probability of a mirror sample and of a microfacet reflection
  that lands below the horizon (returned with weight 0).
* ``eval_pdf_bsdf(params, wo, wi)`` returns both at once, computing the half
  vector, D(ω_h), the Fresnel terms of cos θ_o and the lobe probability once
  (what MIS and `sample_bsdf` need); bit for bit the same as the two calls.
* ``sample_bsdf(params, wo, u_lobe, u1, u2)`` returns a `BsdfSample`: the new
  direction ``wi``, the ``weight`` f_r cos θ_i / pdf (0 for an invalid sample:
  ``wo`` or ``wi`` at or below the surface), the ``pdf`` and an ``is_delta``
  flag. For non-delta samples weight = eval·cos θ_i / pdf_bsdf exactly. For
  delta samples ``pdf`` is the discrete probability of having picked the
  mirror lobe and ``weight`` = F(cos θ_o) / pdf; such a pdf must not enter a
  multiple-importance-sampling weight.

Nothing here loops over points: every branch is a mask (``np.where``), and every
division is guarded, so no NaN or inf leaves this module for any unit input,
including grazing angles, ``wo`` on the normal and directions below the surface.

The model
---------
With metallic mask m, dielectric Fresnel F_d(·; η) (eq. 2.19–2.21) and
conductor Fresnel F_c(·; η, k) (eq. 2.22–2.23),

.. math::

    f_r = (1 - m)\,(1 - F_d(\cos\theta_i))(1 - F_d(\cos\theta_o))\,
          f_{ON}(\rho, \sigma)
          + f_{TS}\big((1 - m) F_d(\omega_i\cdot\omega_h)
                       + m\,F_c(\omega_i\cdot\omega_h)\big),

f_ON Oren–Nayar (eq. 2.28–2.30), f_TS Torrance–Sparrow (eq. 2.24) with the
Beckmann D (eq. 2.26, α = √2 σ) and the V-cavity G (eq. 2.27); metals have no
diffuse part. Below σ = `SMOOTH_ROUGHNESS_RAD` the specular lobe is a perfect
mirror (a delta lobe, eq. 2.17) with reflectance F(cos θ_o).

Clear coat (Blender's Principled BSDF "Coat"; not in the thesis). A coat of weight c ∈ [0, 1] and
roughness σ_c is a dielectric interface of η_c = `COAT_IOR` over the model above (the base f_base):

.. math::

    f_r = c\,f_{TS}\big(F_d(\omega_i\cdot\omega_h; \eta_c);\ \alpha_c = \sqrt2\,\sigma_c\big)
          + \big(1 - c F_d(\cos\theta_i; \eta_c)\big)\big(1 - c F_d(\cos\theta_o; \eta_c)\big) f_{base}

light is reflected by the coat or transmitted through it twice (no refraction of the direction, no
absorption, no reflections between the layers: the common single-scattering layer model). Symmetric
in ω_i and ω_o, so reciprocal; the base's albedo is scaled by at most (1 − c F_c(θ_o)) where the coat
takes c F_c(θ_o), so the albedo stays ≤ 1 (white furnace, tests). A smooth coat (σ_c below
`SMOOTH_ROUGHNESS_RAD`) is a second mirror lobe. With c = 0 every value is the base's, bit for bit.

Departures from the thesis
~~~~~~~~~~~~~~~~~~~~~~~~~~
* **Diffuse Fresnel weight.** The thesis code (§5.1.2) weights the diffuse
  term by 1 − F(ω_i·ω_h). Here it is weighted by
  (1 − F(cos θ_i))(1 − F(cos θ_o)): light enters the body through the surface
  (transmitted fraction 1 − F(θ_i)) and leaves it again (1 − F(θ_o)). The
  product is symmetric in ω_i and ω_o, so f_r stays reciprocal (eq. 2.13), and
  the diffuse albedo seen from ω_o is at most (1 − F(θ_o)) times the Oren–Nayar
  albedo, so it shrinks exactly where the specular lobe takes the energy
  F(θ_o). With the half-vector weight a grazing viewer gets a near-mirror lobe
  *and* an almost undiminished diffuse lobe: for ρ = 1, σ = 0.1, η = 1.52 the
  albedo would be 1.11 at θ_o = 70°, 1.36 at 85° and 1.61 at 89.9°.
* **Oren–Nayar clamped at 0.** Eq. 2.28 goes negative for σ ≳ 1 rad when both
  directions are near grazing on opposite sides (cos(φ_o − φ_i) < 0, β → 90°),
  breaking eq. 2.11; the sum 2.30 is clamped at 0.
* **Energy.** Measured with ρ = 1 (white furnace, ``tests/tofcore/test_bsdf.py``)
  the albedo stays ≤ 1 for η ≥ 1.05 at every σ and angle. Eq. 2.28–2.30 alone
  is not bounded: with η = 1 (no Fresnel factors) the albedo reaches ≈ 1.05
  (σ ≈ 0.3, θ_o → 90°). ρ is the albedo of the body *under* the interface:
  with η = 1.52 the diffuse part returns ≈ 0.87 ρ at normal incidence.
* **Conductor tint.** The thesis code multiplies the conductor Fresnel by the
  diffuse reflectance; here a metal's reflectance comes from η and k alone and
  ``reflectance`` only scales the diffuse lobe.

Parameters (`SurfaceParams`, all (N,) arrays)
---------------------------------------------
===========  ======  ======  ==========================================================
name         type    unit    meaning (thesis default)
===========  ======  ======  ==========================================================
reflectance  float   1       near-IR diffuse albedo ρ in [0, 1]
roughness    float   rad     σ ≥ 0: Oren–Nayar σ and Beckmann α = √2 σ (0.5)
metallic     float   1       mask m in [0, 1]: f_r = (1 − m) dielectric + m conductor
ior          float   1       η > 0: dielectric index and conductor real part (1.52);
                             a blend 0 < m < 1 uses the same η for both parts
extinction   float   1       k ≥ 0, conductor absorption (ignored by the dielectric part)
coat         float   1       c in [0, 1]: weight of the clear coat (0: none)
coat_rough…  float   rad     σ_c ≥ 0: the coat's roughness (``coat_roughness``; 0 = mirror)
===========  ======  ======  ==========================================================

Example
-------
>>> import numpy as np
>>> n = 4
>>> params = SurfaceParams(reflectance=np.full(n, 0.8), roughness=np.full(n, 0.5),
...                        metallic=np.zeros(n), ior=np.full(n, 1.52),
...                        extinction=np.zeros(n))
>>> wo = np.tile([0.0, 0.6, 0.8], (n, 1))
>>> rng = np.random.default_rng(1)
>>> s = sample_bsdf(params, wo, *rng.random((3, n)))
>>> bool(np.all(s.weight >= 0.0))
True
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..backend import asarray, namespace
from ..errors import SceneError
from .fresnel import fresnel_conductor, fresnel_dielectric
from .sampling import (
    beckmann_distribution, pdf_cosine_hemisphere, pdf_vcavity_visible_normal, sample_cosine_hemisphere,
    sample_vcavity_visible_normal,
)

FloatArray = NDArray[np.float64]

#: Below this roughness σ (radians) the specular lobe is a perfect mirror.
SMOOTH_ROUGHNESS_RAD = 1e-4
#: Index of refraction of the clear coat (Blender's Principled BSDF default Coat IOR).
COAT_IOR = 1.5
#: Smallest probability of picking a lobe that can be non-zero (keeps a lobe
#: with a poor albedo estimate from being starved; any value in (0, 0.5) is unbiased).
MIN_LOBE_PROBABILITY = 0.05

# field -> (rule as worded in the error message, check); NaN fails every check.
_PARAMETER_RULES = {
    "reflectance": ("in [0, 1]", lambda x: (x >= 0.0) & (x <= 1.0)),
    "roughness": ("finite and >= 0 (radians)", lambda x: np.isfinite(x) & (x >= 0.0)),
    "metallic": ("in [0, 1]", lambda x: (x >= 0.0) & (x <= 1.0)),
    "ior": ("finite and > 0", lambda x: np.isfinite(x) & (x > 0.0)),
    "extinction": ("finite and >= 0", lambda x: np.isfinite(x) & (x >= 0.0)),
    "coat": ("in [0, 1]", lambda x: (x >= 0.0) & (x <= 1.0)),
    "coat_roughness": ("finite and >= 0 (radians)", lambda x: np.isfinite(x) & (x >= 0.0)),
}


@dataclass(frozen=True, kw_only=True)
class SurfaceParams:
    """Reflection parameters of N surface points; see the module table for units.

    Scalars are broadcast to the common length; the fields are stored as 1-D
    float64 arrays. Raises `SceneError` on out-of-range or non-finite values.
    """

    reflectance: FloatArray
    roughness: FloatArray
    metallic: FloatArray
    ior: FloatArray
    extinction: FloatArray
    coat: FloatArray = 0.0
    coat_roughness: FloatArray = 0.0

    def __post_init__(self) -> None:
        names = [field.name for field in fields(self)]
        arrays = np.broadcast_arrays(
            *(np.atleast_1d(asarray(getattr(self, name), dtype=np.float64)) for name in names)
        )
        bad = {}
        for name, array in zip(names, arrays):
            if array.ndim != 1:
                raise SceneError(f"SurfaceParams: {name} must be 1-D, got shape {array.shape!r}")
            bad[name] = ~_PARAMETER_RULES[name][1](array)
            object.__setattr__(self, name, namespace(array).ascontiguousarray(array))
        # One host round trip for all checks (each would be a GPU synchronisation), then the culprit.
        if bool(np.stack([b.any() for b in bad.values()]).any()):
            for name, b in bad.items():
                if b.any():
                    raise SceneError(f"SurfaceParams: {name} must be {_PARAMETER_RULES[name][0]}, "
                                     f"got {float(getattr(self, name)[b][0])!r}")
        metallic = self.metallic
        # Which Fresnel terms the points need (specular_fresnel), read back once here.
        has_metal, all_metal, has_coat = (bool(x) for x in np.stack(
            [metallic.any(), (metallic == 1.0).all(), (self.coat > 0.0).any()]).tolist())
        object.__setattr__(self, "_has_metal", has_metal)
        object.__setattr__(self, "_all_metal", all_metal)
        object.__setattr__(self, "_has_coat", has_coat)  # points without a coat take the base's code alone

    def take(self, index) -> SurfaceParams:
        """The parameters of the points ``index`` (integer array)."""
        return SurfaceParams(**{f.name: getattr(self, f.name)[index] for f in fields(self)})


@dataclass(frozen=True)
class BsdfSample:
    """Result of `sample_bsdf` for N points (see the module contract)."""

    wi: FloatArray  #: (N, 3) sampled unit direction, local frame
    weight: FloatArray  #: (N,) f_r cos θ_i / pdf (1), 0 if invalid
    pdf: FloatArray  #: (N,) solid-angle pdf (1/sr); lobe probability if is_delta
    is_delta: NDArray[np.bool_]  #: (N,) True where the mirror lobe was sampled


def beckmann_alpha(roughness_rad: ArrayLike) -> FloatArray:
    """Beckmann roughness α = √2 σ (eq. 2.26); σ in radians, α unitless."""
    return np.sqrt(2.0) * asarray(roughness_rad, dtype=np.float64)


def cos_azimuth_difference(wo: ArrayLike, wi: ArrayLike) -> FloatArray:
    """cos(φ_o − φ_i) of two local-frame directions (unitless).

    Returns 0 where either direction lies on the normal, where the azimuth is
    undefined (every term that multiplies it vanishes there, since β = 0).
    """
    wo = asarray(wo, dtype=np.float64)
    wi = asarray(wi, dtype=np.float64)
    planar_dot = wo[..., 0] * wi[..., 0] + wo[..., 1] * wi[..., 1]
    planar_norms = np.hypot(wo[..., 0], wo[..., 1]) * np.hypot(wi[..., 0], wi[..., 1])
    cos_phi = planar_dot / np.where(planar_norms > 0.0, planar_norms, 1.0)
    return np.where(planar_norms > 0.0, np.clip(cos_phi, -1.0, 1.0), 0.0)


def oren_nayar(
    reflectance: ArrayLike,
    roughness_rad: ArrayLike,
    cos_theta_i: ArrayLike,
    cos_theta_o: ArrayLike,
    cos_phi_diff: ArrayLike,
) -> FloatArray:
    r"""Oren–Nayar BRDF of a rough diffuse surface (eq. 2.28–2.30), without cosine.

    Parameters
    ----------
    reflectance : array_like
        Diffuse albedo ρ in [0, 1] (unitless).
    roughness_rad : array_like
        Standard deviation σ of the facet slope angle (radians, ≥ 0).
    cos_theta_i, cos_theta_o : array_like
        Cosines of the polar angles of ω_i and ω_o (unitless), clipped to [0, 1].
    cos_phi_diff : array_like
        cos(φ_o − φ_i), see `cos_azimuth_difference` (unitless).

    Returns
    -------
    numpy.ndarray
        f_r (1/sr), ≥ 0; exactly ρ/π for σ = 0.

    Notes
    -----
    With the thesis's α = max(θ_i, θ_o) → ``theta_max`` and
    β = min(θ_i, θ_o) → ``theta_min`` (not the Beckmann α),
    :math:`s = \sigma^2` and :math:`c = \cos(\phi_o - \phi_i)`:

    .. math::

        f_{direct} = \frac{\rho}{\pi}\Big[C_1 + c\,C_2\tan\beta
            + (1 - |c|)\,C_3\tan\frac{\alpha + \beta}{2}\Big] \quad (2.28)

        f_{inter} = 0.17\,\frac{\rho^2}{\pi}\,\frac{s}{s + 0.13}
            \Big[1 - c\Big(\frac{2\beta}{\pi}\Big)^2\Big] \quad (2.29)

        C_1 = 1 - 0.5\frac{s}{s + 0.33}, \quad
        C_2 = 0.45\frac{s}{s + 0.09}\Big(\sin\alpha
            - [c < 0]\Big(\frac{2\beta}{\pi}\Big)^3\Big), \quad
        C_3 = 0.125\frac{s}{s + 0.09}\Big(\frac{4\alpha\beta}{\pi^2}\Big)^2

        f_r = \max(0,\; f_{direct} + f_{inter}) \quad (2.30)

    The clamp at 0 is a departure: for σ ≳ 1 and both directions near grazing
    with c < 0, eq. 2.28 is negative. For ρ = 1 the albedo of eq. 2.30 alone
    reaches ≈ 1.05 (σ ≈ 0.3, θ_o → 90°); the (1 − F) factors of `eval_bsdf`
    remove that excess.
    """
    rho = asarray(reflectance, dtype=np.float64)
    s = np.square(asarray(roughness_rad, dtype=np.float64))
    cos_phi = asarray(cos_phi_diff, dtype=np.float64)
    theta_i = np.arccos(np.clip(asarray(cos_theta_i, dtype=np.float64), 0.0, 1.0))
    theta_o = np.arccos(np.clip(asarray(cos_theta_o, dtype=np.float64), 0.0, 1.0))
    theta_max = np.maximum(theta_i, theta_o)
    theta_min = np.minimum(theta_i, theta_o)
    scaled_min = 2.0 * theta_min / np.pi
    c1 = 1.0 - 0.5 * s / (s + 0.33)
    c2 = 0.45 * s / (s + 0.09) * (np.sin(theta_max) - np.where(cos_phi < 0.0, scaled_min**3, 0.0))
    c3 = 0.125 * s / (s + 0.09) * np.square(4.0 * theta_max * theta_min / np.pi**2)
    direct = (rho / np.pi) * (
        c1
        + cos_phi * c2 * np.tan(theta_min)
        + (1.0 - np.abs(cos_phi)) * c3 * np.tan(0.5 * (theta_max + theta_min))
    )
    interreflection = 0.17 * rho * rho / np.pi * s / (s + 0.13) * (1.0 - cos_phi * scaled_min**2)
    return np.maximum(direct + interreflection, 0.0)


def vcavity_geometry(
    cos_theta_h: ArrayLike, cos_theta_o: ArrayLike, cos_theta_i: ArrayLike, cos_theta_oh: ArrayLike
) -> FloatArray:
    r"""V-cavity masking–shadowing factor G (eq. 2.27).

    Parameters
    ----------
    cos_theta_h : array_like
        n·ω_h, cosine of the half vector's polar angle (unitless).
    cos_theta_o, cos_theta_i : array_like
        n·ω_o and n·ω_i (unitless).
    cos_theta_oh : array_like
        ω_o·ω_h (= ω_i·ω_h) (unitless).

    Returns
    -------
    numpy.ndarray
        G in [0, 1]; 0 where ω_o·ω_h ≤ 0 or any cosine is negative.

    Notes
    -----
    .. math::

        G = \min\Big[1,\ \frac{2(n\cdot\omega_h)(n\cdot\omega_o)}{\omega_o\cdot\omega_h},\
                     \frac{2(n\cdot\omega_h)(n\cdot\omega_i)}{\omega_o\cdot\omega_h}\Big]
        \quad (2.27)
    """
    cos_h = np.maximum(asarray(cos_theta_h, dtype=np.float64), 0.0)
    cos_o = np.maximum(asarray(cos_theta_o, dtype=np.float64), 0.0)
    cos_i = np.maximum(asarray(cos_theta_i, dtype=np.float64), 0.0)
    cos_oh = asarray(cos_theta_oh, dtype=np.float64)
    valid = cos_oh > 0.0
    scale = 2.0 * cos_h / np.where(valid, cos_oh, 1.0)
    return np.where(valid, np.minimum(1.0, scale * np.minimum(cos_o, cos_i)), 0.0)


def torrance_sparrow(
    fresnel: ArrayLike,
    distribution: ArrayLike,
    geometry: ArrayLike,
    cos_theta_i: ArrayLike,
    cos_theta_o: ArrayLike,
) -> FloatArray:
    r"""Torrance–Sparrow microfacet BRDF (eq. 2.24), without cosine.

    Parameters
    ----------
    fresnel : array_like
        F_r(ω_i·ω_h) (unitless).
    distribution : array_like
        D(ω_h) (1/sr), eq. 2.26.
    geometry : array_like
        G(ω_o, ω_i) (unitless), eq. 2.27.
    cos_theta_i, cos_theta_o : array_like
        n·ω_i and n·ω_o (unitless).

    Returns
    -------
    numpy.ndarray
        f_r (1/sr); 0 where either cosine is ≤ 0.

    Notes
    -----
    .. math::

        f_r = \frac{F_r(\omega_h)\,D(\omega_h)\,G(\omega_o, \omega_i)}
                   {4\cos\theta_i\cos\theta_o} \quad (2.24)
    """
    denominator = 4.0 * np.multiply(cos_theta_i, cos_theta_o, dtype=np.float64)
    valid = denominator > 0.0
    numerator = asarray(fresnel) * asarray(distribution) * asarray(geometry)
    return np.where(valid, numerator / np.where(valid, denominator, 1.0), 0.0)


def specular_fresnel(params: SurfaceParams, cos_theta: ArrayLike) -> FloatArray:
    """Fresnel reflectance of the specular lobe, (1 − m) F_d + m F_c (unitless).

    ``cos_theta`` is ω_i·ω_h for the rough lobe and cos θ_o for the mirror.
    """
    metallic = params.metallic
    # Leave out the Fresnel term a batch of points does not need (all dielectric or all metal).
    if not params._has_metal:
        return fresnel_dielectric(cos_theta, params.ior)
    conductor = fresnel_conductor(cos_theta, params.ior, params.extinction)
    if params._all_metal:
        return conductor
    return (1.0 - metallic) * fresnel_dielectric(cos_theta, params.ior) + metallic * conductor


def specular_probability(params: SurfaceParams, cos_theta_o: ArrayLike) -> FloatArray:
    """Probability that `sample_bsdf` picks the specular lobe (unitless).

    The lobes' albedos are estimated from ω_o alone: specular ≈ F(cos θ_o)
    (`specular_fresnel`), diffuse ≈ (1 − m)(1 − F_d(cos θ_o)) ρ. A lobe that can
    be non-zero gets at least `MIN_LOBE_PROBABILITY`; a lobe that is
    identically zero (no diffuse part for m = 1 or ρ = 0, no specular part for
    a dielectric with η = 1) gets probability 0.
    """
    return _outgoing(params, asarray(cos_theta_o, dtype=np.float64)).probability


@dataclass(frozen=True)
class _Outgoing:
    """Terms of ω_o alone, shared by `eval_bsdf`, `pdf_bsdf` and `sample_bsdf` at the same points."""

    cos_o: FloatArray  #: cos θ_o
    fresnel_o: FloatArray  #: F_d(cos θ_o), the dielectric Fresnel of the diffuse weight
    probability: FloatArray  #: P_s, `specular_probability`
    coat_fresnel_o: FloatArray | None = None  #: F_d(cos θ_o; η_c) (None without a coat)
    coat_probability: FloatArray | None = None  #: P_c, `coat_probability` (None without a coat)


def _outgoing(params: SurfaceParams, cos_o: FloatArray) -> _Outgoing:
    fresnel_o = fresnel_dielectric(cos_o, params.ior)
    specular = specular_fresnel(params, cos_o) if params._has_metal else fresnel_o
    diffuse = (1.0 - params.metallic) * (1.0 - fresnel_o) * params.reflectance
    total = specular + diffuse
    share = specular / np.where(total > 0.0, total, 1.0)
    has_specular = (params.metallic > 0.0) | (params.ior != 1.0)
    has_diffuse = diffuse > 0.0
    both = np.clip(share, MIN_LOBE_PROBABILITY, 1.0 - MIN_LOBE_PROBABILITY)
    probability = np.where(has_specular & has_diffuse, both, np.where(has_specular, 1.0, 0.0))
    if not params._has_coat:
        return _Outgoing(cos_o=cos_o, fresnel_o=fresnel_o, probability=probability)
    coat_fresnel_o = fresnel_dielectric(cos_o, COAT_IOR)
    coat = params.coat * coat_fresnel_o
    base = (1.0 - coat) * total
    coat_total = coat + base
    coat_share = np.clip(coat / np.where(coat_total > 0.0, coat_total, 1.0), MIN_LOBE_PROBABILITY,
                         1.0 - MIN_LOBE_PROBABILITY)
    has_coat = coat > 0.0
    coat_probability = np.where(has_coat & (base > 0.0), coat_share, np.where(has_coat, 1.0, 0.0))
    return _Outgoing(cos_o=cos_o, fresnel_o=fresnel_o, probability=probability, coat_fresnel_o=coat_fresnel_o,
                     coat_probability=coat_probability)


def coat_probability(params: SurfaceParams, cos_theta_o: ArrayLike) -> FloatArray:
    """Probability that `sample_bsdf` picks the coat's lobe (unitless): the coat's albedo estimated as
    c F_d(cos θ_o; η_c) against the base's, (1 − c F_d(cos θ_o; η_c)) times `specular_probability`'s two
    estimates; at least `MIN_LOBE_PROBABILITY` for either where both can be non-zero, 0 without a coat."""
    out = _outgoing(params, asarray(cos_theta_o, dtype=np.float64))
    return out.coat_probability if out.coat_probability is not None else namespace(out.cos_o).zeros_like(out.cos_o)


@dataclass(frozen=True)
class _Pair:
    """Terms of a direction pair (ω_o, ω_i), shared by `eval_bsdf` and `pdf_bsdf`."""

    cos_i: FloatArray  #: cos θ_i
    valid: NDArray[np.bool_]  #: both directions above the surface
    h: FloatArray  #: (N, 3) half vector (eq. 2.25)
    cos_oh: FloatArray  #: ω_o·ω_h
    alpha: FloatArray  #: Beckmann α, 0 for a mirror lobe
    distribution: FloatArray  #: D(ω_h) (eq. 2.26)
    coat_alpha: FloatArray | None = None  #: the coat's α, 0 for a mirror coat (None without a coat)
    coat_distribution: FloatArray | None = None  #: the coat's D(ω_h)


def _pair(params: SurfaceParams, wo: FloatArray, wi: FloatArray) -> _Pair:
    cos_i = wi[..., 2]
    h = _half_vector(wo, wi)
    alpha = _rough_alpha(params.roughness)
    pair = _Pair(cos_i=cos_i, valid=(wo[..., 2] > 0.0) & (cos_i > 0.0), h=h, cos_oh=np.sum(wo * h, axis=-1),
                 alpha=alpha, distribution=beckmann_distribution(h[..., 2], alpha))
    if not params._has_coat:
        return pair
    coat_alpha = _rough_alpha(params.coat_roughness)
    return replace(pair, coat_alpha=coat_alpha, coat_distribution=beckmann_distribution(h[..., 2], coat_alpha))


def _half_vector(wo: FloatArray, wi: FloatArray) -> FloatArray:
    """Normalised ω_o + ω_i (eq. 2.25); the normal where the sum vanishes."""
    total = wo + wi
    length = np.linalg.norm(total, axis=-1, keepdims=True)
    return np.where(length > 0.0, total / np.where(length > 0.0, length, 1.0), _normal_like(total))


def _normal_like(w: FloatArray) -> FloatArray:
    """The local normal (0, 0, 1) in the shape and array module of directions ``w``."""
    normal = namespace(w).zeros_like(w)
    normal[..., 2] = 1.0
    return normal


def _rough_alpha(roughness: FloatArray) -> FloatArray:
    """Beckmann α where a specular lobe of roughness σ is rough, 0 where it is a mirror."""
    return np.where(roughness >= SMOOTH_ROUGHNESS_RAD, beckmann_alpha(roughness), 0.0)


def eval_bsdf(params: SurfaceParams, wo: ArrayLike, wi: ArrayLike) -> FloatArray:
    """BRDF value f_r (1/sr) without the cosine; see the module contract.

    Parameters
    ----------
    params : SurfaceParams
        (N,) surface parameters.
    wo, wi : array_like
        (N, 3) unit directions in the local shading frame, pointing away.

    Returns
    -------
    numpy.ndarray
        (N,) f_r ≥ 0; 0 where cos θ_o ≤ 0 or cos θ_i ≤ 0; mirror lobes excluded.
    """
    wo = asarray(wo, dtype=np.float64)
    wi = asarray(wi, dtype=np.float64)
    cos_o = wo[..., 2]
    return _eval(params, wo, wi, cos_o, fresnel_dielectric(cos_o, params.ior), _pair(params, wo, wi))


def _eval(params: SurfaceParams, wo, wi, cos_o, fresnel_o, pair: _Pair, coat_fresnel_o=None) -> FloatArray:
    """`eval_bsdf` from the shared terms (``coat_fresnel_o``: F_d(cos θ_o; η_c) where known)."""
    transmitted = (1.0 - fresnel_dielectric(pair.cos_i, params.ior)) * (1.0 - fresnel_o)
    diffuse = (1.0 - params.metallic) * transmitted * oren_nayar(
        params.reflectance, params.roughness, pair.cos_i, cos_o, cos_azimuth_difference(wo, wi)
    )
    specular = torrance_sparrow(
        specular_fresnel(params, pair.cos_oh),
        pair.distribution,
        vcavity_geometry(pair.h[..., 2], cos_o, pair.cos_i, pair.cos_oh),
        pair.cos_i,
        cos_o,
    )
    if not params._has_coat:
        return np.where(pair.valid, diffuse + specular, 0.0)
    if coat_fresnel_o is None:
        coat_fresnel_o = fresnel_dielectric(cos_o, COAT_IOR)
    coat = params.coat
    through = (1.0 - coat * fresnel_dielectric(pair.cos_i, COAT_IOR)) * (1.0 - coat * coat_fresnel_o)
    coat_specular = coat * torrance_sparrow(
        fresnel_dielectric(pair.cos_oh, COAT_IOR),
        pair.coat_distribution,
        vcavity_geometry(pair.h[..., 2], cos_o, pair.cos_i, pair.cos_oh),
        pair.cos_i,
        cos_o,
    )
    return np.where(pair.valid, coat_specular + through * (diffuse + specular), 0.0)


def pdf_bsdf(params: SurfaceParams, wo: ArrayLike, wi: ArrayLike) -> FloatArray:
    r"""Solid-angle density (1/sr) of the non-delta part of `sample_bsdf`.

    Parameters
    ----------
    params : SurfaceParams
        (N,) surface parameters.
    wo, wi : array_like
        (N, 3) unit directions in the local shading frame, pointing away.

    Returns
    -------
    numpy.ndarray
        (N,) density; 0 where cos θ_o ≤ 0 or cos θ_i ≤ 0.

    Notes
    -----
    One-sample MIS over the lobes, with P_s = `specular_probability`:

    .. math::

        p(\omega_i) = P_s\,\frac{D_{\omega_o}(\omega_h)}{4\,\omega_o\cdot\omega_h}
                      + (1 - P_s)\,\frac{\cos\theta_i}{\pi},

    :math:`D_{\omega_o}` the V-cavity visible-normal density
    (`tofcore.scene.sampling.pdf_vcavity_visible_normal`) and 1/(4 ω_o·ω_h) the
    Jacobian of the reflection ω_i = 2(ω_o·ω_h)ω_h − ω_o. A mirror lobe
    contributes no density.
    """
    wo = asarray(wo, dtype=np.float64)
    wi = asarray(wi, dtype=np.float64)
    out = _outgoing(params, wo[..., 2])
    return _pdf(wo, out.probability, _pair(params, wo, wi), out.coat_probability)


def _pdf(wo, probability, pair: _Pair, coat_probability=None) -> FloatArray:
    """`pdf_bsdf` from the shared terms; with a coat P_c p_coat + (1 − P_c) p_base."""
    cos_oh = pair.cos_oh
    reflect_jacobian = 1.0 / (4.0 * np.where(cos_oh > 0.0, cos_oh, 1.0))
    rough = (cos_oh > 0.0) & (pair.alpha > 0.0)
    visible_normal = pdf_vcavity_visible_normal(wo, pair.h, pair.alpha, distribution=pair.distribution)
    specular = np.where(rough, visible_normal * reflect_jacobian, 0.0)
    density = probability * specular + (1.0 - probability) * pdf_cosine_hemisphere(pair.cos_i)
    if coat_probability is not None:
        coat_rough = (cos_oh > 0.0) & (pair.coat_alpha > 0.0)
        coat_normal = pdf_vcavity_visible_normal(wo, pair.h, pair.coat_alpha, distribution=pair.coat_distribution)
        coat = np.where(coat_rough, coat_normal * reflect_jacobian, 0.0)
        density = coat_probability * coat + (1.0 - coat_probability) * density
    return np.where(pair.valid, density, 0.0)


def eval_pdf_bsdf(params: SurfaceParams, wo: ArrayLike, wi: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """(`eval_bsdf`, `pdf_bsdf`) of the same directions, computing what they share once.

    The half vector, D(ω_h), the Fresnel terms of cos θ_o and the lobe probability are the same for
    both; a caller that needs f_r and the density (MIS, sampling) pays for them once.
    """
    wo = asarray(wo, dtype=np.float64)
    wi = asarray(wi, dtype=np.float64)
    out = _outgoing(params, wo[..., 2])
    pair = _pair(params, wo, wi)
    return (_eval(params, wo, wi, out.cos_o, out.fresnel_o, pair, out.coat_fresnel_o),
            _pdf(wo, out.probability, pair, out.coat_probability))


def sample_bsdf(
    params: SurfaceParams, wo: ArrayLike, u_lobe: ArrayLike, u1: ArrayLike, u2: ArrayLike
) -> BsdfSample:
    """Draw ω_i for each point: pick a lobe with ``u_lobe``, then warp (u1, u2).

    Parameters
    ----------
    params : SurfaceParams
        (N,) surface parameters.
    wo : array_like
        (N, 3) unit direction towards the viewer, local shading frame.
    u_lobe, u1, u2 : array_like
        (N,) uniform random numbers in [0, 1) (unitless).

    Returns
    -------
    BsdfSample
        See the module contract.

    Notes
    -----
    The specular lobe (probability P_s) reflects ω_o about a V-cavity visible
    normal (rough) or about the normal (mirror); the diffuse lobe draws a
    cosine-weighted direction. ``u_lobe``, rescaled to [0, 1) within the chosen
    lobe's interval, decides the V-cavity facet swap, so three uniforms suffice.
    """
    wo = asarray(wo, dtype=np.float64)
    u_lobe = asarray(u_lobe, dtype=np.float64)
    out = _outgoing(params, wo[..., 2])
    cos_o, probability, coat_probability = out.cos_o, out.probability, out.coat_probability
    if coat_probability is not None:  # the coat's lobe first: u_lobe < P_c; the base's lobes share the rest
        pick_coat = u_lobe < coat_probability
        u_coat = np.clip(u_lobe / np.where(coat_probability > 0.0, coat_probability, 1.0), 0.0,
                         np.nextafter(1.0, 0.0))
        u_lobe = np.clip((u_lobe - coat_probability) / np.where(coat_probability < 1.0, 1.0 - coat_probability, 1.0),
                         0.0, np.nextafter(1.0, 0.0))
    pick_specular = u_lobe < probability
    u_swap = np.where(
        pick_specular,
        u_lobe / np.where(probability > 0.0, probability, 1.0),
        (u_lobe - probability) / np.where(probability < 1.0, 1.0 - probability, 1.0),
    )
    u_swap = np.clip(u_swap, 0.0, np.nextafter(1.0, 0.0))
    alpha = _rough_alpha(params.roughness)
    wi_specular = _reflect(wo, sample_vcavity_visible_normal(wo, alpha, u1, u2, u_swap), alpha)
    wi = np.where(pick_specular[..., None], wi_specular, sample_cosine_hemisphere(u1, u2))
    if coat_probability is not None:
        coat_alpha = _rough_alpha(params.coat_roughness)
        wi_coat = _reflect(wo, sample_vcavity_visible_normal(wo, coat_alpha, u1, u2, u_coat), coat_alpha)
        wi = np.where(pick_coat[..., None], wi_coat, wi)

    pair = _pair(params, wo, wi)
    pdf = _pdf(wo, probability, pair, coat_probability)
    f_cos = _eval(params, wo, wi, cos_o, out.fresnel_o, pair, out.coat_fresnel_o) * np.maximum(pair.cos_i, 0.0)
    weight = np.where(pdf > 0.0, f_cos / np.where(pdf > 0.0, pdf, 1.0), 0.0)

    is_delta = pick_specular & (alpha == 0.0) & (cos_o > 0.0)
    mirror_fresnel = specular_fresnel(params, cos_o) if params._has_metal else out.fresnel_o
    if coat_probability is None:
        mirror_weight = mirror_fresnel / np.where(probability > 0.0, probability, 1.0)
        return BsdfSample(wi=wi, weight=np.where(is_delta, mirror_weight, weight),
                          pdf=np.where(is_delta, probability, pdf), is_delta=is_delta)
    # Under a coat the base's mirror is seen through it twice, (1 − c F_c(θ_o))²; the coat's own mirror
    # reflects c F_c(θ_o). Each delta lobe's weight is its reflectance over the probability of picking it.
    base_share = 1.0 - coat_probability
    through = 1.0 - params.coat * out.coat_fresnel_o
    base_mirror = ~pick_coat & is_delta
    base_pick = base_share * probability
    coat_mirror = pick_coat & (coat_alpha == 0.0) & (cos_o > 0.0)
    coat_pick = np.where(coat_probability > 0.0, coat_probability, 1.0)
    weight = np.where(base_mirror, through * through * mirror_fresnel / np.where(base_pick > 0.0, base_pick, 1.0),
                      np.where(coat_mirror, params.coat * out.coat_fresnel_o / coat_pick, weight))
    pdf = np.where(base_mirror, base_pick, np.where(coat_mirror, coat_probability, pdf))
    return BsdfSample(wi=wi, weight=weight, pdf=pdf, is_delta=base_mirror | coat_mirror)


def _reflect(wo: FloatArray, m: FloatArray, alpha: FloatArray) -> FloatArray:
    """ω_o reflected about the sampled microfacet normal m, or about the normal where α = 0 (a mirror)."""
    m = np.where((alpha > 0.0)[..., None], m, _normal_like(m))
    return 2.0 * np.sum(wo * m, axis=-1, keepdims=True) * m - wo
