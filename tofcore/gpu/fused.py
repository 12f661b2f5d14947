"""Fused elementwise kernels: hot chains of NumPy-style operations as one CUDA kernel each.

On the GPU every NumPy-style operation is a kernel launch and a pass over device memory; a chain
of them is launch- and bandwidth-bound. The chains here are the ones the GPU profile found hot,
each bit-identical to its NumPy twin (integer arithmetic; float operations in the same order).

* :func:`uniform` — :func:`tofcore.tracer.rng.uniform`: two SplitMix64 finalisers over a mix of
  (key, pixel, sample, dimension), 53 bits → [0, 1); 14 array operations in NumPy, one kernel here.
* :func:`fresnel_dielectric`, :func:`fresnel_conductor` — :mod:`tofcore.scene.fresnel`: evaluated several
  times per vertex (BSDF value, pdf, lobe choice); 28 % of the bytes the GPU trace moved (counted on
  the Kinect room frame), 11 and 12 operations each in NumPy.
* :func:`square_correlation` — :func:`tofcore.sensor.modulation.square_correlation`, per raw image and
  contribution: 7 operations in NumPy.
"""

from __future__ import annotations

import functools

from .. import backend
from ..tracer import qmc
from ..tracer import rng as _rng

_MASK64 = (1 << 64) - 1


@functools.lru_cache(maxsize=None)
def _uniform_kernel(cp):
    c = {k: f"{int(getattr(_rng, k)):#x}ULL" for k in ("_GOLDEN", "_MIX_PIXEL", "_MIX_SAMPLE", "_M1", "_M2")}
    return cp.ElementwiseKernel(
        "int64 pixel, int64 sample, uint64 key, uint64 dim_mix", "float64 u",
        f"""
        unsigned long long x = key ^ ((unsigned long long)pixel * {c['_MIX_PIXEL']})
                                   ^ ((unsigned long long)sample * {c['_MIX_SAMPLE']}) ^ dim_mix;
        for (int round = 0; round < 2; ++round) {{
            x += {c['_GOLDEN']};
            x = (x ^ (x >> 30)) * {c['_M1']};
            x = (x ^ (x >> 27)) * {c['_M2']};
            x = x ^ (x >> 31);
        }}
        u = (double)(x >> 11) * (1.0 / 9007199254740992.0);
        """,
        "tofcore_uniform")


def uniform(key, pixel, sample, dim: int):
    """:func:`tofcore.tracer.rng.uniform` for CuPy ``pixel`` and ``sample`` arrays, bit for bit."""
    cp = backend.namespace(pixel, sample)
    dim_mix = (int(dim) * int(_rng._MIX_DIM)) & _MASK64
    return _uniform_kernel(cp)(pixel.astype(cp.int64, copy=False), sample.astype(cp.int64, copy=False),
                               cp.uint64(int(key)), cp.uint64(dim_mix))


_QMC_BODY = """
    long long replicate = sample % REPLICATES;
    unsigned int j = (unsigned int)(sample / REPLICATES);
    unsigned long long h[2];
    for (int which = 0; which < 2; ++which) {
        unsigned long long x = key ^ ((unsigned long long)pixel * MIX_PIXEL)
                                   ^ ((unsigned long long)replicate * MIX_SAMPLE) ^ dim_mix[which];
        for (int round = 0; round < 2; ++round) {
            x += GOLDEN;
            x = (x ^ (x >> 30)) * M1;
            x = (x ^ (x >> 27)) * M2;
            x = x ^ (x >> 31);
        }
        h[which] = x;
    }
    unsigned int s_index = (unsigned int)(h[0] & 0xFFFFFFFFULL);
    unsigned int s_x = (unsigned int)(h[0] >> 32);
    unsigned int s_y = (unsigned int)(h[1] & 0xFFFFFFFFULL);
    unsigned int index = owen(j, s_index);
"""

_QMC_PREAMBLE = """
__device__ unsigned int owen(unsigned int x, unsigned int seed) {
    x = __brev(x);
    x += seed;
""" + "".join(f"    x ^= x * {int(k):#010x}u;\n" for k in qmc._LK) + """    return __brev(x);
}
"""
"""The Laine–Karras hash of :func:`tofcore.tracer.qmc.owen_scramble`, its constants taken from ``qmc._LK``."""


@functools.lru_cache(maxsize=None)
def _qmc_kernel(cp, two: bool):
    c = {k: f"{int(getattr(_rng, k)):#x}ULL" for k in ("_GOLDEN", "_MIX_PIXEL", "_MIX_SAMPLE", "_M1", "_M2")}
    body = _QMC_BODY.replace("REPLICATES", f"{qmc.REPLICATES}LL")
    for name in ("GOLDEN", "MIX_PIXEL", "MIX_SAMPLE", "M1", "M2"):
        body = body.replace(name, c["_" + name])
    if two:
        body = body.replace("dim_mix[which]", "(which ? dim_mix_y : dim_mix_x)") + """
        unsigned int x = __brev(index), y = 0, m = 1;
        for (int b = 0; index != 0u; ++b, index >>= 1) {
            if (index & 1u) y ^= m << (31 - b);
            m ^= m << 1;
        }
        u = owen(x, s_x) * (1.0 / 4294967296.0);
        v = owen(y, s_y) * (1.0 / 4294967296.0);
        """
        return cp.ElementwiseKernel("int64 pixel, int64 sample, uint64 key, uint64 dim_mix_x, uint64 dim_mix_y",
                                    "float64 u, float64 v", body, "tofcore_qmc_2d", preamble=_QMC_PREAMBLE)
    body = body.replace("dim_mix[which]", "(which ? dim_mix_y : dim_mix_x)") + """
        u = owen(__brev(index), s_x) * (1.0 / 4294967296.0);
        """
    return cp.ElementwiseKernel("int64 pixel, int64 sample, uint64 key, uint64 dim_mix_x, uint64 dim_mix_y",
                                "float64 u", body, "tofcore_qmc_1d", preamble=_QMC_PREAMBLE)


