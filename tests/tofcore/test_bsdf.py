"""BSDF (tofcore.scene.bsdf), Fresnel (tofcore.scene.fresnel) and warps (tofcore.scene.sampling).

Numbered like Mitsuba's plugin tests: limits and closed forms first, then the
properties of a plausible BRDF (eq. 2.11–2.13), then the sampling contract
(pdfs integrate to one, histograms follow the pdfs, weight = f cos / pdf), then
robustness at grazing angles and in the smooth limit.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import pytest

from tofcore.scene.bsdf import (
    COAT_IOR, SMOOTH_ROUGHNESS_RAD, SurfaceParams, beckmann_alpha, coat_probability, eval_bsdf, eval_pdf_bsdf,
    oren_nayar, pdf_bsdf, sample_bsdf, specular_fresnel, specular_probability, vcavity_geometry,
)
from tofcore.errors import SceneError
from tofcore.scene.fresnel import fresnel_conductor, fresnel_dielectric
from tofcore.scene.sampling import (
    beckmann_distribution, pdf_beckmann_normal, pdf_concentric_disk, pdf_cosine_hemisphere, pdf_vcavity_visible_normal,
    sample_beckmann_normal, sample_concentric_disk, sample_cosine_hemisphere, sample_vcavity_visible_normal,
)

# Materials of the checks: (metallic, ior, extinction). A dielectric with the
# thesis's η = 1.52, a silver-like conductor, a k = 0 "conductor" and a 50 %
# metallic blend (both parts share η).
DIELECTRIC = (0.0, 1.52, 0.0)
SILVER_LIKE = (1.0, 0.2, 3.0)
CONDUCTOR_K0 = (1.0, 1.5, 0.0)
HALF_METAL = (0.5, 1.52, 3.0)
MATERIALS = [DIELECTRIC, SILVER_LIKE, CONDUCTOR_K0, HALF_METAL]
ROUGHNESSES = [0.0, 0.1, 0.5, 1.0]


def make_params(n, *, reflectance=1.0, roughness=0.5, metallic=0.0, ior=1.52, extinction=0.0):
    """SurfaceParams of n points, every field broadcast to (n,)."""
    values = dict(reflectance=reflectance, roughness=roughness, metallic=metallic, ior=ior,
                  extinction=extinction)
    return SurfaceParams(**{key: np.broadcast_to(np.asarray(v, np.float64), (n,)) for key, v in values.items()})


def direction(theta_deg, phi_deg=0.0):
    theta, phi = np.radians(theta_deg), np.radians(phi_deg)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)


def random_hemisphere(rng, n):
    """Uniform directions on the upper hemisphere."""
    z = rng.random(n)
    phi = 2.0 * np.pi * rng.random(n)
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def gauss_legendre(lo, hi, panels, order):
    """Composite Gauss–Legendre nodes and weights on [lo, hi]."""
    x, w = np.polynomial.legendre.leggauss(order)
    edges = np.linspace(lo, hi, panels + 1)
    half = 0.5 * np.diff(edges)[:, None]
    nodes = 0.5 * (edges[:-1] + edges[1:])[:, None] + half * x
    return nodes.ravel(), (half * w).ravel()


def hemisphere_quadrature(theta_panels=64, phi_points=512, order=8):
    """Directions and solid-angle weights (sin θ dθ dφ) covering the upper hemisphere."""
    theta, w_theta = gauss_legendre(0.0, 0.5 * np.pi, theta_panels, order)
    phi = (np.arange(phi_points) + 0.5) * 2.0 * np.pi / phi_points
    t, p = np.meshgrid(theta, phi, indexing="ij")
    weights = (w_theta * np.sin(theta))[:, None] * (2.0 * np.pi / phi_points) * np.ones_like(p)
    dirs = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)
    return dirs.reshape(-1, 3), weights.ravel()


@functools.lru_cache(maxsize=None)
def specular_mass_below_horizon(theta_o_deg, phi_o_deg, alpha):
    """Probability that reflecting ω_o about a V-cavity visible normal goes below the horizon.

    Such samples are returned with weight 0, so pdf_bsdf integrates over the
    upper hemisphere to 1 − P(specular) times this mass. Integrated over the
    visible normals m, where the integrand only has a step (in ω_i space the
    density is nearly singular at ω_i = −ω_o); the step limits the quadrature
    error to ≈ 2e-4 (checked against 4·10⁶ samples of the warp).
    """
    wo = direction(theta_o_deg, phi_o_deg)
    m, w = hemisphere_quadrature()
    wi_z = 2.0 * (m @ wo) * m[:, 2] - wo[2]
    return float(np.sum(w * pdf_vcavity_visible_normal(wo, m, alpha) * (wi_z <= 0.0)))


def chi2_p_value(statistic, dof):
    """Upper tail of the chi-square distribution, Wilson–Hilferty approximation.

    Accurate to a few 1e-3 in p for dof ≥ 10, ample for a 1 % threshold.
    """
    scale = 2.0 / (9.0 * dof)
    z = ((statistic / dof) ** (1.0 / 3.0) - (1.0 - scale)) / math.sqrt(scale)
    return 0.5 * math.erfc(z / math.sqrt(2.0))


def chi2_hemisphere(dirs, pdf, n_total, extra=(), theta_bins=10, phi_bins=20):
    """Mitsuba-style chi-square test of sampled directions against a pdf.

    Histogram on a (θ, φ) grid; the expected count of each cell is n_total
    times the pdf integrated over the cell (8×8 Gauss–Legendre). Cells expecting
    fewer than 5 samples are pooled (the chi-square approximation needs ≥ 5).
    ``extra`` holds (observed, expected) pairs for discrete outcomes (the delta
    lobe). Returns the p-value.
    """
    theta = np.arccos(np.clip(dirs[:, 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(dirs[:, 1], dirs[:, 0]), 2.0 * np.pi)
    observed, _, _ = np.histogram2d(theta, phi, bins=[theta_bins, phi_bins],
                                    range=[[0.0, 0.5 * np.pi], [0.0, 2.0 * np.pi]])
    x, w = np.polynomial.legendre.leggauss(8)
    expected = np.zeros_like(observed)
    t_edges = np.linspace(0.0, 0.5 * np.pi, theta_bins + 1)
    p_edges = np.linspace(0.0, 2.0 * np.pi, phi_bins + 1)
    for i in range(theta_bins):
        th = 0.5 * (t_edges[i] + t_edges[i + 1]) + 0.5 * (t_edges[i + 1] - t_edges[i]) * x
        for j in range(phi_bins):
            ph = 0.5 * (p_edges[j] + p_edges[j + 1]) + 0.5 * (p_edges[j + 1] - p_edges[j]) * x
            tt, pp = np.meshgrid(th, ph, indexing="ij")
            cell_dirs = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1)
            values = pdf(cell_dirs.reshape(-1, 3)).reshape(tt.shape) * np.sin(tt)
            area = 0.25 * (t_edges[i + 1] - t_edges[i]) * (p_edges[j + 1] - p_edges[j])
            expected[i, j] = n_total * area * np.sum(w[:, None] * w[None, :] * values)
    observed = np.append(observed.ravel(), [o for o, _ in extra])
    expected = np.append(expected.ravel(), [e for _, e in extra])
    small = expected < 5.0
    observed = np.append(observed[~small], observed[small].sum())
    expected = np.append(expected[~small], expected[small].sum())
    if expected[-1] == 0.0:
        observed, expected = observed[:-1], expected[:-1]
    assert observed.sum() == n_total
    # The expected counts add up to n_total: measured within 7e-5 (the step
    # integral of the below-horizon mass dominates), so 5e-4.
    assert expected.sum() == pytest.approx(n_total, rel=5e-4)
    statistic = float(np.sum((observed - expected) ** 2 / expected))
    return chi2_p_value(statistic, len(expected) - 1)


# Eight chi-square tests (tests 10, 14, 15): Šidák's correction keeps the
# family-wise false-failure rate at 1 %; with fixed seeds the outcome is fixed,
# the threshold says how unlucky a seed would have to be.
CHI2_SIGNIFICANCE = 1.0 - (1.0 - 0.01) ** (1.0 / 8.0)


# 1. Fresnel ------------------------------------------------------------------

def test_01_dielectric_fresnel_normal_incidence():
    # ((1.52 − 1)/(1.52 + 1))² = 0.042580; the brief quotes 0.0426 to 4 digits.
    assert float(fresnel_dielectric(1.0, 1.52)) == pytest.approx(0.0426, abs=1e-4)


def test_02_dielectric_fresnel_matches_closed_form():
    # Walter et al. 2007, eq. 22 — an independent algebraic form of eq. 2.19–2.21;
    # both are a few flops of float64, so they agree to rounding (1e-12).
    cos_i = np.linspace(0.0, 1.0, 101)
    for eta in (1.1, 1.33, 1.52, 2.5):
        g = np.sqrt(eta**2 - 1.0 + cos_i**2)
        closed = 0.5 * (g - cos_i) ** 2 / (g + cos_i) ** 2 * (
            1.0 + (cos_i * (g + cos_i) - 1.0) ** 2 / (cos_i * (g - cos_i) + 1.0) ** 2)
        np.testing.assert_allclose(fresnel_dielectric(cos_i, eta), closed, rtol=1e-12, atol=1e-15)


def test_03_conductor_fresnel_normal_incidence():
    # Exact algebra at cos θ = 1, so equality holds to rounding (1e-12).
    eta = np.array([0.2, 0.5, 1.0, 1.5, 2.7])
    k = np.array([3.0, 0.0, 1.0, 0.0, 4.1])
    expected = ((eta - 1.0) ** 2 + k**2) / ((eta + 1.0) ** 2 + k**2)
    np.testing.assert_allclose(fresnel_conductor(np.ones(5), eta, k), expected, rtol=1e-12, atol=1e-15)


def test_04_fresnel_range_and_dtype():
    cos_i = np.linspace(-0.5, 1.5, 401).astype(np.float32)
    for f in (fresnel_dielectric(cos_i, 1.52), fresnel_dielectric(cos_i, 0.7),
              fresnel_conductor(cos_i, 0.2, 3.0), fresnel_conductor(cos_i, 0.0, 0.0)):
        assert f.dtype == np.float64 and np.all(np.isfinite(f)) and np.all((f >= 0) & (f <= 1))
    assert float(fresnel_dielectric(0.0, 1.52)) == 1.0
    assert float(fresnel_conductor(0.0, 0.2, 3.0)) == 1.0


# 2. Model limits and plausibility (eq. 2.11–2.13) ------------------------------

def test_05_oren_nayar_smooth_is_lambert_exactly():
    rng = np.random.default_rng(5)
    n = 10_000
    rho = rng.random(n)
    cos_i = np.concatenate([[0.0, 1.0, 1e-8], rng.random(n - 3)])
    cos_o = rng.random(n)
    cos_phi = rng.uniform(-1.0, 1.0, n)
    assert np.array_equal(oren_nayar(rho, 0.0, cos_i, cos_o, cos_phi), rho / np.pi)


def test_06_oren_nayar_non_negative():
    theta = np.radians(np.linspace(0.0, 89.999, 200))
    t_i, t_o = np.meshgrid(theta, theta)
    for sigma in (0.5, 1.0, 1.5, 3.0):
        for rho in (0.01, 0.5, 1.0):
            f = oren_nayar(rho, sigma, np.cos(t_i), np.cos(t_o), -1.0)
            assert np.all(f >= 0.0)


def test_07_reciprocity():
    rng = np.random.default_rng(7)
    n = 20_000
    wo, wi = random_hemisphere(rng, n), random_hemisphere(rng, n)
    params = SurfaceParams(
        reflectance=rng.random(n),
        roughness=rng.choice([0.0, 1e-3, 0.05, 0.1, 0.5, 1.0, 2.0], n),
        metallic=rng.choice([0.0, 0.3, 1.0], n),
        ior=rng.choice([1.0, 1.33, 1.52, 0.2, 2.5], n),
        extinction=rng.choice([0.0, 3.0], n),
    )
    forward, backward = eval_bsdf(params, wo, wi), eval_bsdf(params, wi, wo)
    # Every factor is symmetric by construction; only rounding differs (the half
    # vector's dot product with ω_o vs ω_i), far below the 1e-5 of the brief.
    # atol: values below 1e-12 1/sr are D's exponential tail, irrelevant to light.
    np.testing.assert_allclose(forward, backward, rtol=1e-5, atol=1e-12)
    assert np.all(forward >= 0.0)


@pytest.fixture(scope="module")
def furnace_albedos():
    """Directional albedo (ρ = 1) for σ × material × incidence, by sample_bsdf.

    All configurations go through one vectorised call: 25 000 samples each.
    """
    angles = [0.0, 45.0, 70.0, 85.0, 89.9]
    configs = [(s, mat, a) for s in ROUGHNESSES for mat in MATERIALS for a in angles]
    per = 25_000
    n = per * len(configs)
    roughness = np.repeat([c[0] for c in configs], per)
    metallic, ior, extinction = (np.repeat([c[1][j] for c in configs], per) for j in range(3))
    wo = np.repeat(direction(np.array([c[2] for c in configs])), per, axis=0)
    params = make_params(n, reflectance=1.0, roughness=roughness, metallic=metallic, ior=ior,
                         extinction=extinction)
    s = sample_bsdf(params, wo, *np.random.default_rng(8).random((3, n)))
    weights = s.weight.reshape(len(configs), per)
    return configs, weights.mean(axis=1), weights.std(axis=1) / math.sqrt(per), s


def test_08_white_furnace_energy_conservation(furnace_albedos):
    configs, mean, stderr, s = furnace_albedos
    assert np.all(np.isfinite(s.weight)) and np.all(s.weight >= 0.0)
    # Eq. 2.12: albedo ≤ 1, allowing 3 standard errors of the estimate.
    for config, m, e in zip(configs, mean, stderr):
        assert m <= 1.0 + 3.0 * e, f"albedo {m:.4f} ± {e:.4f} > 1 for (σ, material, θ_o) = {config}"


def test_09_smooth_limits_have_analytic_albedo(furnace_albedos):
    configs, mean, stderr, _ = furnace_albedos
    # Smooth dielectric: F(θ_o) + (1 − F(θ_o)) ∫ (1 − F(θ_i)) cos θ_i/π dω_i (Lambert).
    mu, w = gauss_legendre(0.0, 1.0, 64, 8)
    diffuse_out = 2.0 * np.sum(w * mu * (1.0 - fresnel_dielectric(mu, 1.52)))
    for (sigma, material, angle), m, e in zip(configs, mean, stderr):
        if sigma != 0.0 or material not in (DIELECTRIC, SILVER_LIKE):
            continue
        f_o = float(fresnel_dielectric(np.cos(np.radians(angle)), 1.52))
        if material == DIELECTRIC:
            # 4 standard errors + quadrature error (< 1e-9): a 6e-5 false-alarm rate.
            assert m == pytest.approx(f_o + (1.0 - f_o) * diffuse_out, abs=4.0 * e + 1e-9)
        else:
            # Every sample is the mirror with weight F_c(θ_o): no variance at all.
            f_c = float(fresnel_conductor(np.cos(np.radians(angle)), 0.2, 3.0))
            assert m == pytest.approx(f_c, rel=1e-12)


# 3. Sampling: pdfs, histograms, weights -------------------------------------

def test_10_disk_warp_uniform_and_normalised():
    rng = np.random.default_rng(10)
    n = 400_000
    x, y = sample_concentric_disk(*rng.random((2, n)))
    r2 = x * x + y * y
    assert np.all(r2 <= 1.0 + 1e-12)
    # Uniform on the disk ⇔ r² and φ uniform: chi-square on a 10 × 10 grid.
    phi = np.mod(np.arctan2(y, x), 2.0 * np.pi)
    observed, _, _ = np.histogram2d(r2, phi, bins=10, range=[[0, 1], [0, 2 * np.pi]])
    expected = n / 100.0
    statistic = float(np.sum((observed - expected) ** 2 / expected))
    assert chi2_p_value(statistic, 99) > CHI2_SIGNIFICANCE
    # ∫ pdf dA over the square [−1, 1]² by Monte Carlo: mean = (1/π)·(π/4) = 1/4,
    # tolerance 5 standard errors of the Bernoulli mean.
    square = rng.uniform(-1.0, 1.0, (2, n))
    estimate = 4.0 * pdf_concentric_disk(*square).mean()
    sigma = 4.0 / np.pi * math.sqrt(0.25 * np.pi * (1 - 0.25 * np.pi) / n)
    assert estimate == pytest.approx(1.0, abs=5.0 * sigma)


@pytest.mark.parametrize("alpha", [0.05, 0.3, 1.0, 2.0])
def test_11_warp_pdfs_integrate_to_one(alpha):
    dirs, w = hemisphere_quadrature()
    # Composite 8-point Gauss–Legendre in θ (64 panels), midpoint rule in φ (512):
    # measured error < 1e-13 for all four α and halving the grid changes the
    # sums by < 1e-13, so 1e-9 leaves room for platform rounding only.
    assert np.sum(w * pdf_cosine_hemisphere(dirs[:, 2])) == pytest.approx(1.0, abs=1e-9)
    assert np.sum(w * pdf_beckmann_normal(dirs, alpha)) == pytest.approx(1.0, abs=1e-9)
    for theta_o in (0.0, 40.0, 80.0, 89.99):
        wo = direction(theta_o, 30.0)
        total = np.sum(w * pdf_vcavity_visible_normal(wo, dirs, alpha))
        assert total == pytest.approx(1.0, abs=1e-9)


def test_12_visible_normal_pdf_equals_g1_form():
    # pdf = G₁(ω_o, m) ⟨ω_o, m⟩ D(m) / cos θ_o (Heitz & d'Eon 2014); two algebraic
    # routes to the same number, equal to rounding (1e-10 relative).
    rng = np.random.default_rng(12)
    n = 10_000
    wo, m = random_hemisphere(rng, n), random_hemisphere(rng, n)
    alpha = rng.uniform(0.05, 2.0, n)
    cos_om = np.sum(wo * m, axis=1)
    g1 = vcavity_geometry(m[:, 2], wo[:, 2], np.ones(n), cos_om)
    expected = g1 * np.maximum(cos_om, 0.0) * beckmann_distribution(m[:, 2], alpha) / wo[:, 2]
    np.testing.assert_allclose(pdf_vcavity_visible_normal(wo, m, alpha), expected, rtol=1e-10, atol=1e-300)


@pytest.mark.parametrize("material", MATERIALS)
@pytest.mark.parametrize("roughness", ROUGHNESSES + [0.3])
def test_13_bsdf_pdf_integrates_to_one(material, roughness):
    metallic, ior, extinction = material
    dirs, w = hemisphere_quadrature()
    for theta_o in (0.0, 45.0, 85.0):
        wo = np.broadcast_to(direction(theta_o, 10.0), dirs.shape)
        params = make_params(len(dirs), reflectance=0.7, roughness=roughness, metallic=metallic,
                             ior=ior, extinction=extinction)
        total = np.sum(w * pdf_bsdf(params, wo, dirs))
        p_specular = float(specular_probability(params, wo[:1, 2])[0])
        if roughness < SMOOTH_ROUGHNESS_RAD:
            # A mirror lobe has no density: the rest integrates to 1 − P(mirror).
            expected = 1.0 - p_specular
        else:
            # Reflections below the horizon are returned with weight 0 and no density.
            alpha = float(beckmann_alpha(roughness))
            expected = 1.0 - p_specular * specular_mass_below_horizon(theta_o, 10.0, alpha)
        # The upper-hemisphere sum is converged to < 1e-6 (doubling the grid
        # changes it less; the σ = 0.1 lobe at 85° needs the 512 φ points); the
        # step integral of the mass below the horizon is good to ≈ 2e-4; so 1e-3.
        assert total == pytest.approx(expected, abs=1e-3)


@pytest.mark.parametrize(
    "name, sampler, pdf",
    [
        ("cosine", lambda u: sample_cosine_hemisphere(u[0], u[1]), lambda d: pdf_cosine_hemisphere(d[:, 2])),
        ("beckmann", lambda u: sample_beckmann_normal(0.4, u[0], u[1]), lambda d: pdf_beckmann_normal(d, 0.4)),
        ("vcavity", lambda u: sample_vcavity_visible_normal(direction(60.0, 20.0), 0.7, u[0], u[1], u[2]),
         lambda d: pdf_vcavity_visible_normal(direction(60.0, 20.0), d, 0.7)),
    ],
)
def test_14_warp_chi2(name, sampler, pdf):
    n = 200_000
    u = np.random.default_rng(14).random((3, n))
    assert chi2_hemisphere(sampler(u), pdf, n) > CHI2_SIGNIFICANCE, name


@pytest.mark.parametrize(
    "material, roughness, theta_o, reflectance",
    [(DIELECTRIC, 0.5, 45.0, 0.5), (SILVER_LIKE, 0.2, 70.0, 1.0), (HALF_METAL, 0.35, 20.0, 0.8),
     (DIELECTRIC, 0.0, 60.0, 0.6)],
)
def test_15_bsdf_sampling_chi2(material, roughness, theta_o, reflectance):
    metallic, ior, extinction = material
    n = 200_000
    params = make_params(n, reflectance=reflectance, roughness=roughness, metallic=metallic, ior=ior,
                         extinction=extinction)
    wo = np.broadcast_to(direction(theta_o, 50.0), (n, 3))
    s = sample_bsdf(params, wo, *np.random.default_rng(15).random((3, n)))
    one = make_params(1, reflectance=reflectance, roughness=roughness, metallic=metallic, ior=ior,
                      extinction=extinction)
    p_specular = float(specular_probability(one, wo[:1, 2])[0])
    if roughness == 0.0:
        # The mirror is a discrete outcome: one extra bin.
        extra = [(int(s.is_delta.sum()), n * p_specular)]
    else:
        # Reflections below the horizon (weight 0) are another discrete outcome.
        below = n * p_specular * specular_mass_below_horizon(theta_o, 50.0, float(beckmann_alpha(roughness)))
        extra = [(int(np.sum(s.wi[:, 2] <= 0.0)), below)]
    upper = ~s.is_delta & (s.wi[:, 2] > 0.0)
    p_value = chi2_hemisphere(s.wi[upper], lambda d: pdf_bsdf(one, wo[:1], d), n, extra=extra)
    assert p_value > CHI2_SIGNIFICANCE


def test_16_sample_weight_is_eval_cos_over_pdf():
    rng = np.random.default_rng(16)
    n = 100_000
    params = SurfaceParams(
        reflectance=rng.random(n),
        roughness=rng.choice([0.0, 1e-4, 0.02, 0.1, 0.5, 1.0, 2.0], n),
        metallic=rng.choice([0.0, 0.5, 1.0], n),
        ior=rng.choice([1.0, 1.52, 0.2], n),
        extinction=rng.choice([0.0, 3.0], n),
    )
    wo = random_hemisphere(rng, n)
    s = sample_bsdf(params, wo, *rng.random((3, n)))
    rough = ~s.is_delta
    f_cos = eval_bsdf(params, wo, s.wi) * np.maximum(s.wi[:, 2], 0.0)
    pdf = pdf_bsdf(params, wo, s.wi)
    np.testing.assert_array_equal(s.pdf[rough], pdf[rough])
    ok = rough & (pdf > 0.0)
    # The same expression in the same order: equal to the last bit.
    np.testing.assert_array_equal(s.weight[ok], f_cos[ok] / pdf[ok])
    assert np.all(s.weight[rough & (pdf == 0.0)] == 0.0)
    # Delta samples: mirror about the normal, weight F(θ_o)/P(mirror), pdf = P(mirror).
    d = s.is_delta
    assert d.any() and np.all(params.roughness[d] < SMOOTH_ROUGHNESS_RAD)
    np.testing.assert_allclose(s.wi[d], wo[d] * [-1.0, -1.0, 1.0], rtol=0, atol=1e-15)
    p_mirror = specular_probability(params, wo[:, 2])
    np.testing.assert_allclose(s.pdf[d], p_mirror[d], rtol=1e-15)
    np.testing.assert_allclose(s.weight[d], specular_fresnel(params, wo[:, 2])[d] / p_mirror[d], rtol=1e-15)


# 4. Robustness ----------------------------------------------------------------

def test_17_no_nan_or_inf_at_the_edges():
    thetas = [0.0, 30.0, 89.0, 89.9, 89.99, 90.0, 91.0, 180.0]
    rough = [0.0, 1e-6, SMOOTH_ROUGHNESS_RAD, 1e-3, 0.1, 1.0, 3.0]
    mats = [(0.0, 1.0, 0.0), (0.0, 1.52, 0.0), (0.0, 0.7, 0.0), (1.0, 0.2, 3.0), (1.0, 0.05, 0.0), (0.5, 1.5, 0.0)]
    grid = np.array(np.meshgrid(np.arange(len(thetas)), np.arange(len(thetas)), np.arange(len(rough)),
                                np.arange(len(mats)), [0.0, 1.0], indexing="ij")).reshape(5, -1)
    n = grid.shape[1]
    t_o, t_i = np.array(thetas)[grid[0].astype(int)], np.array(thetas)[grid[1].astype(int)]
    wo = direction(t_o, 0.0).astype(np.float32)  # float32 input on purpose
    wi = direction(t_i, 135.0).astype(np.float32)
    wo[t_o == 0.0] = [0.0, 0.0, 1.0]  # exactly on the normal
    mat = np.array(mats)[grid[3].astype(int)]
    params = make_params(n, reflectance=grid[4], roughness=np.array(rough)[grid[2].astype(int)],
                         metallic=mat[:, 0], ior=mat[:, 1], extinction=mat[:, 2])
    edge_uniforms = np.array([0.0, 0.5, np.nextafter(np.float32(1.0), np.float32(0.0))], np.float32)
    with np.errstate(divide="raise", over="raise", invalid="raise"):
        f = eval_bsdf(params, wo, wi)
        p = pdf_bsdf(params, wo, wi)
        samples = [sample_bsdf(params, wo, *np.full((3, n), u)) for u in edge_uniforms]
        samples.append(sample_bsdf(params, wo, *np.random.default_rng(17).random((3, n)).astype(np.float32)))
    below = (wo[:, 2] <= 0.0) | (wi[:, 2] <= 0.0)
    assert np.all(np.isfinite(f)) and np.all(f >= 0.0) and np.all(f[below] == 0.0)
    assert np.all(np.isfinite(p)) and np.all(p >= 0.0) and np.all(p[below] == 0.0)
    for s in samples:
        for array in (s.wi, s.weight, s.pdf):
            assert array.dtype == np.float64 and np.all(np.isfinite(array))
        assert np.all(s.weight >= 0.0) and np.all(s.pdf >= 0.0)
        assert np.all(s.weight[s.wi[:, 2] <= 0.0] == 0.0)
        assert np.all(s.weight[wo[:, 2] <= 0.0] == 0.0) and not np.any(s.is_delta[wo[:, 2] <= 0.0])
        # wo is float32 (unit to ~1e-7) and the mirror/microfacet reflection
        # keeps its length, so 1e-6.
        np.testing.assert_allclose(np.linalg.norm(s.wi, axis=1), 1.0, atol=1e-6)


def test_18_smooth_delta_reflects_about_the_normal():
    n = 5
    wo = direction(np.array([0.0, 20.0, 60.0, 89.0, 89.99]), np.array([0.0, 10.0, 100.0, 200.0, 300.0]))
    params = make_params(n, roughness=0.0, metallic=1.0, ior=0.2, extinction=3.0)
    s = sample_bsdf(params, wo, np.full(n, 0.3), np.full(n, 0.6), np.full(n, 0.9))
    assert np.all(s.is_delta) and np.all(s.pdf == 1.0)
    np.testing.assert_allclose(s.wi, wo * [-1.0, -1.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(s.weight, fresnel_conductor(wo[:, 2], 0.2, 3.0), rtol=1e-15)
    # eval and pdf exclude the delta lobe: a pure mirror has f = pdf = 0 everywhere.
    assert np.all(eval_bsdf(params, wo, s.wi) == 0.0) and np.all(pdf_bsdf(params, wo, s.wi) == 0.0)


def test_19_beckmann_alpha_and_param_validation():
    assert float(beckmann_alpha(0.5)) == pytest.approx(math.sqrt(2.0) * 0.5, rel=1e-15)
    with pytest.raises(SceneError, match=r"SurfaceParams: reflectance must be in \[0, 1\], got 1\.5"):
        make_params(3, reflectance=np.array([0.2, 1.5, 0.3]))
    with pytest.raises(SceneError, match=r"SurfaceParams: roughness must be finite and >= 0 \(radians\), got -0\.1"):
        make_params(2, roughness=-0.1)
    with pytest.raises(SceneError, match=r"SurfaceParams: ior must be finite and > 0, got nan"):
        make_params(2, ior=np.nan)


def test_20_eval_pdf_together_equals_separate_calls():
    """eval_pdf_bsdf shares the half vector, D and the Fresnel terms: bit for bit the two calls, over
    mirrors, metals, blends, η < 1 and directions below the surface."""
    rng = np.random.default_rng(20)
    n = 20_000
    params = SurfaceParams(
        reflectance=rng.uniform(0.0, 1.0, n),
        roughness=np.where(rng.random(n) < 0.1, 0.0, rng.uniform(0.0, 1.2, n)),
        metallic=np.where(rng.random(n) < 0.3, rng.random(n), 0.0),
        ior=rng.uniform(0.8, 3.0, n), extinction=rng.uniform(0.0, 3.0, n))
    wo = rng.normal(size=(n, 3))
    wi = rng.normal(size=(n, 3))
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    f, pdf = eval_pdf_bsdf(params, wo, wi)
    np.testing.assert_array_equal(f, eval_bsdf(params, wo, wi))
    np.testing.assert_array_equal(pdf, pdf_bsdf(params, wo, wi))
    assert (f > 0).mean() > 0.1 and (pdf > 0).mean() > 0.1


# 5. The clear coat ------------------------------------------------------------------------------------------------

COATS = [(0.3, 0.0), (1.0, 0.0), (1.0, 0.1), (0.5, 0.4)]  # (weight c, roughness σ_c)


def coated_params(n, *, coat, coat_roughness, **base):
    """make_params with a coat of weight ``coat`` and roughness ``coat_roughness``."""
    params = make_params(n, **base)
    return dataclasses.replace(params, coat=np.full(n, float(coat)), coat_roughness=np.full(n, float(coat_roughness)))


def test_21_a_coat_of_weight_zero_is_the_base_bit_for_bit():
    """Points without a coat in a batch that has coated points: eval, pdf and samples as without any coat."""
    rng = np.random.default_rng(21)
    n = 20_000
    wo, wi = random_hemisphere(rng, n), random_hemisphere(rng, n)
    fields = dict(reflectance=rng.random(n), roughness=rng.choice([0.0, 0.05, 0.5], n),
                  metallic=rng.choice([0.0, 0.5, 1.0], n), ior=rng.choice([1.0, 1.52], n),
                  extinction=rng.choice([0.0, 3.0], n))
    plain = SurfaceParams(**fields)
    coat = np.where(np.arange(n) % 2 == 0, 0.0, 0.7)
    mixed = SurfaceParams(**fields, coat=coat, coat_roughness=rng.choice([0.0, 0.2], n))
    bare = coat == 0.0
    u = rng.random((3, n))
    for a, b in ((eval_bsdf(mixed, wo, wi), eval_bsdf(plain, wo, wi)),
                 (pdf_bsdf(mixed, wo, wi), pdf_bsdf(plain, wo, wi))):
        np.testing.assert_array_equal(a[bare], b[bare])
        assert not np.array_equal(a[~bare], b[~bare])
    s, t = sample_bsdf(mixed, wo, *u), sample_bsdf(plain, wo, *u)
    for name in ("wi", "weight", "pdf", "is_delta"):
        np.testing.assert_array_equal(getattr(s, name)[bare], getattr(t, name)[bare], err_msg=name)


def test_22_coat_is_reciprocal_and_conserves_energy():
    """f_r(ω_o, ω_i) = f_r(ω_i, ω_o), and the white furnace's albedo ≤ 1 (3 standard errors) under every coat,
    over a white dielectric, a metal and a rough blend, at normal to grazing incidence."""
    rng = np.random.default_rng(22)
    n = 20_000
    wo, wi = random_hemisphere(rng, n), random_hemisphere(rng, n)
    params = SurfaceParams(reflectance=rng.random(n), roughness=rng.choice([0.0, 0.1, 0.5, 1.0], n),
                           metallic=rng.choice([0.0, 0.5, 1.0], n), ior=rng.choice([1.0, 1.52, 0.2], n),
                           extinction=rng.choice([0.0, 3.0], n), coat=rng.random(n),
                           coat_roughness=rng.choice([0.0, 0.05, 0.3, 1.0], n))
    np.testing.assert_allclose(eval_bsdf(params, wo, wi), eval_bsdf(params, wi, wo), rtol=1e-5, atol=1e-12)
    per = 20_000
    for coat, coat_roughness in COATS:
        for material in (DIELECTRIC, SILVER_LIKE, HALF_METAL):
            for roughness in (0.0, 0.5):
                for theta in (0.0, 60.0, 85.0, 89.9):
                    metallic, ior, extinction = material
                    p = coated_params(per, coat=coat, coat_roughness=coat_roughness, reflectance=1.0,
                                      roughness=roughness, metallic=metallic, ior=ior, extinction=extinction)
                    s = sample_bsdf(p, np.broadcast_to(direction(theta), (per, 3)), *rng.random((3, per)))
                    mean, err = s.weight.mean(), s.weight.std() / math.sqrt(per)
                    assert np.all(np.isfinite(s.weight)) and mean <= 1.0 + 3.0 * err, (coat, coat_roughness,
                                                                                      material, roughness, theta, mean)


def test_23_a_smooth_coat_over_a_black_base_reflects_c_times_fresnel():
    """The analytic limit: a mirror coat of weight c over a body that reflects nothing (ρ = 0, η = 1: no base
    lobe) has albedo c F_d(cos θ_o; 1.5), all of it in the delta lobe (whose weight is c F / P_c; the base's
    share, if the rounding of F_d(·; 1) leaves it one, returns 0)."""
    n = 100_000
    for coat in (0.25, 1.0):
        for theta in (0.0, 45.0, 80.0):
            p = coated_params(n, coat=coat, coat_roughness=0.0, reflectance=0.0, roughness=0.5, ior=1.0)
            wo = np.broadcast_to(direction(theta), (n, 3))
            s = sample_bsdf(p, wo, *np.random.default_rng(23).random((3, n)))
            expected = coat * fresnel_dielectric(math.cos(math.radians(theta)), COAT_IOR)
            p_coat = coat_probability(p, wo[:, 2])
            np.testing.assert_allclose(s.weight[s.is_delta], expected / p_coat[s.is_delta], rtol=1e-14)
            assert np.all(s.weight[~s.is_delta] < 1e-20)  # F_d(·; η = 1) rounds to ~1e-17 near grazing, not 0
            assert s.weight.mean() == pytest.approx(expected, abs=4.0 * s.weight.std() / math.sqrt(n) + 1e-15)


@pytest.mark.parametrize("coat, coat_roughness", COATS)
def test_24_coated_pdf_integrates_to_one_minus_the_deltas(coat, coat_roughness):
    """∫ pdf = 1 − P_c (mirror coat, or its reflections below the horizon) − (1 − P_c) P_s (the base's mirror, or
    its mass below the horizon), over a rough base and a mirror base."""
    dirs, w = hemisphere_quadrature()
    for roughness in (0.0, 0.5):
        for theta_o in (0.0, 45.0):
            wo = np.broadcast_to(direction(theta_o, 10.0), dirs.shape)
            p = coated_params(len(dirs), coat=coat, coat_roughness=coat_roughness, reflectance=0.7,
                              roughness=roughness)
            total = np.sum(w * pdf_bsdf(p, wo, dirs))
            p_coat = float(coat_probability(p, wo[:1, 2])[0])
            p_specular = float(specular_probability(p, wo[:1, 2])[0])
            lost_coat = 1.0 if coat_roughness < SMOOTH_ROUGHNESS_RAD else specular_mass_below_horizon(
                theta_o, 10.0, float(beckmann_alpha(coat_roughness)))
            lost_base = 1.0 if roughness < SMOOTH_ROUGHNESS_RAD else specular_mass_below_horizon(
                theta_o, 10.0, float(beckmann_alpha(roughness)))
            expected = 1.0 - p_coat * lost_coat - (1.0 - p_coat) * p_specular * lost_base
            assert total == pytest.approx(expected, abs=1e-3), (roughness, theta_o)


def test_25_coated_sampling_matches_its_pdf_and_weights():
    """χ² of the coated lobes' directions against pdf_bsdf (the two mirrors one extra bin), weight = f cos / pdf
    for the rough samples to the last bit, and each mirror's weight its reflectance over its probability."""
    n = 200_000
    p = coated_params(n, coat=0.6, coat_roughness=0.2, reflectance=0.8, roughness=0.0)
    one = coated_params(1, coat=0.6, coat_roughness=0.2, reflectance=0.8, roughness=0.0)
    wo = np.broadcast_to(direction(40.0, 30.0), (n, 3))
    s = sample_bsdf(p, wo, *np.random.default_rng(25).random((3, n)))
    p_coat = float(coat_probability(one, wo[:1, 2])[0])
    p_mirror = (1.0 - p_coat) * float(specular_probability(one, wo[:1, 2])[0])
    below = n * p_coat * specular_mass_below_horizon(40.0, 30.0, float(beckmann_alpha(0.2)))
    extra = [(int(s.is_delta.sum()), n * p_mirror), (int(np.sum(~s.is_delta & (s.wi[:, 2] <= 0.0))), below)]
    upper = ~s.is_delta & (s.wi[:, 2] > 0.0)
    assert chi2_hemisphere(s.wi[upper], lambda d: pdf_bsdf(one, wo[:1], d), n, extra=extra) > CHI2_SIGNIFICANCE
    rough = ~s.is_delta & (s.pdf > 0.0)
    f_cos = eval_bsdf(p, wo, s.wi) * np.maximum(s.wi[:, 2], 0.0)
    np.testing.assert_array_equal(s.weight[rough], f_cos[rough] / pdf_bsdf(p, wo, s.wi)[rough])
    through = 1.0 - 0.6 * fresnel_dielectric(wo[:, 2], COAT_IOR)
    mirror = through * through * fresnel_dielectric(wo[:, 2], 1.52) / p_mirror
    np.testing.assert_allclose(s.weight[s.is_delta], mirror[s.is_delta], rtol=1e-14)
