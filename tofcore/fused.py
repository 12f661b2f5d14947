"""Fused elementwise kernels: hot chains of NumPy-style operations as one CUDA kernel each.

On the GPU every NumPy-style operation is a kernel launch and a pass over device memory; a chain
of them is launch- and bandwidth-bound. The chains here are the ones the GPU profile found hot,
each bit-identical to its NumPy twin (integer arithmetic; float operations in the same order).

* :func:`uniform` — :func:`tofcore.rng.uniform`: two SplitMix64 finalisers over a mix of
  (key, pixel, sample, dimension), 53 bits → [0, 1); 14 array operations in NumPy, one kernel here.
* :func:`fresnel_dielectric`, :func:`fresnel_conductor` — :mod:`tofcore.scene.fresnel`: evaluated several
  times per vertex (BSDF value, pdf, lobe choice); 28 % of the bytes the GPU trace moved (counted on
  the Kinect room frame), 11 and 12 operations each in NumPy.
* :func:`square_correlation` — :func:`tofcore.sensor.modulation.square_correlation`, per raw image and
  contribution: 7 operations in NumPy.
* :func:`poisson` — :func:`tofcore.sensor.noise.poisson`, the sensor's shot noise: inversion (45 terms) or
  PTRS (up to 24 rejection rounds) per element; as masked array code on a device ~1,900 operations a frame.
  Integer hashing is exact; ``exp``, ``log`` and ``cos`` are CUDA's (≤ 1–2 ulp from glibc's), so a count
  can differ from NumPy's only where a comparison falls within a few ulp (never seen on 10⁶ counts).

Device-only code, like :mod:`tofcore.gpu`, but beside that folder rather than in it: these kernels twin the
tracer's and the sensor's functions and take their constants from them, so they stand a floor above both,
while :mod:`tofcore.gpu.traversal` (the BVH's twin) stands below the compiled tracer that launches it. In one
folder the two would lift the compiled tracer, and the render that picks it, a floor (docs/architecture.md).
"""

from __future__ import annotations

import functools
import math

from . import backend
from .sensor import noise as _noise
from .tracer import qmc
from . import rng as _rng

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
    """:func:`tofcore.rng.uniform` for CuPy ``pixel`` and ``sample`` arrays, bit for bit."""
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


@functools.lru_cache(maxsize=None)
def _poisson_kernel(cp):
    c = {k: f"{int(getattr(_rng, k)):#x}ULL" for k in ("_GOLDEN", "_MIX_PIXEL", "_MIX_DIM", "_M1", "_M2")}
    table = ", ".join(repr(float(v)) for v in _noise._LOG_FACTORIAL)
    preamble = f"""
    __device__ double tofcore_u_open(unsigned long long key, long long i, long long dim) {{
        unsigned long long x = key ^ ((unsigned long long)i * {c['_MIX_PIXEL']})
                                   ^ ((unsigned long long)dim * {c['_MIX_DIM']});
        for (int round = 0; round < 2; ++round) {{
            x += {c['_GOLDEN']};
            x = (x ^ (x >> 30)) * {c['_M1']};
            x = (x ^ (x >> 27)) * {c['_M2']};
            x = x ^ (x >> 31);
        }}
        return (double)(x >> 11) * (1.0 / 9007199254740992.0) + {2.0 ** -54!r};
    }}
    __device__ double tofcore_log_factorial(double k) {{
        const double table[16] = {{{table}}};
        if (k < 16.0) return table[(int)k];
        const double x = k + 1.0;
        const double inv = 1.0 / x;
        const double inv2 = inv * inv;
        return (x - 0.5) * log(x) - x + {_noise.HALF_LOG_2PI!r}
               + inv * ({1.0 / 12.0!r} - inv2 * ({1.0 / 360.0!r} - inv2 * ({1.0 / 1260.0!r} - inv2 / 1680.0)));
    }}
    """
    body = f"""
    const long long first = dim0;
    double count = 0.0;
    bool pending = false;
    if (lam < {_noise.PTRS_MIN_MEAN!r}) {{
        const double u = tofcore_u_open(key, i, first);
        double p = exp(-lam), cdf = p;
        for (int k = 1; k <= {_noise.INVERSION_TERMS}; ++k) {{
            count = count + (u > cdf ? 1.0 : 0.0);
            p = p * lam / (double)k;
            cdf = cdf + p;
        }}
    }} else if (lam < {_noise.GAUSSIAN_MIN_MEAN!r}) {{
        const double b = 0.931 + 2.53 * sqrt(lam);
        const double a = -0.059 + 0.02483 * b;
        const double log_inv_alpha = log(1.1239 + 1.1328 / (b - 3.4));
        const double v_r = 0.9277 - 3.6224 / (b - 2.0);
        const double log_lam = log(lam);
        pending = true;
        for (int r = 0; r < {_noise.PTRS_ROUNDS} && pending; ++r) {{
            const double u = tofcore_u_open(key, i, first + 1 + 2 * r) - 0.5;
            const double v = tofcore_u_open(key, i, first + 2 + 2 * r);
            const double us = 0.5 - fabs(u);
            double k = floor((2.0 * a / us + b) * u + lam + 0.43);
            k = k < -1.0 ? -1.0 : k;
            bool accepted = us >= 0.07 && v <= v_r;
            if (!accepted && k >= 0.0 && !(us < 0.013 && v > us)) {{
                const double hat = log(v) + log_inv_alpha - log(a / (us * us) + b);
                accepted = hat <= -lam + k * log_lam - tofcore_log_factorial(k);
            }}
            if (accepted) {{
                count = k < 0.0 ? 0.0 : k;
                pending = false;
            }}
        }}
    }} else {{
        pending = true;
    }}
    if (pending) {{
        const long long z_dim = first + 1 + 2 * {_noise.PTRS_ROUNDS};
        const double u1 = tofcore_u_open(key, i, z_dim), u2 = tofcore_u_open(key, i, z_dim + 1);
        const double z = sqrt(-2.0 * log(u1)) * cos(2.0 * {math.pi!r} * u2);
        const double x = floor(lam + sqrt(lam) * z + 0.5);
        count = x < 0.0 ? 0.0 : x;
    }}
    counts = count;
    """
    return cp.ElementwiseKernel("float64 lam, uint64 key, int64 dim0", "float64 counts", body,
                                "tofcore_poisson", preamble=preamble, options=_NO_FMA)


def poisson(mean, key, dim: int, *, check: bool = True):
    """:func:`tofcore.sensor.noise.poisson` for a CuPy array of means: the same loop per element, one kernel."""
    cp = backend.namespace(mean)
    lam = cp.ascontiguousarray(cp.asarray(mean, cp.float64))
    if check and not bool(cp.all(lam >= 0.0) & cp.all(cp.isfinite(lam))):
        raise _noise.ConfigError("poisson: mean must be finite and >= 0")
    return _poisson_kernel(cp)(lam, cp.uint64(int(key)), int(dim))