def scrambled_2d(key, pixel, sample, dim: int):
    """:func:`tofcore.tracer.qmc.scrambled_2d` for CuPy ``pixel`` and ``sample`` arrays, bit for bit."""
    return qmc_sample(key, pixel, sample, dim, two=True)


def scrambled_1d(key, pixel, sample, dim: int):
    """:func:`tofcore.tracer.qmc.scrambled_1d` for CuPy ``pixel`` and ``sample`` arrays, bit for bit."""
    return qmc_sample(key, pixel, sample, dim, two=False)


def qmc_sample(key, pixel, sample, dim: int, two: bool):
    """The ``"sobol"`` sampler's (u, v) (``two``) or u for CuPy arrays: one kernel for both dimensions."""
    cp = backend.namespace(pixel, sample)
    mixes = [cp.uint64((int(d) * int(_rng._MIX_DIM)) & _MASK64) for d in (dim, dim + qmc.SEED_DIM_OFFSET)]
    args = (pixel.astype(cp.int64, copy=False), sample.astype(cp.int64, copy=False), cp.uint64(int(key)), *mixes)
    return _qmc_kernel(cp, two)(*args)


# Floating-point kernels compile without FMA contraction and spell out every operation in the order of
# the NumPy twin, so they round identically (IEEE double +, −, ×, ÷ and sqrt are correctly rounded).
_NO_FMA = ("--fmad=false",)

_CLIP01 = "(x < 0.0 ? 0.0 : (x > 1.0 ? 1.0 : x))"  # np.clip(x, 0, 1), NaN stays NaN


@functools.lru_cache(maxsize=None)
def _fresnel_dielectric_kernel(cp):
    return cp.ElementwiseKernel(
        "float64 x, float64 eta", "float64 reflectance",
        f"""
        const double cos_1 = {_CLIP01};
        const double sin2_2 = (1.0 - cos_1 * cos_1) / (eta * eta);
        const double one_minus = 1.0 - sin2_2;
        const double cos_2 = sqrt(one_minus < 0.0 ? 0.0 : one_minus);
        const double r_parallel = (eta * cos_1 - cos_2) / (eta * cos_1 + cos_2);
        const double r_perpendicular = (cos_1 - eta * cos_2) / (cos_1 + eta * cos_2);
        reflectance = sin2_2 >= 1.0 ? 1.0
                      : 0.5 * (r_parallel * r_parallel + r_perpendicular * r_perpendicular);
        """,
        "tofcore_fresnel_dielectric", options=_NO_FMA)


@functools.lru_cache(maxsize=None)
def _fresnel_conductor_kernel(cp):
    return cp.ElementwiseKernel(
        "float64 x, float64 eta, float64 k", "float64 reflectance",
        f"""
        const double cos_i = {_CLIP01};
        const double eta2_k2 = eta * eta + k * k;
        const double two_eta_cos = 2.0 * eta * cos_i;
        const double cos2 = cos_i * cos_i;
        const double r_parallel2 = (eta2_k2 * cos2 - two_eta_cos + 1.0) / (eta2_k2 * cos2 + two_eta_cos + 1.0);
        const double denominator = eta2_k2 + two_eta_cos + cos2;
        const double r_perpendicular2 = denominator > 0.0 ? (eta2_k2 - two_eta_cos + cos2) / denominator : 1.0;
        reflectance = 0.5 * (r_parallel2 + r_perpendicular2);
        """,
        "tofcore_fresnel_conductor", options=_NO_FMA)


@functools.lru_cache(maxsize=None)
def _square_correlation_kernel(cp):
    # x − floor(x), as the NumPy twin computes the fractional part (exact in IEEE double).
    return cp.ElementwiseKernel(
        "float64 tau, float64 f_hz, float64 offset, float64 peak, float64 lo, float64 hi, float64 duty",
        "float64 g",
        """
        const double shifted = f_hz * tau - offset + 0.5;
        const double u = fabs(shifted - floor(shifted) - 0.5);
        const double x = peak - u;
        g = (x < lo ? lo : (x > hi ? hi : x)) / duty;
        """,
        "tofcore_square_correlation", options=_NO_FMA)


def fresnel_dielectric(cos_theta_i, eta):
    """:func:`tofcore.scene.fresnel.fresnel_dielectric` for CuPy arrays, bit for bit."""
    cp = backend.namespace(cos_theta_i, eta)
    return _fresnel_dielectric_kernel(cp)(cp.asarray(cos_theta_i, cp.float64), cp.asarray(eta, cp.float64))


def fresnel_conductor(cos_theta_i, eta, k):
    """:func:`tofcore.scene.fresnel.fresnel_conductor` for CuPy arrays, bit for bit."""
    cp = backend.namespace(cos_theta_i, eta, k)
    return _fresnel_conductor_kernel(cp)(cp.asarray(cos_theta_i, cp.float64), cp.asarray(eta, cp.float64),
                                         cp.asarray(k, cp.float64))


def square_correlation(tau_s, f_hz: float, offset_fraction: float, duty: float):
    """:func:`tofcore.sensor.modulation.square_correlation` for a CuPy array of delays, bit for bit."""
    cp = backend.namespace(tau_s)
    return _square_correlation_kernel(cp)(cp.asarray(tau_s, cp.float64), float(f_hz), float(offset_fraction),
                                          0.25 + 0.5 * duty, max(0.0, duty - 0.5), min(duty, 0.5), float(duty))
