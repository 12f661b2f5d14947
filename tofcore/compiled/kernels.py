r"""One path of the tracer as scalar functions: the source compiled for the CPU (and for CUDA).

Every function here is a scalar twin of the NumPy reference (the module and function it mirrors are
named in each docstring), written so that the compiled code performs the same IEEE operations in the
same order: float32 where the reference traverses the BVH in float32, float64 elsewhere, the same
counter-based random numbers and Sobol' dimensions, the same sums in sample order. What can still
differ is the last bit of the transcendental functions (NumPy's vectorised ``exp``/``log``/``sin``/
``cos``/``arccos``/``tan`` against the compiler's libm): tests/tofcore/test_compiled.py states the
tolerance that follows from it. Vectors are tuples (x, y, z); nothing allocates.

A surface point is the tuple ``(position, geometric_normal, tangent, bitangent, shading_normal,
params)`` with ``params`` the material record of :func:`surface_params` (its fields named by
:mod:`tofcore.compiled.layout` from the material table ``tofcore.scene.material.PARAMETERS``), as
:class:`tofcore.tracer.surface.Surface` and :class:`tofcore.scene.bsdf.SurfaceParams` hold them for N points.

Decorated by :func:`tofcore.compiled._target.device_function`: ``numba.njit`` when imported normally,
``numba.cuda.jit(device=True)`` when :mod:`tofcore.compiled.cuda` compiles this same file for CUDA.
The CPU driver :func:`trace_pixels` (numba threads over pixels) is here too, because numba's cache checks
only the stamp of a function's own file: everything the cached CPU code inlines must live in this file.
Constants read from the reference modules (rng, qmc, bsdf, …) are frozen into the machine code too, so
the cache folder is named after a hash of every constant defined above the decorators
(:func:`tofcore.compiled._target.constants_fingerprint`): a changed constant compiles anew. Function
bodies therefore read only this module's globals, never ``module.attribute`` of another module.

numba compiles a function once per argument type, and a constant argument (``0``, ``-1``, ``False``, a
global such as ``DIM_PIXEL``) has a type of its own (``Literal[int](0)``), as has a loop variable's first
value while numba infers the loop's types. So constants a call passes, and the first values of such
variables, go through ``np.int64(...)`` or ``bool(np.int64(0))``: each function compiles for its one
argument type, 86 overloads instead of 111, the kernels' first compile 21 s instead of 28 (2 cores). The
literal ``any_hit`` of :func:`traverse` is kept on purpose: a closest-hit and an any-hit traversal.
"""

from __future__ import annotations

import math

import numpy as np
from numba import config as numba_config, prange

from ..constants import SPEED_OF_LIGHT_M_S
from ..scene import bsdf as _bsdf
from ..scene.camera import _NEWTON_MAX_ITER, _NEWTON_STEP_TOL
from ..tracer import qmc as _qmc
from .. import rng as _rng
from ..tracer import sampler as _sampler
from ..tracer import surface as _surface
from ._target import cpu_parallel_function, device_function, gpu_kernel_function, gpu_module
from .layout import (COAT, COAT_ROUGHNESS, EXTINCTION, HARMONIC, IOR, LAMBERTIAN, LED_INTENSITY, LED_KIND, LED_POWER,
                     LED_PROBABILITY, LED_SKIP_FIRST_SHADOW, MATERIAL_COLUMNS, METALLIC, METALLIC_MAP, NORMAL_MAP,
                     N_COUNTERS, PHASOR, POINT, PULSED, REFLECTANCE, REFLECTANCE_MAP, ROUGHNESS, ROUGHNESS_MAP, SINE,
                     SQUARE, STACK_SIZE, STACK_T_SIZE, TABLE)

# ------------------------------------------------------------------ constants, from the reference modules
GOLDEN, MIX_PIXEL, MIX_SAMPLE, MIX_DIM = _rng._GOLDEN, _rng._MIX_PIXEL, _rng._MIX_SAMPLE, _rng._MIX_DIM
M1, M2 = _rng._M1, _rng._M2
S11, S27, S30, S31 = _rng._S11, _rng._S27, _rng._S30, _rng._S31
U0, U1, U2, U4, U8, U16, U24, U32 = (np.uint64(k) for k in (0, 1, 2, 4, 8, 16, 24, 32))
V31 = np.uint64(1 << 31)
MASK32 = np.uint64(0xFFFFFFFF)
BYTE = np.uint64(0xFF)
C55, C33, C0F, C00FF = (np.uint64(c) for c in (0x55555555, 0x33333333, 0x0F0F0F0F, 0x00FF00FF))
LK0, LK1, LK2, LK3 = (np.uint64(c) for c in _qmc._LK)
SOBOL = _qmc._SOBOL_DIM1_TABLES.astype(np.uint64)  # (4, 256) byte tables of Sobol' dimension 2
TO_UNIT = _qmc._TO_UNIT
INV_2_53 = 1.0 / 9007199254740992.0
REPLICATES = _qmc.REPLICATES
SEED_DIM_OFFSET = _qmc.SEED_DIM_OFFSET
DIM_PIXEL, DIM_LENS = _sampler.PIXEL, _sampler.LENS  # the sampler's one table (tofcore.tracer.sampler)
DIM_LED_CHOICE, DIM_EMISSION = _sampler.LED_CHOICE, _sampler.EMISSION
SMOOTH_ROUGHNESS_RAD = _bsdf.SMOOTH_ROUGHNESS_RAD
MIN_LOBE_PROBABILITY = _bsdf.MIN_LOBE_PROBABILITY
COAT_IOR = _bsdf.COAT_IOR
SPAWN_RELATIVE = _surface.SPAWN_RELATIVE
LEAVE_RELATIVE = _surface.LEAVE_RELATIVE
OFFSET_FLOOR_M = _surface.OFFSET_FLOOR_M
ONE_BELOW_ONE = float(np.nextafter(1.0, 0.0))
SQRT2 = float(np.sqrt(2.0))
PI = np.pi
PI_SQUARED = np.pi**2
TWO_PI = 2.0 * np.pi
QUARTER_PI = 0.25 * np.pi
HALF_PI = 0.5 * np.pi
TAN_HALF_PI = float(np.tan(HALF_PI))  # what the reference's tan(acos(0)) gives
INV_4PI = 1.0 / (4.0 * np.pi)
NEWTON_TOL = _NEWTON_STEP_TOL
NEWTON_MAX_ITER = _NEWTON_MAX_ITER
TINY_DIR = np.float32(1e-30)
F32_ZERO, F32_ONE = np.float32(0.0), np.float32(1.0)
F32_INF = np.float32(np.inf)
# Rows of the BVH records (tofcore.bvh): node = 6 plane rows + child row; leaf = 9 vertex rows + triangle row.
CHILD_ROW, PRIM_ROW, WIDTH = 6, 9, 4

# Below every constant: the decorators hash them all into the name of the cache folder (_target).
fn = device_function(__name__)
cpu_parallel = cpu_parallel_function(__name__)
gpu_kernel = gpu_kernel_function(__name__)
cuda = gpu_module(__name__)


# ------------------------------------------------------------------ float32 arithmetic, rounded as NumPy rounds it
# The GPU compiler fuses a multiply and an add into one FMA, rounded once; NumPy's float32 texture blend
# rounds each product and the sum (an ulp apart, 6e-8: more than the tests' 1e-9). CUDA's __fmul_rn and
# __fadd_rn are never fused; on the CPU (no contraction without fastmath) and in numba's CUDA simulator the
# plain operators round as NumPy does.
if cuda is None or numba_config.ENABLE_CUDASIM:
    @fn
    def mul32(a, b):
        return a * b

    @fn
    def add32(a, b):
        return a + b
else:
    from numba.cuda.libdevice import fadd_rn as add32, fmul_rn as mul32  # noqa: F401


# ------------------------------------------------------------------ vectors
@fn
def dot(a, b):
    """Dot product summed x, y, z in that order (tofcore.tracer.surface.dot)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@fn
def norm(a):
    """Euclidean length, ((x² + y²) + z²) then the square root (numpy.linalg.norm over 3 values)."""
    return math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])


@fn
def sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


@fn
def scale(a, s):
    return (a[0] * s, a[1] * s, a[2] * s)


@fn
def divide(a, s):
    return (a[0] / s, a[1] / s, a[2] / s)


@fn
def neg(a):
    return (-a[0], -a[1], -a[2])


@fn
def to_f32(a):
    return (np.float32(a[0]), np.float32(a[1]), np.float32(a[2]))


@fn
def rotate(v, rot):
    """``v @ R.T`` as tofcore.tracer.surface.rotate sums it: v_x R[:, 0] + v_y R[:, 1] + v_z R[:, 2].

    ``rot``: any array whose rows 0–2 hold R (the ``frame`` array of :func:`trace_path`).
    """
    return (v[0] * rot[0, 0] + v[1] * rot[0, 1] + v[2] * rot[0, 2],
            v[0] * rot[1, 0] + v[1] * rot[1, 1] + v[2] * rot[1, 2],
            v[0] * rot[2, 0] + v[1] * rot[2, 1] + v[2] * rot[2, 2])


# ------------------------------------------------------------------ random numbers (tofcore.rng, tofcore.qmc)
@fn
def splitmix(x):
    """SplitMix64's finaliser on a uint64 (tofcore.rng._splitmix)."""
    x = x + GOLDEN
    x = (x ^ (x >> S30)) * M1
    x = (x ^ (x >> S27)) * M2
    return x ^ (x >> S31)


@fn
def hash_bits(key, pixel, sample, dim):
    """64 random bits of (key, pixel, sample, dim) (tofcore.rng.bits)."""
    x = key ^ (np.uint64(pixel) * MIX_PIXEL) ^ (np.uint64(sample) * MIX_SAMPLE) ^ (np.uint64(dim) * MIX_DIM)
    return splitmix(splitmix(x))


@fn
def uniform(key, pixel, sample, dim):
    """A uniform in [0, 1) with 53 random bits (tofcore.rng.uniform)."""
    return np.float64(hash_bits(key, pixel, sample, dim) >> S11) * INV_2_53


@fn
def reverse_bits(x):
    """The 32 low bits of a uint64 reversed (tofcore.tracer.qmc.reverse_bits)."""
    x = ((x >> U1) & C55) | ((x & C55) << U1)
    x = ((x >> U2) & C33) | ((x & C33) << U2)
    x = ((x >> U4) & C0F) | ((x & C0F) << U4)
    x = ((x >> U8) & C00FF) | ((x & C00FF) << U8)
    return ((x >> U16) | (x << U16)) & MASK32


@fn
def owen_scramble(x, seed):
    """Hash-based Owen scramble of a 32-bit value (tofcore.tracer.qmc.owen_scramble), uint32 arithmetic."""
    x = (reverse_bits(x) + seed) & MASK32
    x = (x ^ (x * LK0)) & MASK32
    x = (x ^ (x * LK1)) & MASK32
    x = (x ^ (x * LK2)) & MASK32
    x = (x ^ (x * LK3)) & MASK32
    return reverse_bits(x)


@fn
def sobol_dim1_lookup(index):
    """Sobol' dimension 2 of a 32-bit index by four byte lookups (tofcore.tracer.qmc.sobol_2d)."""
    return (SOBOL[0, np.int64(index & BYTE)] ^ SOBOL[1, np.int64((index >> U8) & BYTE)]
            ^ SOBOL[2, np.int64((index >> U16) & BYTE)] ^ SOBOL[3, np.int64(index >> U24)])


@fn
def sobol_dim1_bits(index):
    """Sobol' dimension 2 of a 32-bit index bit by bit, the same number as :func:`sobol_dim1_lookup`: bit b
    of the index toggles v_b = m_b · 2^(31 − b) with m_0 = 1, m_(b+1) = m_b ⊕ 2 m_b, so v_(b+1) = v_b ⊕
    (v_b >> 1) (tofcore.tracer.qmc._sobol_dim1_tables). On the GPU a table would sit in constant memory, whose
    loads a warp serialises when its threads read different entries (wf_start stalled 114 cycles per
    instruction on them); 32 shifts and XORs in registers do not."""
    out = U0
    v = V31
    rest = index
    for _ in range(32):
        if rest & U1:
            out ^= v
        rest >>= U1
        v ^= v >> U1
    return out


sobol_dim1 = sobol_dim1_bits if cuda is not None else sobol_dim1_lookup
"""Sobol' dimension 2: by lookups on the CPU (its caches serve them in a few cycles), bit by bit on the GPU."""


@fn
def qmc_seeds(key, pixel, sample, dim):
    """(index, x, y scramble seeds, point index j) of a sample (tofcore.tracer.qmc._seeds)."""
    replicate = sample % REPLICATES
    bits = hash_bits(key, pixel, replicate, dim)
    more = hash_bits(key, pixel, replicate, dim + SEED_DIM_OFFSET)
    return bits & MASK32, bits >> U32, more & MASK32, np.uint64(sample // REPLICATES)


@fn
def sample_2d(key, pixel, sample, dim, independent):
    """Uniforms (u, v) of dimension pair ``dim`` (tofcore.tracer.qmc.sample_2d)."""
    if independent:
        return uniform(key, pixel, sample, 2 * dim), uniform(key, pixel, sample, 2 * dim + 1)
    s_index, s_x, s_y, j = qmc_seeds(key, pixel, sample, dim)
    i = owen_scramble(j, s_index)
    u = np.float64(owen_scramble(reverse_bits(i), s_x)) * TO_UNIT
    v = np.float64(owen_scramble(sobol_dim1(i), s_y)) * TO_UNIT
    return u, v


@fn
def sample_1d(key, pixel, sample, dim, independent):
    """A uniform of dimension ``dim`` (tofcore.tracer.qmc.sample_1d)."""
    if independent:
        return uniform(key, pixel, sample, 2 * dim)
    s_index, s_x, s_y, j = qmc_seeds(key, pixel, sample, dim)
    return np.float64(owen_scramble(reverse_bits(owen_scramble(j, s_index)), s_x)) * TO_UNIT


# ------------------------------------------------------------------ sampling (tofcore.sampling)
@fn
def concentric_disk(u1, u2):
    """Shirley–Chiu concentric map of the unit square onto the unit disk (sample_concentric_disk)."""
    a = 2.0 * u1 - 1.0
    b = 2.0 * u2 - 1.0
    if abs(a) > abs(b):
        radius = a
        phi = QUARTER_PI * b / (1.0 if radius == 0.0 else radius)
    else:
        radius = b
        phi = HALF_PI - QUARTER_PI * a / (1.0 if radius == 0.0 else radius)
    return radius * math.cos(phi), radius * math.sin(phi)


@fn
def cosine_hemisphere(u1, u2):
    """Cosine-weighted direction about +z (sample_cosine_hemisphere)."""
    x, y = concentric_disk(u1, u2)
    return (x, y, math.sqrt(max(1.0 - x * x - y * y, 0.0)))


# ------------------------------------------------------------------ camera (tofcore.camera.Camera.generate_rays)
@fn
def distort_with_jacobian(cam, x, y):
    """OpenCV distortion and its symmetric Jacobian (Camera._distort_with_jacobian); ``cam`` as in camera_ray."""
    k1, k2, p1, p2, k3 = cam[5], cam[6], cam[7], cam[8], cam[9]
    x2 = x * x
    y2 = y * y
    xy = x * y
    r2 = x2 + y2
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    radial_d = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2)
    yd = y * radial + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy
    j_xx = radial + 2.0 * x2 * radial_d + 2.0 * p1 * y + 6.0 * p2 * x
    j_xy = 2.0 * xy * radial_d + 2.0 * p1 * x + 2.0 * p2 * y
    j_yy = radial + 2.0 * y2 * radial_d + 6.0 * p1 * y + 2.0 * p2 * x
    return xd, yd, j_xx, j_xy, j_yy


@fn
def undistort_near(cam, table, xd, yd, row, col):
    """Newton's inverse of the distortion from the pixel's tabulated start (Camera._undistort_near)."""
    width, fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3], cam[4]
    i = np.int64(row * width + col)
    dxd = xd - (col - cx) / fx
    dyd = yd - (row - cy) / fy
    x = table[0, i] + table[2, i] * dxd + table[3, i] * dyd
    y = table[1, i] + table[3, i] * dxd + table[4, i] * dyd
    for _ in range(NEWTON_MAX_ITER):
        fxd, fyd, j_xx, j_xy, j_yy = distort_with_jacobian(cam, x, y)
        rx = fxd - xd
        ry = fyd - yd
        inv_det = 1.0 / (j_xx * j_yy - j_xy * j_xy)
        step_x = (j_yy * rx - j_xy * ry) * inv_det
        step_y = (j_xx * ry - j_xy * rx) * inv_det
        x = x - step_x
        y = y - step_y
        if max(abs(step_x), abs(step_y)) < NEWTON_TOL:
            return x, y
    return np.nan, np.nan


@fn
def camera_ray(cam, table, pixel, u_jitter, v_jitter, u_lens, v_lens):
    """Sensor-frame origin and unit direction of one camera sample (Camera._ray_block).

    ``cam`` = (width, fx, fy, cx, cy, k1, k2, p1, p2, k3, aperture_radius_m, focus_distance_m,
    has_distortion); ``table`` the camera's (5, P) centre table (x, y, inverse Jacobian xx, xy, yy).
    """
    width = np.int64(cam[0])
    row = pixel // width
    col = pixel - row * width
    xd = (col + (u_jitter - 0.5 - cam[3])) / cam[1]
    yd = (row + (v_jitter - 0.5 - cam[4])) / cam[2]
    x, y = xd, yd
    if cam[12] != 0.0:
        x, y = undistort_near(cam, table, xd, yd, row, col)
    ox, oy = 0.0, 0.0
    if cam[10] > 0.0:
        lens_x, lens_y = concentric_disk(u_lens, v_lens)
        ox = lens_x * cam[10]
        oy = lens_y * cam[10]
        x = x - ox / cam[11]
        y = y - oy / cam[11]
    inv_norm = 1.0 / math.sqrt(x * x + y * y + 1.0)
    return (ox, oy, 0.0), (x * inv_norm, y * inv_norm, inv_norm)


# ------------------------------------------------------------------ BVH traversal (tofcore.bvh)
@fn
def ray_frame(d):
    """float32 frame (b1, b2) perpendicular to the unit direction d (tofcore.scene.bvh._ray_frame)."""
    x, y, z = d
    sign = F32_ONE if z >= F32_ZERO else -F32_ONE
    a = -F32_ONE / (sign + z)
    b = x * y * a
    return (F32_ONE + sign * x * x * a, sign * b, -sign * x), (b, sign + y * y * a, -y)


@fn
def inverse_direction(d):
    """1/d per axis in float32, components below 1e-30 in magnitude replaced by ±1e-30
    (tofcore.scene.bvh._ray_records)."""
    return (F32_ONE / (d[0] if abs(d[0]) >= TINY_DIR else (-TINY_DIR if d[0] < F32_ZERO else TINY_DIR)),
            F32_ONE / (d[1] if abs(d[1]) >= TINY_DIR else (-TINY_DIR if d[1] < F32_ZERO else TINY_DIR)),
            F32_ONE / (d[2] if abs(d[2]) >= TINY_DIR else (-TINY_DIR if d[2] < F32_ZERO else TINY_DIR)))


# The four children's slab tests of a node at once, as LLVM vector instructions (issue 32's route (b): LLVM's
# SLP vectorizer did not pack the scalar loop by itself, so the vectors are written out). Each lane rounds as the
# scalar tests did: the float32 subtract and multiply, max and min as numba's max(a, b) = b if b > a else a (NaN as
# Python keeps it), and the ordered a <= b (tests/tofcore/test_kernel_twins.py holds it to the scalar loop bit for
# bit). CPU build only: the CUDA build never traverses here (the GPU traces with tofcore.gpu.traversal).
if cuda is None:
    from llvmlite import ir as _ir
    from numba import types as _types
    from numba.cpython.unsafe.numbers import trailing_zeros
    from numba.extending import intrinsic as _intrinsic

    @_intrinsic
    def slab_test(typingctx, planes, node, ex, ey, ez, o, inv, best_t):
        """(hit mask, entry distances) of the WIDTH children of the node whose first row is ``node``: bit c of the
        mask set where child c's box is entered at t_in[c] ≤ its exit clipped at ``best_t``; ``planes`` the
        (rows, WIDTH) float32 node planes, ``ex, ey, ez`` the entry-plane rows (:func:`traverse`), ``o``,
        ``inv`` float32 (x, y, z)."""
        f32 = _types.float32
        if not (isinstance(planes, _types.Array) and planes.dtype == f32 and planes.ndim == 2
                and planes.layout == "C" and o == _types.UniTuple(f32, 3) and inv == o and best_t == f32):
            return None
        signature = _types.Tuple((_types.int64, _types.UniTuple(f32, WIDTH)))(planes, node, ex, ey, ez, o, inv,
                                                                                best_t)

        def codegen(context, builder, sig, args):
            planes_v, node_v, ex_v, ey_v, ez_v, o_v, inv_v, best_v = args
            array = context.make_array(sig.args[0])(context, builder, planes_v)
            lanes = _ir.VectorType(_ir.FloatType(), WIDTH)
            i32, i64 = _ir.IntType(32), _ir.IntType(64)
            row_bytes = builder.extract_value(array.strides, 0)
            first = context.cast(builder, node_v, sig.args[1], _types.intp)
            base = builder.bitcast(array.data, _ir.IntType(8).as_pointer())

            def plane(row_offset, row_type, constant=0):
                row = builder.add(first, context.cast(builder, row_offset, row_type, _types.intp))
                if constant:
                    row = builder.add(row, _ir.Constant(row.type, constant))
                address = builder.gep(base, [builder.mul(row, row_bytes)])
                return builder.load(builder.bitcast(address, lanes.as_pointer()), align=4)

            def splat(value):
                one = builder.insert_element(_ir.Constant(lanes, _ir.Undefined), value, _ir.Constant(i32, 0))
                return builder.shuffle_vector(one, one, _ir.Constant(_ir.VectorType(i32, WIDTH), [0] * WIDTH))

            def larger(acc, v):  # numba's max(acc, v)
                return builder.select(builder.fcmp_ordered(">", v, acc), v, acc)

            def smaller(acc, v):  # numba's min(acc, v)
                return builder.select(builder.fcmp_ordered("<", v, acc), v, acc)

            near, far = [], []
            for axis, (entry, entry_type, opposite) in enumerate(((ex_v, sig.args[2], 3), (ey_v, sig.args[3], 5),
                                                                  (ez_v, sig.args[4], 7))):
                origin = splat(builder.extract_value(o_v, axis))
                scale = splat(builder.extract_value(inv_v, axis))
                near.append(builder.fmul(builder.fsub(plane(entry, entry_type), origin), scale))
                # the exit plane's row: node + opposite − entry
                exit_row = builder.sub(_ir.Constant(i64, opposite), context.cast(builder, entry, entry_type,
                                                                                  _types.intp))
                far.append(builder.fmul(builder.fsub(plane(exit_row, _types.intp), origin), scale))
            t_in = larger(larger(larger(near[0], near[1]), near[2]), _ir.Constant(lanes, [0.0] * WIDTH))
            t_out = smaller(smaller(smaller(far[0], far[1]), far[2]), splat(best_v))
            hits = builder.fcmp_ordered("<=", t_in, t_out)
            mask = builder.zext(builder.bitcast(hits, _ir.IntType(WIDTH)), i64)
            entries = context.make_tuple(builder, sig.return_type.types[1],
                                         [builder.extract_element(t_in, _ir.Constant(i32, c)) for c in range(WIDTH)])
            return context.make_tuple(builder, sig.return_type, [mask, entries])

        return signature, codegen


@fn
def push_child(stack, stack_t, top, first, child, t_in, any_hit):
    """Push ``child`` entered at ``t_in`` above stack[top − 1]; for a closest hit, insertion-sorted into the
    children pushed since ``first`` so the nearest is popped first. Returns the new top."""
    j = top
    while not any_hit and j > first and stack_t[j - 1] < t_in:
        stack[j] = stack[j - 1]
        stack_t[j] = stack_t[j - 1]
        j -= 1
    stack[j] = child
    stack_t[j] = t_in
    return top + 1


@fn
def traverse(bvh, o, d, t_max, ignore, any_hit, stack, stack_t):
    """Closest hit (or any hit) of one float32 ray over the 4-wide BVH records, with a per-ray stack.

    Same slab test as tofcore.scene.bvh.BVH._trace (entry plane chosen by the sign of the direction, tiny
    direction components replaced by ±1e-30 (:func:`inverse_direction`), boxes clipped at the best t so
    far) and the same watertight triangle test in float32 (the same products and sums in the same order;
    the divisions only once the ray is inside the triangle). For a closest hit, children are
    visited near to far (:func:`push_child`); an any-hit ray, whose answer does not depend on the order,
    visits them as they come. Returns (t, prim, u, v); prim −1 on a miss.
    ``bvh`` = (node planes, node children, leaf vertices, leaf triangles): the first four arrays of the
    scene tuple (tofcore.compiled.setup.scene_arrays); ``stack`` (int64, STACK_SIZE entries) and ``stack_t``
    (float32, STACK_T_SIZE) are scratch: the first row of a node record and its entry distance, and after the
    stack the WIDTH entry distances of the node being opened, which the loop over its entered children (set
    bits of the slab test's mask, lowest first: the order of the children) reads by index.
    """
    nodes_f, nodes_i, leaves_f, leaves_i = bvh
    children = stack_t.shape[0] - WIDTH  # the last WIDTH entries hold a node's children's entry distances
    inv = inverse_direction(d)
    # Entry-plane rows per axis: the box minimum (row a) for a positive direction, else the maximum (3 + a).
    ex, ey, ez = 3 if d[0] < F32_ZERO else 0, 4 if d[1] < F32_ZERO else 1, 5 if d[2] < F32_ZERO else 2
    b1, b2 = ray_frame(d)
    best_t, best_prim, best_u, best_v = t_max, -1, F32_ZERO, F32_ZERO
    stack[0] = 0
    stack_t[0] = F32_ZERO
    top = 1
    while top > 0:
        top -= 1
        if stack_t[top] > best_t:
            continue
        node = stack[top]
        first = top  # the children entered go to stack[first:top], far (bottom) to near (top)
        mask, entries = slab_test(nodes_f, node, ex, ey, ez, o, inv, best_t)
        if mask == 0:
            continue
        stack_t[children], stack_t[children + 1], stack_t[children + 2], stack_t[children + 3] = entries
        while mask != 0:  # the children whose boxes the ray enters before the best t so far, in order
            c = trailing_zeros(mask)  # one branch per child entered, not four per node
            mask &= mask - 1
            t_in = stack_t[children + c]
            # best_t may have fallen since the test (a leaf before c): the exit clipped at it again, as before
            if not t_in <= best_t:
                continue
            child = nodes_i[node + CHILD_ROW, c]
            if child >= 0:
                top = push_child(stack, stack_t, top, first, child, t_in, any_hit)
                continue
            row = ~child  # a leaf: its triangles now (tofcore.bvh._watertight written out: a call costs)
            for k in range(leaves_i.shape[1]):
                prim = leaves_i[row + PRIM_ROW, k]
                if prim < 0 or prim == ignore:
                    continue
                ax, ay, az = leaves_f[row, k] - o[0], leaves_f[row + 1, k] - o[1], leaves_f[row + 2, k] - o[2]
                px, py, pz = leaves_f[row + 3, k] - o[0], leaves_f[row + 4, k] - o[1], leaves_f[row + 5, k] - o[2]
                cx, cy, cz = leaves_f[row + 6, k] - o[0], leaves_f[row + 7, k] - o[1], leaves_f[row + 8, k] - o[2]
                a1, a2 = ax * b1[0] + ay * b1[1] + az * b1[2], ax * b2[0] + ay * b2[1] + az * b2[2]
                p1, p2 = px * b1[0] + py * b1[1] + pz * b1[2], px * b2[0] + py * b2[1] + pz * b2[2]
                c1, c2 = cx * b1[0] + cy * b1[1] + cz * b1[2], cx * b2[0] + cy * b2[1] + cz * b2[2]
                w_u, w_v, w_w = c1 * p2 - c2 * p1, a1 * c2 - a2 * c1, p1 * a2 - p2 * a1
                # The edge functions share a sign (zero counts as both): only then the divisions.
                if not ((w_u >= F32_ZERO and w_v >= F32_ZERO and w_w >= F32_ZERO)
                        or (w_u <= F32_ZERO and w_v <= F32_ZERO and w_w <= F32_ZERO)):
                    continue
                det = w_u + w_v + w_w
                t = (w_u * (ax * d[0] + ay * d[1] + az * d[2]) + w_v * (px * d[0] + py * d[1] + pz * d[2])
                     + w_w * (cx * d[0] + cy * d[1] + cz * d[2])) / det
                if not (t > F32_ZERO and t < best_t):
                    continue
                if any_hit:
                    return t, prim, w_v / det, w_w / det
                best_t, best_prim, best_u, best_v = t, prim, w_v / det, w_w / det
    return best_t, best_prim, best_u, best_v


@fn
def intersect(geo, o, d, t_max, ignore, any_hit, work):
    """:func:`traverse` over the scene tuple ``geo`` (see tofcore.compiled.setup.scene_arrays) with the
    stacks of ``work``. Only the four BVH arrays go on: every array passed costs its fields in each call."""
    return traverse((geo[0], geo[1], geo[2], geo[3]), o, d, t_max, ignore, any_hit, work[1], work[2])


@fn
def point_offset(p, relative):
    """``relative`` × the largest coordinate of p, at least OFFSET_FLOOR_M (tofcore.tracer.surface.point_offset)."""
    return relative * max(max(abs(p[0]), abs(p[1]), abs(p[2])), OFFSET_FLOOR_M)


@fn
def spawn_offset(geo, prim, position, ng):
    """The distance a ray leaving ``position`` on triangle ``prim`` starts off it along ``ng``
    (tofcore.tracer.surface.spawn_offset: the point's coordinates or its triangle's, pbrt-v4's bound)."""
    triangles, vertices = geo[4], geo[5]
    i0, i1, i2 = triangles[prim, 0], triangles[prim, 1], triangles[prim, 2]
    own = max(abs(position[0]), abs(position[1]), abs(position[2]))
    c0 = np.float64(max(abs(vertices[i0, 0]), abs(vertices[i1, 0]), abs(vertices[i2, 0])))
    c1 = np.float64(max(abs(vertices[i0, 1]), abs(vertices[i1, 1]), abs(vertices[i2, 1])))
    c2 = np.float64(max(abs(vertices[i0, 2]), abs(vertices[i1, 2]), abs(vertices[i2, 2])))
    local = abs(ng[0]) * c0 + abs(ng[1]) * c1 + abs(ng[2]) * c2
    return SPAWN_RELATIVE * max(max(own, local), OFFSET_FLOOR_M)


@fn
def shadow_ray(spawn, target, margin_m):
    """float32 origin, unit direction and t_max of a ray stopping ``margin_m`` short of ``target``
    (tofcore.tracer.surface.shadow_ray)."""
    to_target = sub(target, spawn)
    length = norm(to_target)
    direction = divide(to_target, length if length > 0.0 else 1.0)
    return to_f32(spawn), to_f32(direction), np.float32(length - margin_m)


# ------------------------------------------------------------------ surfaces (tofcore.surface.surface_at)
@fn
def orthonormal_basis(n):
    """Tangent and bitangent completing the unit normal n (Duff et al. 2017; surface.orthonormal_basis)."""
    sign = 1.0 if n[2] >= 0 else -1.0
    a = -1.0 / (sign + n[2])
    b = n[0] * n[1] * a
    return (1.0 + sign * (n[0] * n[0]) * a, sign * b, -sign * n[0]), (b, sign + (n[1] * n[1]) * a, -n[1])


@fn
def hit_point(geo, prim, u, v, ray_origin, ray_direction):
    """(position, geometric normal facing the ray) where a float64 ray hits triangle ``prim`` at float32
    barycentrics (u, v): the float64 ray–plane point o + t d, t = (v₀ − o)·n_g / (d·n_g), or the barycentric
    point where the ray grazes the plane (|d·n_g| ≤ 1e-9) (tofcore.tracer.surface.surface_geometry)."""
    triangles, vertices, face_normals = geo[4], geo[5], geo[6]
    i0, i1, i2 = triangles[prim, 0], triangles[prim, 1], triangles[prim, 2]
    ng = (np.float64(face_normals[prim, 0]), np.float64(face_normals[prim, 1]), np.float64(face_normals[prim, 2]))
    p0 = (np.float64(vertices[i0, 0]), np.float64(vertices[i0, 1]), np.float64(vertices[i0, 2]))
    cos_ray = dot(ray_direction, ng)
    if abs(cos_ray) > 1e-9:
        t = dot(sub(p0, ray_origin), ng) / cos_ray
        position = (ray_origin[0] + t * ray_direction[0], ray_origin[1] + t * ray_direction[1],
                    ray_origin[2] + t * ray_direction[2])
    else:
        w0 = np.float64(F32_ONE - u - v)
        u64 = np.float64(u)
        v64 = np.float64(v)
        position = (w0 * p0[0] + u64 * vertices[i1, 0] + v64 * vertices[i2, 0],
                    w0 * p0[1] + u64 * vertices[i1, 1] + v64 * vertices[i2, 1],
                    w0 * p0[2] + u64 * vertices[i1, 2] + v64 * vertices[i2, 2])
    if dot(ng, ray_direction) > 0:
        return position, (ng[0] * -1.0, ng[1] * -1.0, ng[2] * -1.0)
    return position, (ng[0] * 1.0, ng[1] * 1.0, ng[2] * 1.0)


@fn
def surface_at(geo, prim, u, v, ray_origin, ray_direction):
    """The surface tuple where a float64 ray hits triangle ``prim`` at float32 barycentrics (u, v), its
    material's textures applied (tofcore.tracer.surface.surface_at)."""
    triangles, vertices, normals, material_ids, materials = geo[4], geo[5], geo[7], geo[8], geo[9]
    i0, i1, i2 = triangles[prim, 0], triangles[prim, 1], triangles[prim, 2]
    w0 = np.float64(F32_ONE - u - v)
    u64 = np.float64(u)
    v64 = np.float64(v)
    position, ng = hit_point(geo, prim, u, v, ray_origin, ray_direction)
    if normals.shape[0] > 0:
        ns = (w0 * normals[i0, 0] + u64 * normals[i1, 0] + v64 * normals[i2, 0],
              w0 * normals[i0, 1] + u64 * normals[i1, 1] + v64 * normals[i2, 1],
              w0 * normals[i0, 2] + u64 * normals[i1, 2] + v64 * normals[i2, 2])
        ns = divide(ns, norm(ns))
    else:
        ns = ng
    m = material_ids[prim]
    reflectance, roughness, metallic = materials[m, REFLECTANCE], materials[m, ROUGHNESS], materials[m, METALLIC]
    slots = geo[11]
    if slots[m, REFLECTANCE_MAP] >= 0 or slots[m, ROUGHNESS_MAP] >= 0 or slots[m, METALLIC_MAP] >= 0 \
            or slots[m, NORMAL_MAP] >= 0:
        uvs, textures = geo[10], (geo[12], geo[13])
        tex_u = w0 * uvs[i0, 0] + u64 * uvs[i1, 0] + v64 * uvs[i2, 0]
        tex_v = w0 * uvs[i0, 1] + u64 * uvs[i1, 1] + v64 * uvs[i2, 1]
        if slots[m, REFLECTANCE_MAP] >= 0:
            reflectance = np.float64(texture_sample(textures, slots[m, REFLECTANCE_MAP], tex_u, tex_v, np.int64(0)))
        if slots[m, ROUGHNESS_MAP] >= 0:
            roughness = np.float64(texture_sample(textures, slots[m, ROUGHNESS_MAP], tex_u, tex_v, np.int64(0)))
        if slots[m, METALLIC_MAP] >= 0:
            metallic = np.float64(texture_sample(textures, slots[m, METALLIC_MAP], tex_u, tex_v, np.int64(0)))
        normal_map = slots[m, NORMAL_MAP]
        if normal_map >= 0:
            c = dot(ns, ng)
            side = 1.0 if c > 0 else (-1.0 if c < 0 else 0.0)  # np.sign
            rgb = (texture_sample(textures, normal_map, tex_u, tex_v, np.int64(0)),
                   texture_sample(textures, normal_map, tex_u, tex_v, np.int64(1)),
                   texture_sample(textures, normal_map, tex_u, tex_v, np.int64(2)))
            ns = perturb_normal(geo, prim, scale(ns, side), rgb)
    ns = scale(ns, -1.0 if dot(ns, ng) < 0 else 1.0)
    tangent, bitangent = orthonormal_basis(ns)
    params = surface_params(min(max(reflectance, 0.0), 1.0), max(roughness, 0.0), min(max(metallic, 0.0), 1.0),
                            materials[m, IOR], materials[m, EXTINCTION], materials[m, COAT],
                            materials[m, COAT_ROUGHNESS])
    return position, ng, tangent, bitangent, ns, params


@fn
def surface_params(reflectance, roughness, metallic, ior, extinction, coat, coat_roughness):
    """The ``params`` record of a surface point (tofcore.scene.bsdf.SurfaceParams): its fields in the order of
    layout.MATERIAL_COLUMNS (the material table), read by name (params[REFLECTANCE], …)."""
    return (reflectance, roughness, metallic, ior, extinction, coat, coat_roughness)


# ------------------------------------------------------------------ textures (tofcore.scene.material, ambient)
#   textures = (table (T, 4) int64: offset, height, width, channels of each image; data: every image's
#               float32 texels, row-major (H, W, C), one after the other)    tofcore.compiled.setup.texture_store
@fn
def texture_sample(textures, t, u, v, c):
    """Channel c of texture t at UV (u, v) (float64; (0, 0) the bottom-left corner), float32: bilinear
    between the four texel centres around the point, repeat wrapping (Texture.sample)::

        x = u W − ½,  y = (1 − v) H − ½,  f_x = x − ⌊x⌋,  f_y = y − ⌊y⌋
        value = (d₀₀ (1 − f_x) + d₀₁ f_x)(1 − f_y) + (d₁₀ (1 − f_x) + d₁₁ f_x) f_y     (float32)
    """
    table, data = textures
    offset, h, w, channels = table[t, 0], table[t, 1], table[t, 2], table[t, 3]
    x = u * w - 0.5
    y = (1.0 - v) * h - 0.5
    x0 = math.floor(x)
    y0 = math.floor(y)
    fx = np.float32(x - x0)
    fy = np.float32(y - y0)
    col0 = np.int64(x0) % w
    row0 = np.int64(y0) % h
    col1 = (col0 + 1) % w
    row1 = (row0 + 1) % h
    d00 = data[offset + (row0 * w + col0) * channels + c]
    d01 = data[offset + (row0 * w + col1) * channels + c]
    d10 = data[offset + (row1 * w + col0) * channels + c]
    d11 = data[offset + (row1 * w + col1) * channels + c]
    top = add32(mul32(d00, F32_ONE - fx), mul32(d01, fx))
    bottom = add32(mul32(d10, F32_ONE - fx), mul32(d11, fx))
    return add32(mul32(top, F32_ONE - fy), mul32(bottom, fy))


@fn
def perturb_normal(geo, prim, n, rgb):
    """The shading normal n bent by a tangent-space normal map's RGB (float32, [0, 1]) (surface._perturb).

    The tangent follows increasing u on the triangle (dP/du from its UVs, Gram–Schmidt against n; the
    basis of n where the UVs are degenerate); the bitangent is n × t; m = 2 rgb − 1 and the normal is
    normalise(m_x t + m_y b + max(m_z, 10⁻³) n).
    """
    triangles, vertices, uvs = geo[4], geo[5], geo[10]
    i0, i1, i2 = triangles[prim, 0], triangles[prim, 1], triangles[prim, 2]
    p0 = (np.float64(vertices[i0, 0]), np.float64(vertices[i0, 1]), np.float64(vertices[i0, 2]))
    e1 = sub((np.float64(vertices[i1, 0]), np.float64(vertices[i1, 1]), np.float64(vertices[i1, 2])), p0)
    e2 = sub((np.float64(vertices[i2, 0]), np.float64(vertices[i2, 1]), np.float64(vertices[i2, 2])), p0)
    d1u = np.float64(uvs[i1, 0]) - np.float64(uvs[i0, 0])
    d1v = np.float64(uvs[i1, 1]) - np.float64(uvs[i0, 1])
    d2u = np.float64(uvs[i2, 0]) - np.float64(uvs[i0, 0])
    d2v = np.float64(uvs[i2, 1]) - np.float64(uvs[i0, 1])
    det = d1u * d2v - d2u * d1v
    dpdu = ((e1[0] * d2v - e2[0] * d1v) / det, (e1[1] * d2v - e2[1] * d1v) / det,
            (e1[2] * d2v - e2[2] * d1v) / det)
    fallback = orthonormal_basis(n)[0]
    if not (math.isfinite(dpdu[0]) and math.isfinite(dpdu[1]) and math.isfinite(dpdu[2])):
        dpdu = fallback
    along = dot(dpdu, n)
    t = (dpdu[0] - along * n[0], dpdu[1] - along * n[1], dpdu[2] - along * n[2])
    length = norm(t)
    t = divide(t, max(length, 1e-300)) if length > 1e-12 else fallback
    b = (n[1] * t[2] - n[2] * t[1], n[2] * t[0] - n[0] * t[2], n[0] * t[1] - n[1] * t[0])
    mx, my, mz = 2.0 * np.float64(rgb[0]) - 1.0, 2.0 * np.float64(rgb[1]) - 1.0, 2.0 * np.float64(rgb[2]) - 1.0
    mz = max(mz, 1e-3)
    bent = (mx * t[0] + my * b[0] + mz * n[0], mx * t[1] + my * b[1] + mz * n[1], mx * t[2] + my * b[2] + mz * n[2])
    return divide(bent, norm(bent))


@fn
def ambient_radiance(sky, textures, radiance, d):
    """Ambient radiance (W m⁻² sr⁻¹) seen looking along unit world direction d (Ambient.radiance): the
    constant ``radiance`` plus, where ``sky`` = (strength, texture index) names an environment map, strength
    × the map at Blender's equirectangular coordinates (float32 product)::

        u = atan2(d_y, −d_x) / 2π + ½,   v = clip(atan2(d_z, hypot(d_x, d_y)) / π + ½, ½/H, 1 − ½/H)
    """
    t = np.int64(sky[1])
    if t < 0:
        return radiance
    u = math.atan2(d[1], -d[0]) / TWO_PI + 0.5
    v = math.atan2(d[2], math.hypot(d[0], d[1])) / PI + 0.5
    h = textures[0][t, 1]
    v = min(max(v, 0.5 / h), 1.0 - 0.5 / h)
    return radiance + np.float64(mul32(np.float32(sky[0]), texture_sample(textures, t, u, v, np.int64(0))))


@fn
def add_transient(film, pixel, w, length, bin_m):
    """Weight w of path length L into row ``pixel`` of the path-length histogram ``film`` (P, B), split
    between the two nearest bin centres (b + ½)·bin_m so that Σw and Σw·L are kept inside the range
    (accumulate.Tally._add_transient): x = L / bin_m − ½, w(1 − frac x) to bin ⌊x⌋, w frac x to ⌊x⌋ + 1."""
    n_bins = film.shape[1]
    x = length / bin_m - 0.5
    below = math.floor(x)
    if not (below >= -1.0 and below < n_bins):
        return
    frac = x - below
    b = np.int64(below)
    lower = w * (1.0 - frac)
    upper = w * frac
    if b >= 0 and lower != 0:
        film[pixel, b] += lower
    if b + 1 < n_bins and upper != 0:
        film[pixel, b + 1] += upper


@fn
def to_local(surf, w):
    """World direction into the shading frame (Surface.to_local)."""
    return dot(w, surf[2]), dot(w, surf[3]), dot(w, surf[4])


@fn
def to_world(surf, w):
    """Shading-frame direction into the world frame (Surface.to_world)."""
    t, b, n = surf[2], surf[3], surf[4]
    return (w[0] * t[0] + w[1] * b[0] + w[2] * n[0], w[0] * t[1] + w[1] * b[1] + w[2] * n[1],
            w[0] * t[2] + w[1] * b[2] + w[2] * n[2])


# ------------------------------------------------------------------ reflection (tofcore.fresnel, tofcore.bsdf)
@fn
def fresnel_dielectric(cos_theta_i, eta):
    """Unpolarised dielectric Fresnel reflectance seen from air (fresnel.fresnel_dielectric, eq. 2.19–2.21)."""
    cos_1 = min(max(cos_theta_i, 0.0), 1.0)
    sin2_2 = (1.0 - cos_1 * cos_1) / (eta * eta)
    if sin2_2 >= 1.0:
        return 1.0
    cos_2 = math.sqrt(max(1.0 - sin2_2, 0.0))
    r_parallel = (eta * cos_1 - cos_2) / (eta * cos_1 + cos_2)
    r_perpendicular = (cos_1 - eta * cos_2) / (cos_1 + eta * cos_2)
    return 0.5 * (r_parallel * r_parallel + r_perpendicular * r_perpendicular)


@fn
def fresnel_conductor(cos_theta_i, eta, k):
    """Unpolarised conductor Fresnel reflectance (fresnel.fresnel_conductor, eq. 2.22–2.23)."""
    cos_i = min(max(cos_theta_i, 0.0), 1.0)
    eta2_k2 = eta * eta + k * k
    two_eta_cos = 2.0 * eta * cos_i
    cos2 = cos_i * cos_i
    r_parallel2 = (eta2_k2 * cos2 - two_eta_cos + 1.0) / (eta2_k2 * cos2 + two_eta_cos + 1.0)
    denominator = eta2_k2 + two_eta_cos + cos2
    r_perpendicular2 = (eta2_k2 - two_eta_cos + cos2) / denominator if denominator > 0.0 else 1.0
    return 0.5 * (r_parallel2 + r_perpendicular2)


@fn
def specular_fresnel(params, cos_theta):
    """(1 − m) F_d + m F_c (bsdf.specular_fresnel); the pure cases are the reference's per-batch shortcuts."""
    metallic, ior, extinction = params[METALLIC], params[IOR], params[EXTINCTION]
    if metallic == 0.0:
        return fresnel_dielectric(cos_theta, ior)
    if metallic == 1.0:
        return fresnel_conductor(cos_theta, ior, extinction)
    return (1.0 - metallic) * fresnel_dielectric(cos_theta, ior) + metallic * fresnel_conductor(cos_theta, ior,
                                                                                               extinction)


@fn
def outgoing(params, cos_o):
    """(F_d(cos θ_o), P_s, F_d(cos θ_o; η_c), P_c): the terms of ω_o alone (bsdf._outgoing); the coat's two
    are 0 without a coat."""
    reflectance, metallic, ior = params[REFLECTANCE], params[METALLIC], params[IOR]
    fresnel_o = fresnel_dielectric(cos_o, ior)
    specular = specular_fresnel(params, cos_o) if metallic != 0.0 else fresnel_o
    diffuse = (1.0 - metallic) * (1.0 - fresnel_o) * reflectance
    total = specular + diffuse
    share = specular / (total if total > 0.0 else 1.0)
    has_specular = metallic > 0.0 or ior != 1.0
    if has_specular and diffuse > 0.0:
        probability = min(max(share, MIN_LOBE_PROBABILITY), 1.0 - MIN_LOBE_PROBABILITY)
    else:
        probability = 1.0 if has_specular else 0.0
    coat_fresnel_o = 0.0
    coat_probability = 0.0
    if params[COAT] > 0.0:
        coat_fresnel_o = fresnel_dielectric(cos_o, COAT_IOR)
        coat = params[COAT] * coat_fresnel_o
        base = (1.0 - coat) * total
        coat_total = coat + base
        coat_share = min(max(coat / (coat_total if coat_total > 0.0 else 1.0), MIN_LOBE_PROBABILITY),
                         1.0 - MIN_LOBE_PROBABILITY)
        if coat > 0.0:
            coat_probability = coat_share if base > 0.0 else 1.0
    return fresnel_o, probability, coat_fresnel_o, coat_probability


@fn
def rough_alpha(roughness):
    """Beckmann α = √2 σ of a specular lobe of roughness σ, or 0 for a mirror lobe (bsdf._rough_alpha)."""
    return SQRT2 * roughness if roughness >= SMOOTH_ROUGHNESS_RAD else 0.0


@fn
def beckmann_distribution(cos_theta, alpha):
    """Beckmann D(ω_h) (sampling.beckmann_distribution, eq. 2.26)."""
    if not (cos_theta > 1e-12 and alpha > 1e-50):
        return 0.0
    cos2 = cos_theta * cos_theta
    alpha2 = alpha * alpha
    tan2_theta = (1.0 - cos2) / cos2
    return math.exp(-tan2_theta / alpha2) / (PI * alpha2 * cos2 * cos2)


@fn
def half_vector(wo, wi):
    """Normalised ω_o + ω_i, the normal where the sum vanishes (bsdf._half_vector)."""
    total = (wo[0] + wi[0], wo[1] + wi[1], wo[2] + wi[2])
    length = norm(total)
    if length > 0.0:
        return divide(total, length)
    return (0.0, 0.0, 1.0)


@fn
def oren_nayar(reflectance, roughness, cos_theta_i, cos_theta_o, cos_phi):
    """Oren–Nayar f_r without cosine (bsdf.oren_nayar, eq. 2.28–2.30).

    The reference's sin θ_max, tan θ_min and tan((θ_max + θ_min)/2) from the cosines, without calling sin and
    tan (7 % of a thread's profile): sin θ = √(1 − cos²θ), tan θ = sin θ / cos θ and the half-angle identity
    tan((a + b)/2) = (sin a + sin b) / (cos a + cos b); the same values to rounding (≈ 1e-16 relative). θ_max is
    the angle of the smaller cosine; both cosines 0 (a grazing pair, never shaded) gives the reference's
    tan(π/2)."""
    s = roughness * roughness
    cos_i = min(max(cos_theta_i, 0.0), 1.0)
    cos_o = min(max(cos_theta_o, 0.0), 1.0)
    cos_min_angle, cos_max_angle = max(cos_i, cos_o), min(cos_i, cos_o)  # cos θ_min, cos θ_max
    theta_max = math.acos(cos_max_angle)
    theta_min = math.acos(cos_min_angle)
    sin_max = math.sqrt(1.0 - cos_max_angle * cos_max_angle)
    sin_min = math.sqrt(1.0 - cos_min_angle * cos_min_angle)
    tan_min = sin_min / cos_min_angle if cos_min_angle > 0.0 else TAN_HALF_PI
    cos_sum = cos_max_angle + cos_min_angle
    tan_mid = (sin_max + sin_min) / cos_sum if cos_sum > 0.0 else TAN_HALF_PI
    scaled_min = 2.0 * theta_min / PI
    c1 = 1.0 - 0.5 * s / (s + 0.33)
    c2 = 0.45 * s / (s + 0.09) * (sin_max - (scaled_min * scaled_min * scaled_min if cos_phi < 0.0 else 0.0))
    root_c3 = 4.0 * theta_max * theta_min / PI_SQUARED
    c3 = 0.125 * s / (s + 0.09) * (root_c3 * root_c3)
    direct = (reflectance / PI) * (c1 + cos_phi * c2 * tan_min + (1.0 - abs(cos_phi)) * c3 * tan_mid)
    interreflection = 0.17 * reflectance * reflectance / PI * s / (s + 0.13) * (1.0 - cos_phi * (scaled_min * scaled_min))
    return max(direct + interreflection, 0.0)


@fn
def cos_azimuth_difference(wo, wi):
    """cos(φ_o − φ_i), 0 where a direction lies on the normal (bsdf.cos_azimuth_difference); the product of the
    planar lengths as one square root, √((x_o² + y_o²)(x_i² + y_i²)), not two hypot calls (2.6 % of a thread's
    profile; the same to rounding for unit vectors, which cannot overflow)."""
    planar_dot = wo[0] * wi[0] + wo[1] * wi[1]
    planar_norms = math.sqrt((wo[0] * wo[0] + wo[1] * wo[1]) * (wi[0] * wi[0] + wi[1] * wi[1]))
    if not planar_norms > 0.0:
        return 0.0
    return min(max(planar_dot / planar_norms, -1.0), 1.0)


@fn
def eval_terms(params, wo, wi, fresnel_o, coat_fresnel_o):
    """f_r and the direction pair's terms ``pair`` = (cos θ_i, valid, h, ω_o·ω_h, α, D, α_c, D_c) (bsdf._pair and
    bsdf._eval; the coat's α_c and D_c are 0 without a coat)."""
    cos_o, cos_i = wo[2], wi[2]
    h = half_vector(wo, wi)
    cos_oh = wo[0] * h[0] + wo[1] * h[1] + wo[2] * h[2]
    alpha = rough_alpha(params[ROUGHNESS])
    distribution = beckmann_distribution(h[2], alpha)
    coat = params[COAT]
    coat_alpha = 0.0
    coat_distribution = 0.0
    if coat > 0.0:
        coat_alpha = rough_alpha(params[COAT_ROUGHNESS])
        coat_distribution = beckmann_distribution(h[2], coat_alpha)
    valid = cos_o > 0.0 and cos_i > 0.0
    pair = (cos_i, valid, h, cos_oh, alpha, distribution, coat_alpha, coat_distribution)
    if not valid:
        return 0.0, pair
    transmitted = (1.0 - fresnel_dielectric(cos_i, params[IOR])) * (1.0 - fresnel_o)
    diffuse = (1.0 - params[METALLIC]) * transmitted * oren_nayar(params[REFLECTANCE], params[ROUGHNESS], cos_i,
                                                                  cos_o, cos_azimuth_difference(wo, wi))
    # V-cavity G (eq. 2.27) and Torrance–Sparrow (eq. 2.24)
    geometry = 0.0
    if cos_oh > 0.0:
        geometry = min(1.0, 2.0 * max(h[2], 0.0) / cos_oh * min(max(cos_o, 0.0), max(cos_i, 0.0)))
    denominator = 4.0 * (cos_i * cos_o)
    specular = 0.0
    if denominator > 0.0:
        specular = specular_fresnel(params, cos_oh) * distribution * geometry / denominator
    if not coat > 0.0:
        return diffuse + specular, pair
    # the clear coat: c f_TS(F_d(ω_i·ω_h; η_c), α_c) + (1 − c F_c(θ_i))(1 − c F_c(θ_o)) f_base
    through = (1.0 - coat * fresnel_dielectric(cos_i, COAT_IOR)) * (1.0 - coat * coat_fresnel_o)
    coat_specular = 0.0
    if denominator > 0.0:
        coat_specular = fresnel_dielectric(cos_oh, COAT_IOR) * coat_distribution * geometry / denominator
    return coat * coat_specular + through * (diffuse + specular), pair


@fn
def specular_density(wo, h, cos_oh, alpha, distribution):
    """Solid-angle density of reflecting ω_o about a V-cavity visible normal h of roughness α: D_ωo(h) / (4 ω_o·ω_h),
    0 for a mirror (sampling.pdf_vcavity_visible_normal, times the reflection's Jacobian as bsdf._pdf)."""
    if not (cos_oh > 0.0 and alpha > 0.0):
        return 0.0
    reflect_jacobian = 1.0 / (4.0 * cos_oh)
    visible = max(wo[0] * h[0] + wo[1] * h[1] + wo[2] * h[2], 0.0)
    visible_other = max(wo[0] * -h[0] + wo[1] * -h[1] + wo[2] * h[2], 0.0)
    total = visible + visible_other
    share = visible / (total if total > 0.0 else 1.0)
    return 2.0 * (distribution * max(h[2], 0.0)) * share * reflect_jacobian


@fn
def pdf_terms(wo, lobes, pair):
    """Solid-angle density of the non-delta lobes (bsdf._pdf): ``lobes`` = (P_s, P_c), ``pair`` as eval_terms
    returns it; with a coat P_c p_coat + (1 − P_c) p_base."""
    probability, coat_probability = lobes
    cos_i, valid, h, cos_oh, alpha, distribution, coat_alpha, coat_distribution = pair
    if not valid:
        return 0.0
    specular = specular_density(wo, h, cos_oh, alpha, distribution)
    density = probability * specular + (1.0 - probability) * (max(cos_i, 0.0) / PI)
    if coat_probability > 0.0:
        coat = specular_density(wo, h, cos_oh, coat_alpha, coat_distribution)
        density = coat_probability * coat + (1.0 - coat_probability) * density
    return density


@fn
def coat_fresnel(params, cos_o):
    """F_d(cos θ_o; η_c) where the point has a coat, else 0 (what outgoing returns for it)."""
    return fresnel_dielectric(cos_o, COAT_IOR) if params[COAT] > 0.0 else 0.0


@fn
def eval_bsdf(params, wo, wi):
    """f_r (1/sr) without the cosine (bsdf.eval_bsdf)."""
    return eval_terms(params, wo, wi, fresnel_dielectric(wo[2], params[IOR]), coat_fresnel(params, wo[2]))[0]


@fn
def eval_pdf_bsdf(params, wo, wi):
    """(f_r, pdf) of one direction pair (bsdf.eval_pdf_bsdf)."""
    fresnel_o, probability, coat_fresnel_o, coat_probability = outgoing(params, wo[2])
    f, pair = eval_terms(params, wo, wi, fresnel_o, coat_fresnel_o)
    return f, pdf_terms(wo, (probability, coat_probability), pair)


@fn
def reflect_visible_normal(wo, alpha, u1, u2, u_swap):
    """ω_o reflected about a V-cavity visible normal of roughness α drawn from (u1, u2, u_swap), or about the
    normal for α = 0 (sampling.sample_vcavity_visible_normal and bsdf._reflect)."""
    m = (0.0, 0.0, 1.0)
    if alpha > 0.0:
        tan2_theta = -alpha * alpha * math.log1p(-u1)
        cos_theta = 1.0 / math.sqrt(1.0 + tan2_theta)
        sin_theta = math.sqrt(tan2_theta) * cos_theta
        phi = TWO_PI * u2
        m = (sin_theta * math.cos(phi), sin_theta * math.sin(phi), cos_theta)
        visible = max(wo[0] * m[0] + wo[1] * m[1] + wo[2] * m[2], 0.0)
        visible_other = max(wo[0] * -m[0] + wo[1] * -m[1] + wo[2] * m[2], 0.0)
        if u_swap * (visible + visible_other) >= visible and visible_other > 0.0:
            m = (-m[0], -m[1], m[2])
    c = 2.0 * (wo[0] * m[0] + wo[1] * m[1] + wo[2] * m[2])
    return c * m[0] - wo[0], c * m[1] - wo[1], c * m[2] - wo[2]


@fn
def sample_bsdf(params, wo, u_lobe, u1, u2):
    """(wi, weight, pdf, is_delta) of one BSDF sample (bsdf.sample_bsdf); see its contract. With a coat its
    lobe is picked first (u_lobe < P_c), the base's lobes share the rest of u_lobe."""
    cos_o = wo[2]
    fresnel_o, probability, coat_fresnel_o, coat_probability = outgoing(params, cos_o)
    pick_coat = False
    u_coat = 0.0
    if coat_probability > 0.0:
        pick_coat = u_lobe < coat_probability
        u_coat = min(max(u_lobe / coat_probability, 0.0), ONE_BELOW_ONE)
        u_lobe = min(max((u_lobe - coat_probability) / (1.0 - coat_probability if coat_probability < 1.0 else 1.0),
                         0.0), ONE_BELOW_ONE)
    if pick_coat:
        coat_alpha = rough_alpha(params[COAT_ROUGHNESS])
        wi = reflect_visible_normal(wo, coat_alpha, u1, u2, u_coat)
        if coat_alpha == 0.0 and cos_o > 0.0:  # the coat's mirror: reflectance c F_c(θ_o)
            return wi, params[COAT] * coat_fresnel_o / coat_probability, coat_probability, True
    else:
        pick_specular = u_lobe < probability
        if pick_specular:
            u_swap = u_lobe / (probability if probability > 0.0 else 1.0)
        else:
            u_swap = (u_lobe - probability) / (1.0 - probability if probability < 1.0 else 1.0)
        u_swap = min(max(u_swap, 0.0), ONE_BELOW_ONE)
        alpha = rough_alpha(params[ROUGHNESS])
        if pick_specular:
            wi = reflect_visible_normal(wo, alpha, u1, u2, u_swap)
        else:
            wi = cosine_hemisphere(u1, u2)
        if pick_specular and alpha == 0.0 and cos_o > 0.0:  # the base's mirror: a delta lobe
            mirror_fresnel = specular_fresnel(params, cos_o) if params[METALLIC] != 0.0 else fresnel_o
            if coat_probability > 0.0:  # seen through the coat twice, (1 − c F_c(θ_o))²
                through = 1.0 - params[COAT] * coat_fresnel_o
                pick = (1.0 - coat_probability) * probability
                return wi, through * through * mirror_fresnel / (pick if pick > 0.0 else 1.0), pick, True
            return wi, mirror_fresnel / (probability if probability > 0.0 else 1.0), probability, True
    f, pair = eval_terms(params, wo, wi, fresnel_o, coat_fresnel_o)
    pdf = pdf_terms(wo, (probability, coat_probability), pair)
    f_cos = f * max(pair[0], 0.0)
    return wi, (f_cos / pdf if pdf > 0.0 else 0.0), pdf, False


# ------------------------------------------------------------------ LEDs (tofcore.led) and correlations (tofcore.modulation)
@fn
def led_intensity(kind, intensity_w_sr, cos_axis):
    """I(θ) in W/sr (LED.intensity, eq. 2.8–2.9)."""
    if kind == POINT:
        return intensity_w_sr
    return intensity_w_sr * max(cos_axis, 0.0)


@fn
def emission_pdf(kind, cos_axis):
    """Solid-angle density of the LED's emission sampling (LED.emission_pdf)."""
    if kind == POINT:
        return INV_4PI
    return max(cos_axis, 0.0) / PI


@fn
def sample_emission(kind, u1, u2):
    """An emission direction in the LED frame, ∝ I(θ) (LED.sample_emission)."""
    if kind == LAMBERTIAN:
        return cosine_hemisphere(u1, u2)
    z = 1.0 - 2.0 * u1
    r = math.sqrt(max(1.0 - z * z, 0.0))
    phi = TWO_PI * u2
    return (r * math.cos(phi), r * math.sin(phi), z)


@fn
def correlation(kind, par, data, tau):
    """g_j(τ) of one channel; ``par`` is its row of tofcore.compiled.setup.correlation_table, ``data`` the
    channels' shared coefficients (a harmonic series' or a table's values).

    PHASOR cos(2πf τ − qπ/2) (modulation.phasor_component; the tracer's channel loops use
    :func:`channel_value`); SINE ½ + cos(2π(fτ − k/N))/π; SQUARE the clipped triangle/trapezoid of
    modulation.square_correlation; PULSED clip(1 − |τ/t0 − b|, 0, 1);
    HARMONIC a₀ + Σₙ aₙ cos(nφ) + bₙ sin(nφ), φ = 2πfτ (modulation.harmonic_correlation); TABLE the
    periodic table linearly interpolated (modulation.tabulated_correlation).
    """
    if kind == PHASOR:  # par: 2πf, qπ/2
        return math.cos(par[0] * tau - par[1])
    if kind == SINE:  # par: f, k/N
        return math.cos((par[0] * tau - par[1]) * TWO_PI) / PI + 0.5
    if kind == SQUARE:  # par: f, k/N, duty D, lower clip, upper clip, ¼ + D/2
        shifted = par[0] * tau - par[1] + 0.5
        u = abs(shifted - math.floor(shifted) - 0.5)
        return min(max(par[5] - u, par[3]), par[4]) / par[2]
    if kind == HARMONIC:  # par: 2πf, first coefficient, N; data: a₀, a₁ … a_N, b₁ … b_N
        phase = par[0] * tau
        first, n_harmonics = np.int64(par[1]), np.int64(par[2])
        total = data[first]
        for n in range(1, n_harmonics + 1):
            a, b = data[first + n], data[first + n_harmonics + n]
            total = total + (a * math.cos(n * phase) + b * math.sin(n * phase))
        return total
    if kind == TABLE:  # par: period T, first value, M; data: g(iT/M)
        first, m = np.int64(par[1]), np.int64(par[2])
        cycles = tau / par[0]
        x = (cycles - math.floor(cycles)) * m
        i = math.floor(x)
        t = x - i
        i0 = np.int64(i) % m
        return data[first + i0] * (1.0 - t) + data[first + (i0 + 1) % m] * t
    return min(max(1.0 - abs(tau / par[0] - par[1]), 0.0), 1.0)  # PULSED, par: t0, bucket


NO_PHASE = (-1.0, 0.0, 0.0)
"""The phase a channel loop starts :func:`channel_value` with: no phasor channel evaluated yet (2πf is never −1)."""


@fn
def channel_value(kind, par, data, tau, phase):
    """(g_j(τ), ``phase``) as :func:`correlation`, for a loop over the channels in order: a PHASOR channel's
    cos(2πfτ − qπ/2) is c·cos(qπ/2) + s·sin(qπ/2) from ``phase`` = (2πf, c = cos 2πfτ, s = sin 2πfτ), computed
    once per frequency and handed on, so the cos and sin channels of one frequency share one ``sincos`` (the
    cross-check's six phasor channels took 12–17 % of its corner trace). ``par[2]``, ``par[3]`` are cos(qπ/2)
    and sin(qπ/2), exact (0, ±1). Against the reference, the cos channel (q = 0) is the same bits; the sin
    channel is sin 2πfτ, where the reference rounds 2πfτ − π/2 first: ≈ 1e-15 apart. Other kinds:
    :func:`correlation`."""
    if kind != PHASOR:
        return correlation(kind, par, data, tau), phase
    if par[0] != phase[0]:
        angle = par[0] * tau
        phase = (par[0], math.cos(angle), math.sin(angle))
    return phase[1] * par[2] + phase[2] * par[3], phase


# ------------------------------------------------------------------ one path (tofcore.transport._trace_chunk)
#
# The path's arguments travel in tuples (numba compiles heterogeneous tuples of arrays and scalars):
#   scene    = (geo, cam, cam_table, frame, leds, corr_kinds, corr_table,     the render's arrays
#               corr_data, sky)
#   settings = (key, max_depth, independent, light_paths, ambient,            the render's switches, its constant
#               transient_bin_m)                                               ambient radiance, W/(m² sr), and its
#                                                                              transient bin width (0: none)
#   rng      = (key, pixel, sample, independent)                               one sample's random numbers
#   vertex   = (surface, spawn point, wo in the local frame, triangle index)  a camera vertex x
#   state    = (throughput β, depth, bsdf_area_pdf, prev_delta, use_mis)      the path at x
#   light    = (found, surface of y, y → LED, |y − LED|, emitted, p_B, margin) the light vertex (light_vertex)
#   sums     = (nee_w, nee_wg, con_w, con_wg, total, film)                     a pixel's sums (trace_path); film:
#                                                                              the frame's transient histogram
#   work     = (counters, stack, stack_t, wg)                                  scratch (traverse, trace_path)
@fn
def led_estimate(frame, leds, vertex, state, i):
    """Next-event estimate to LED ``i`` before its shadow test: (w, distance to the LED, the LED's position)
    (stages._to_led before its shadow test)."""
    surf, spawn, wo, prim = vertex
    throughput, depth, bsdf_area_pdf, prev_delta, use_mis = state
    led_positions, led_table = leds[0], leds[1]
    position, ng, ns, params = surf[0], surf[1], surf[4], surf[5]
    led = (led_positions[i, 0], led_positions[i, 1], led_positions[i, 2])
    to_led = sub(led, position)
    dist = norm(to_led)
    wi_world = divide(to_led, dist)
    cos_geo = dot(wi_world, ng)
    cos_shading = dot(wi_world, ns)
    cos_axis = -dot(wi_world, (frame[4, 0], frame[4, 1], frame[4, 2]))
    kind = np.int64(led_table[i, LED_KIND])
    f = eval_bsdf(params, wo, to_local(surf, wi_world))
    w = throughput * f * max(cos_shading, 0.0) * led_intensity(kind, led_table[i, LED_INTENSITY], cos_axis) / (dist * dist)
    if not cos_geo > 0:
        w = 0.0
    if use_mis:  # strategy A's balance-heuristic weight (light_paths.bsdf_strategy_weight)
        p_light = led_table[i, LED_PROBABILITY] * emission_pdf(kind, cos_axis) * max(cos_geo, 0.0) / (dist * dist)
        share = bsdf_area_pdf / (bsdf_area_pdf + p_light) if bsdf_area_pdf + p_light > 0 else 1.0
        w = w * (1.0 if prev_delta else share)
    return w, dist, led


@fn
def connect_led(geo, frame, leds, vertex, state, i, work):
    """Next-event estimate to LED ``i``, shadow test included: (w, distance to the LED) (stages._to_led)."""
    w, dist, led = led_estimate(frame, leds, vertex, state, i)
    counters = work[0]
    if w > 0:
        if state[1] == 1 and leds[1][i, LED_SKIP_FIRST_SHADOW] != 0.0:  # the camera ray proved this LED sees the first hit
            counters[4] += 1
        else:
            o, d, t_max = shadow_ray(vertex[1], led, point_offset(led, SPAWN_RELATIVE))
            counters[2] += 1
            if intersect(geo, o, d, t_max, vertex[3], True, work)[1] >= 0:
                w = 0.0
    return w, dist


@fn
def light_ray(frame, leds, rng):
    """The ray of the sample's light vertex (light_paths.trace_light_vertices): (LED index, its position,
    the float64 emission direction, its pdf, the float32 query origin and direction)."""
    key, pixel, sample, independent = rng
    led_positions, led_table, led_cdf = leds[0], leds[1], leds[2]
    u_led = sample_1d(key, pixel, sample, np.int64(DIM_LED_CHOICE), independent)
    index = 0
    for c in range(led_cdf.shape[0]):
        if u_led >= led_cdf[c]:
            index += 1
    u1, u2 = sample_2d(key, pixel, sample, np.int64(DIM_EMISSION), independent)
    kind = np.int64(led_table[index, LED_KIND])
    local = sample_emission(kind, u1, u2)
    pdf_dir = led_table[index, LED_PROBABILITY] * emission_pdf(kind, local[2])
    direction = rotate(local, frame)
    origin = (led_positions[index, 0], led_positions[index, 1], led_positions[index, 2])
    offset = point_offset(origin, LEAVE_RELATIVE)
    query = to_f32((origin[0] + offset * direction[0], origin[1] + offset * direction[1],
                    origin[2] + offset * direction[2]))
    return index, origin, direction, pdf_dir, query, to_f32(direction)


@fn
def light_vertex_at(geo, leds, ray, prim, u, v):
    """The ``light`` tuple where the light ray ``ray`` (:func:`light_ray`) hits (prim, u, v); prim −1: none.

    (found, surface of y facing the LED, unit direction y → LED, |y − LED|, emitted, p_B, the margin
    a shadow ray to y stops short of it: 4 × y's spawn offset).
    """
    index, origin, direction, pdf_dir = ray[0], ray[1], ray[2], ray[3]
    led_table = leds[1]
    surf = surface_at(geo, max(prim, 0), u, v, origin, direction)
    if prim < 0 or not pdf_dir > 0:
        return False, surf, direction, 0.0, 0.0, 0.0, 0.0
    to_led = neg(direction)
    led_distance = norm(sub(surf[0], origin))
    cos_geo = dot(to_led, surf[1])
    cos_shading = max(dot(to_led, surf[4]), 0.0)
    q = led_table[index, LED_PROBABILITY]
    emitted = led_table[index, LED_POWER] / (q if q > 0 else 1.0) * cos_shading / cos_geo if cos_geo > 0 else 0.0
    margin = 4.0 * spawn_offset(geo, prim, surf[0], surf[1])
    if not led_distance > point_offset(origin, LEAVE_RELATIVE):  # an LED on (or behind) the surface it lights
        return True, surf, to_led, led_distance, 0.0, 0.0, margin
    return True, surf, to_led, led_distance, emitted, pdf_dir * abs(cos_geo) / (led_distance * led_distance), margin


@fn
def light_vertex(geo, frame, leds, rng, work):
    """The sample's light vertex y (light_paths.trace_light_vertices): the ``light`` tuple of :func:`light_vertex_at`."""
    ray = light_ray(frame, leds, rng)
    work[0][3] += 1
    t, prim, u, v = intersect(geo, ray[4], ray[5], F32_INF, np.int64(-1), False, work)
    return light_vertex_at(geo, leds, ray, prim, u, v)


@fn
def light_estimate(vertex, throughput, light):
    """Strategy B at camera vertex x before its shadow test: (w_B, extra path length |x − y| + |y − LED|)
    (light_paths.connect)."""
    x, spawn, wo, prim = vertex
    y, y_to_led, y_led_distance, y_emitted, y_pdf_area = light[1], light[2], light[3], light[4], light[5]
    to_y = sub(y[0], x[0])
    dist = norm(to_y)
    if not dist > 0:
        dist = np.inf
    w_xy = divide(to_y, dist)
    cos_x = dot(w_xy, x[1])
    cos_y = -dot(w_xy, y[1])
    f_x, pdf_x = eval_pdf_bsdf(x[5], wo, to_local(x, w_xy))
    f_y = eval_bsdf(y[5], to_local(y, neg(w_xy)), to_local(y, y_to_led))
    g = max(dot(w_xy, x[4]), 0.0) * max(cos_y, 0.0) / (dist * dist)
    w = throughput * f_x * g * f_y * y_emitted
    p_bsdf = pdf_x * max(cos_y, 0.0) / (dist * dist)
    if cos_x > 0 and cos_y > 0 and w > 0:
        w = w * y_pdf_area / (p_bsdf + y_pdf_area)
    else:
        w = 0.0
    return w, dist + y_led_distance


@fn
def connect_light(geo, vertex, throughput, light, work):
    """Strategy B at camera vertex x, shadow test included: (w_B, extra path length) (light_paths.connect)."""
    w, extra = light_estimate(vertex, throughput, light)
    if w > 0:
        # Stop short of y by a few ray offsets, so y's own surface does not occlude it.
        o, d, t_max = shadow_ray(vertex[1], light[1][0], light[6])
        work[0][2] += 1
        if intersect(geo, o, d, t_max, vertex[3], True, work)[1] >= 0:
            w = 0.0
    return w, extra


@fn
def camera_start(scene, rng):
    """Scene-frame origin and unit direction of the sample's camera ray (stages.camera_rays)."""
    cam, cam_table, frame = scene[1], scene[2], scene[3]
    key, pixel, sample, independent = rng
    pixel_u, pixel_v = sample_2d(key, pixel, sample, np.int64(DIM_PIXEL), independent)
    lens_u, lens_v = sample_2d(key, pixel, sample, np.int64(DIM_LENS), independent)
    o_s, d_s = camera_ray(cam, cam_table, pixel, pixel_u, pixel_v, lens_u, lens_v)
    o_w = rotate(o_s, frame)
    origin = (o_w[0] + frame[3, 0], o_w[1] + frame[3, 1], o_w[2] + frame[3, 2])
    return origin, rotate(d_s, frame)


@fn
def ray_query(origin, direction, depth):
    """The float32 origin of the path's ray at ``depth``: the camera ray (depth 1) leaves the lens by
    LEAVE_RELATIVE of its coordinates, the others start at their spawn point."""
    if depth == 1:
        offset = point_offset(origin, LEAVE_RELATIVE)
        return to_f32((origin[0] + offset * direction[0], origin[1] + offset * direction[1],
                       origin[2] + offset * direction[2]))
    return to_f32(origin)


@fn
def next_hit(geo, origin, direction, depth, prev_prim, work):
    """(prim, u, v) where the path's ray from ``origin`` hits (prim −1 on a miss)."""
    work[0][0 if depth == 1 else 1] += 1
    t, prim, u, v = intersect(geo, ray_query(origin, direction, depth), to_f32(direction), F32_INF, prev_prim,
                              False, work)
    return prim, u, v


@fn
def camera_vertex(geo, prim, surf, direction):
    """The ``vertex`` tuple of a hit: its surface, the point a ray leaving it starts from, wo, prim."""
    position, ng = surf[0], surf[1]
    offset = spawn_offset(geo, prim, position, ng)
    spawn = (position[0] + ng[0] * offset, position[1] + ng[1] * offset, position[2] + ng[2] * offset)
    return surf, spawn, to_local(surf, neg(direction)), prim


@fn
def add_next_events(scene, vertex, state, path_length, film, sums, work):
    """Next-event estimation to every LED at the vertex, summed in LED order, added to bucket depth − 1
    of ``nee_w``/``nee_wg``, to the path's ``total`` and, with ``film`` = (pixel, bin width > 0), to the
    pixel's transient histogram (stages.next_event)."""
    geo, frame, leds, corr_kinds, corr_table, corr_data = scene[0], scene[3], scene[4], scene[5], scene[6], scene[7]
    nee_w, nee_wg, total = sums[0], sums[1], sums[4]
    wg = work[3]
    n_corr = corr_kinds.shape[0]
    w_sum = 0.0
    for j in range(n_corr):
        wg[j] = 0.0
    for i in range(leds[0].shape[0]):
        w, led_distance = connect_led(geo, frame, leds, vertex, state, i, work)
        length = path_length + led_distance
        if film[1] > 0:
            add_transient(sums[5], film[0], w, length, film[1])
        tau = length / SPEED_OF_LIGHT_M_S
        w_sum += w
        phase = NO_PHASE
        for j in range(n_corr):
            g, phase = channel_value(corr_kinds[j], corr_table[j], corr_data, tau, phase)
            wg[j] += g * w
    k = state[1] - 1
    nee_w[k] += w_sum
    total[0] += w_sum
    for j in range(n_corr):
        nee_wg[k, j] += wg[j]
        total[1 + j] += wg[j]


@fn
def add_connection(scene, vertex, state, path_length, light, film, sums, work):
    """The connection vertex → light vertex → its LED (depth + 1 surface vertices), added to bucket
    ``depth`` of ``con_w``/``con_wg``, to the path's ``total`` and the pixel's transient histogram
    (stages.light_vertex)."""
    corr_kinds, corr_table, corr_data = scene[5], scene[6], scene[7]
    con_w, con_wg, total = sums[2], sums[3], sums[4]
    depth = state[1]
    w = 0.0
    extra = 0.0
    if light[0]:
        w, extra = connect_light(scene[0], vertex, state[0], light, work)
    length = path_length + extra
    if film[1] > 0:
        add_transient(sums[5], film[0], w, length, film[1])
    tau = length / SPEED_OF_LIGHT_M_S
    con_w[depth] += w
    total[0] += w
    phase = NO_PHASE
    for j in range(corr_kinds.shape[0]):
        g, phase = channel_value(corr_kinds[j], corr_table[j], corr_data, tau, phase)
        wg_j = g * w
        con_wg[depth, j] += wg_j
        total[1 + j] += wg_j


@fn
def next_direction(surf, wo, rng, depth):
    """The BSDF-sampled world direction leaving the vertex at ``depth``, its weight, pdf and whether it
    is a mirror lobe (stages.scatter)."""
    key, pixel, sample, independent = rng
    u1, u2 = sample_2d(key, pixel, sample, 2 * depth + 1, independent)
    u_lobe = sample_1d(key, pixel, sample, 2 * depth, independent)
    wi, weight, pdf, is_delta = sample_bsdf(surf[5], wo, u_lobe, u1, u2)
    return to_world(surf, wi), weight, pdf, is_delta


@fn
def trace_path(scene, settings, pixel, sample, sums, work):
    """Trace sample ``sample`` of pixel ``pixel`` and add its contributions (integrator.trace_chunk for one path).

    ``scene`` = (geo, cam, cam_table, frame, leds, corr_kinds, corr_table, corr_data, sky); ``settings`` =
    (key, max_depth, independent, light_paths, ambient radiance, transient bin width). Adds to the pixel's
    ``sums`` of next-event contributions ``nee_w`` (K,) and ``nee_wg`` (K, J) and of light-vertex connections
    ``con_w``, ``con_wg`` per bounce bucket, in the order the reference adds them, writes the path's channel
    totals (signal, J correlations, ambient) to ``total`` (J + 2,) and, with a bin width > 0, adds its
    weights over path length to row ``pixel`` of the histogram ``film`` (P, B) (in sample order, not in
    the reference's order of its per-chunk histograms: the same addends, summed in another order).
    ``work`` = (counters (layout.N_COUNTERS,) int64 ray counts, stack, stack_t, wg (J,)
    scratch). ``frame`` holds the world_from_sensor rotation (rows 0–2), the lens centre and the LED axis
    in the scene frame (rows 3, 4); ``leds`` = (positions (L, 3), table (L, 5): kind, intensity, power,
    emission probability, first-hit shadow skipped; cdf (L − 1,)).
    """
    geo = scene[0]
    key, max_depth, independent, light_paths, ambient, transient_bin_m = settings
    rng = (key, pixel, sample, independent)
    film = (pixel, transient_bin_m)
    total = sums[4]
    for c in range(total.shape[0]):
        total[c] = 0.0
    # Strategy B's light vertex of this sample (light_paths.trace_light_vertices); without light paths a
    # placeholder of the same type that is never used.
    if light_paths:
        light = light_vertex(geo, scene[3], scene[4], rng, work)
    else:
        y = surface_at(geo, np.int64(0), F32_ZERO, F32_ZERO, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
        light = (bool(np.int64(0)), y, (0.0, 0.0, 1.0), 0.0, 0.0, 0.0, 0.0)
    origin, direction = camera_start(scene, rng)
    prev_point = origin
    throughput = 1.0      # β
    path_length = 0.0     # metres from the lens
    prev_prim = np.int64(-1)  # triangle the ray leaves
    prev_pdf = 0.0        # solid-angle pdf of the bounce that led here
    prev_delta = bool(np.int64(0))  # ... and whether it was a mirror lobe (False)
    for depth in range(1, max_depth + 1):
        prim, u, v = next_hit(geo, origin, direction, depth, prev_prim, work)
        if prim < 0:  # the ray left the scene: it sees the ambient radiance, β · L_amb (stages.intersect)
            total[total.shape[0] - 1] += throughput * ambient_radiance(scene[8], (geo[12], geo[13]), ambient,
                                                                       direction)
            break
        surf = surface_at(geo, prim, u, v, origin, direction)
        position, ng = surf[0], surf[1]
        segment = norm(sub(position, prev_point))
        path_length = path_length + segment
        vertex = camera_vertex(geo, prim, surf, direction)
        use_mis = light_paths and depth >= 2
        bsdf_area_pdf = prev_pdf * dot(neg(direction), ng) / (segment * segment) if use_mis else 0.0
        state = (throughput, depth, bsdf_area_pdf, prev_delta, use_mis)
        add_next_events(scene, vertex, state, path_length, film, sums, work)
        if depth == max_depth:
            break
        if light_paths:
            add_connection(scene, vertex, state, path_length, light, film, sums, work)
        new_dir, weight, pdf, is_delta = next_direction(surf, vertex[2], rng, depth)
        # A direction below the geometric surface would leak through it (shading normals): end the path.
        if not (weight > 0 and dot(new_dir, ng) > 0):
            break
        throughput = throughput * weight
        prev_pdf, prev_delta = pdf, is_delta
        prev_prim = prim
        prev_point = position
        origin = vertex[1]
        direction = divide(new_dir, norm(new_dir))


@cpu_parallel
def trace_pixels(scene, settings, pixels, out):
    """Trace samples [first[p], first[p] + counts[p]) of pixels p0 ≤ p < p1 into the frame's sums
    (integrator.trace_chunk).

    ``scene`` and ``settings`` as in :func:`trace_path`; ``pixels`` = (p0, p1, first, counts); ``out`` =
    (signal_sum (K, P), correlation_sum (K, J, P), replicate_sum (R, J + 2, P), ambient_sum (P,), transient_sum
    (P, B) (B = 0 without a histogram) as in :class:`tofcore.tracer.transport.Transport`, counters (p1 − p0,
    N_COUNTERS) receiving each pixel's ray counts).
    """
    # numba's parallel loop takes arrays, scalars and flat tuples of arrays, not a tuple of tuples:
    # the scene is unpacked here and packed again inside the loop.
    geo, cam, cam_table, frame, leds, corr_kinds, corr_table, corr_data, sky = scene
    key, max_depth, independent, light_paths, ambient, transient_bin_m = settings
    p0, p1, first, counts = pixels
    signal_sum, correlation_sum, replicate_sum, ambient_sum, transient_sum, counters = out
    n_depth = signal_sum.shape[0]
    n_corr = corr_kinds.shape[0]
    n_rep = replicate_sum.shape[0]
    n_ch = n_corr + 2
    for local in prange(p1 - p0):
        p = p0 + local
        nee_w = np.zeros(n_depth)
        con_w = np.zeros(n_depth)
        nee_wg = np.zeros((n_depth, n_corr))
        con_wg = np.zeros((n_depth, n_corr))
        total = np.zeros(n_ch)
        replicate = np.zeros((n_rep, n_ch))
        count = np.zeros(N_COUNTERS, np.int64)
        work = (count, np.empty(STACK_SIZE, np.int64), np.empty(STACK_T_SIZE, np.float32), np.zeros(n_corr))
        sums = (nee_w, nee_wg, con_w, con_wg, total, transient_sum)
        seen = 0.0  # the pixel's ambient radiance of this pass (accumulate.Tally.finish)
        for sample in range(first[p], first[p] + counts[p]):
            trace_path((geo, cam, cam_table, frame, leds, corr_kinds, corr_table, corr_data, sky),
                       (key, max_depth, independent, light_paths, ambient, transient_bin_m), p, sample, sums, work)
            r = sample % n_rep
            for c in range(n_ch):
                replicate[r, c] += total[c]
            seen += total[n_ch - 1]
        for k in range(n_depth):
            signal_sum[k, p] += con_w[k]
            signal_sum[k, p] += nee_w[k]
            for j in range(n_corr):
                correlation_sum[k, j, p] += con_wg[k, j]
                correlation_sum[k, j, p] += nee_wg[k, j]
        for r in range(n_rep):
            for c in range(n_ch):
                replicate_sum[r, c, p] += replicate[r, c]
        ambient_sum[p] += seen
        for c in range(N_COUNTERS):
            counters[local, c] = count[c]


FIRST_HIT_BLOCK = 1024
"""Rays of the ground truth a thread traces with one stack (:func:`first_hits`)."""


@cpu_parallel
def first_hits(geo, lens, directions, out):
    """The noise-free ground truth's rays from the lens centre ``lens`` (scene frame) along unit ``directions``
    (R, 3) float64, on numba's threads (tofcore.tracer.stages.first_hit's traversal and hit geometry): each
    ray leaves the lens as a camera ray does (:func:`ray_query`), traverses the BVH in float32, and where it
    hits gets the float64 point and facing normal of :func:`hit_point`. ``out`` = (prim (R,) int32, −1 on a miss;
    point (R, 3) float64, normal (R, 3) float64, both left as they were on a miss)."""
    prim_out, point_out, normal_out = out
    n = directions.shape[0]
    for block in prange((n + FIRST_HIT_BLOCK - 1) // FIRST_HIT_BLOCK):
        work = (np.zeros(N_COUNTERS, np.int64), np.empty(STACK_SIZE, np.int64), np.empty(STACK_T_SIZE, np.float32))
        for i in range(block * FIRST_HIT_BLOCK, min(n, (block + 1) * FIRST_HIT_BLOCK)):
            d = (directions[i, 0], directions[i, 1], directions[i, 2])
            prim, u, v = next_hit(geo, lens, d, np.int64(1), np.int64(-1), work)
            prim_out[i] = prim
            if prim < 0:
                continue
            point, normal = hit_point(geo, prim, u, v, lens, d)
            for a in range(3):
                point_out[i, a] = point[a]
                normal_out[i, a] = normal[a]


GPU_MAX_CHANNELS = 32
"""Correlation channels + 2 a GPU thread holds (local arrays need their size when compiling)."""


# ------------------------------------------------------------------ GPU wavefront: the path in stages
#
# The same path as trace_path, cut where it traces rays: each kernel advances every path of a launch
# group by one stage and leaves its rays in buffers that tofcore.gpu.traversal (a lean kernel, one thread
# per ray, bit for bit the NumPy traversal) traces in between; tofcore.compiled.cuda.trace_pass drives
# them. A group holds the paths of sample indices s0 ≤ s < s1 of a pass: with offsets[s] the pass's paths
# of sample indices below s, path j of the group has sample index l where offsets[l] ≤ offsets[s0] + j <
# offsets[l + 1] and is pixel order[offsets[s0] + j − offsets[l]]; the group has n = offsets[s1] −
# offsets[s0] paths. The buffers below are the pass's, sized for its largest group (rows j ≥ n unused),
# so a launch's arguments are the same from group to group (tofcore.compiled.launch).
# Per-path state in global memory, column j of (values, paths) tables, so that a warp's threads read and
# write neighbouring words (rows of (n, 3) only for the rays the traversal reads, 12 bytes a ray):
#   path    = (pixel, sample, alive, shaded)                  int64 ×2, int8 ×2
#   pstate  = (f (13, n), prev_prim (n,))                     f: β, path length, prev pdf, prev delta,
#                                                             prev point xyz, origin xyz, direction xyz
#   rays    = (origin (n, 3) f32, direction (n, 3) f32, ignore (n,) i32, t_max (n,) f32)   the next
#             closest-hit ray; t_max −1 for a path that has ended (the traversal leaves it at the root)
#   hits    = (prim (n,) i32, u (n,) f32, v (n,) f32)
#   light   = (28, n) float64: the light tuple of light_vertex_at, flattened (LIGHT_* rows)
#   pend    = (w (L + 1, n), length (L + 1, n))               next-event estimates (LED i) and the
#                                                             connection (row L) before their shadow test,
#                                                             and their path lengths
#   shadow  = (origin (n(L+1), 3), direction, t_max, ignore)  their shadow rays; t_max −1: no test
#   contrib = (nee (J + 1, n), con (J + 1, n))   the path's addends of the current depth: weight and
#             channels of its next-event estimates (bucket depth − 1) and of its connection (bucket depth);
#             total (J + 2, n) its channel totals; counters (N_COUNTERS, n) its rays
# wf_gather adds each depth's addends per pixel in sample order: the pass's sums are the CPU's, addend by addend.
LIGHT_FOUND, LIGHT_SURF, LIGHT_PARAMS = 0, 1, 16  # the flag, 5 vectors of the surface, its material record
LIGHT_TO_LED = LIGHT_PARAMS + len(MATERIAL_COLUMNS)  # then y → LED, and 4 numbers (light_vertex_at)
LIGHT_REST = LIGHT_TO_LED + 3
LIGHT_COLUMNS = LIGHT_REST + 4
NO_RAY = np.float32(-1.0)
"""t_max of a ray slot that traces nothing (an ended path, an estimate that needs no shadow test)."""


@fn
def store_vec(a, j, row, v):
    """Rows row … row + 2 of column j of a (values, paths) table: a warp's threads write neighbouring words."""
    a[row, j] = v[0]
    a[row + 1, j] = v[1]
    a[row + 2, j] = v[2]


@fn
def load_vec(a, j, row):
    return a[row, j], a[row + 1, j], a[row + 2, j]


@fn
def store_xyz(a, j, v):
    """Row j of an (n, 3) array (the rays the traversal reads: one ray's 12 bytes side by side)."""
    a[j, 0] = v[0]
    a[j, 1] = v[1]
    a[j, 2] = v[2]


@fn
def store_light(out, j, light):
    """Column j of the light table from a light tuple (light_vertex_at)."""
    surf = light[1]
    out[LIGHT_FOUND, j] = 1.0 if light[0] else 0.0
    store_vec(out, j, LIGHT_SURF, surf[0])  # a heterogeneous tuple takes constant indices only
    store_vec(out, j, LIGHT_SURF + 3, surf[1])
    store_vec(out, j, LIGHT_SURF + 6, surf[2])
    store_vec(out, j, LIGHT_SURF + 9, surf[3])
    store_vec(out, j, LIGHT_SURF + 12, surf[4])
    params = surf[5]
    out[LIGHT_PARAMS + REFLECTANCE, j] = params[REFLECTANCE]
    out[LIGHT_PARAMS + ROUGHNESS, j] = params[ROUGHNESS]
    out[LIGHT_PARAMS + METALLIC, j] = params[METALLIC]
    out[LIGHT_PARAMS + IOR, j] = params[IOR]
    out[LIGHT_PARAMS + EXTINCTION, j] = params[EXTINCTION]
    out[LIGHT_PARAMS + COAT, j] = params[COAT]
    out[LIGHT_PARAMS + COAT_ROUGHNESS, j] = params[COAT_ROUGHNESS]
    store_vec(out, j, LIGHT_TO_LED, light[2])
    out[LIGHT_REST, j] = light[3]
    out[LIGHT_REST + 1, j] = light[4]
    out[LIGHT_REST + 2, j] = light[5]
    out[LIGHT_REST + 3, j] = light[6]


@fn
def load_light(table, j):
    """The light tuple of column j (store_light)."""
    surf = (load_vec(table, j, LIGHT_SURF), load_vec(table, j, LIGHT_SURF + 3), load_vec(table, j, LIGHT_SURF + 6),
            load_vec(table, j, LIGHT_SURF + 9), load_vec(table, j, LIGHT_SURF + 12),
            surface_params(table[LIGHT_PARAMS + REFLECTANCE, j], table[LIGHT_PARAMS + ROUGHNESS, j],
                           table[LIGHT_PARAMS + METALLIC, j], table[LIGHT_PARAMS + IOR, j],
                           table[LIGHT_PARAMS + EXTINCTION, j], table[LIGHT_PARAMS + COAT, j],
                           table[LIGHT_PARAMS + COAT_ROUGHNESS, j]))
    return (table[LIGHT_FOUND, j] != 0.0, surf, load_vec(table, j, LIGHT_TO_LED), table[LIGHT_REST, j],
            table[LIGHT_REST + 1, j], table[LIGHT_REST + 2, j], table[LIGHT_REST + 3, j])


@fn
def store_ray(rays, j, origin, direction, ignore):
    o, d, ig = rays[0], rays[1], rays[2]
    store_xyz(o, j, origin)
    store_xyz(d, j, direction)
    ig[j] = ignore


@gpu_kernel
def wf_start(scene, settings, launch, path, pstate, rays, light_rays, counters):
    """Stage 1: each path's pixel and sample, its camera ray and its light ray.

    ``launch`` = (order (P,) pixels by decreasing sample count, first (P,), offsets (≥ S + 1,) over the
    pass's sample indices, s0, s1): the group of sample indices s0 ≤ s < s1 (the table above).
    """
    j = cuda.grid(1)
    order, first, offsets, s0, s1 = launch
    g = offsets[s0] + j  # the path's index in the pass
    if g >= offsets[s1]:
        return
    lo = s0  # its sample index l: offsets[l] <= g < offsets[l + 1]
    hi = s1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if offsets[mid] <= g:
            lo = mid
        else:
            hi = mid
    p = order[g - offsets[lo]]
    pixel, samples, alive, shaded = path
    pixel[j] = p
    sample = first[p] + lo
    samples[j] = sample
    shaded[j] = 0
    alive[j] = 1
    key, max_depth, independent, light_paths, ambient, transient_bin_m = settings
    rng = (key, p, sample, independent)
    origin, direction = camera_start(scene, rng)
    f = pstate[0]
    f[0, j] = 1.0
    f[1, j] = 0.0
    f[2, j] = 0.0
    f[3, j] = 0.0
    store_vec(f, j, 4, origin)
    store_vec(f, j, 7, origin)
    store_vec(f, j, 10, direction)
    pstate[1][j] = -1
    store_ray(rays, j, ray_query(origin, direction, np.int64(1)), to_f32(direction), np.int64(-1))
    rays[3][j] = F32_INF
    counters[0, j] += 1
    if light_paths:
        ray = light_ray(scene[3], scene[4], rng)
        store_ray(light_rays, j, ray[4], ray[5], -1)
        counters[3, j] += 1


@gpu_kernel
def wf_light(scene, settings, n, path, light_hits, light):
    """Stage 2: the light vertex where each of the group's n paths' light ray hit (light_vertex_at), into the
    light table."""
    j = cuda.grid(1)
    pixel, samples = path[0], path[1]
    if j >= n:
        return
    key, max_depth, independent, light_paths, ambient, transient_bin_m = settings
    ray = light_ray(scene[3], scene[4], (key, pixel[j], samples[j], independent))
    prim, u, v = light_hits
    store_light(light, j, light_vertex_at(scene[0], scene[4], ray, prim[j], u[j], v[j]))


@fn
def queue_next_events(leds, frame, vertex, state, path_length, j, buffers):
    """The next-event estimates of path j's vertex to every LED (led_estimate) into ``pend`` and the shadow
    rays that need a test into ``shadow`` (slots j(L+1) + i), as connect_led decides them."""
    pend_w, pend_length = buffers[2]
    shadow, counters = buffers[3], buffers[5]
    n_led = leds[0].shape[0]
    for i in range(n_led):
        w, dist, led = led_estimate(frame, leds, vertex, state, i)
        pend_w[i, j] = w
        pend_length[i, j] = path_length + dist
        if w > 0:
            if state[1] == 1 and leds[1][i, LED_SKIP_FIRST_SHADOW] != 0.0:  # the camera ray proved this LED sees the first hit
                counters[4, j] += 1
            else:
                k = j * (n_led + 1) + i
                o, d, t_max = shadow_ray(vertex[1], led, point_offset(led, SPAWN_RELATIVE))
                store_ray((shadow[0], shadow[1], shadow[3]), k, o, d, vertex[3])
                shadow[2][k] = t_max
                counters[2, j] += 1


@fn
def queue_connection(vertex, throughput, path_length, j, buffers):
    """Path j's connection to its light vertex (light_estimate) into column L of ``pend``, its shadow ray
    into slot j(L+1) + L, as connect_light decides it."""
    light, shadow, counters = buffers[1], buffers[3], buffers[5]
    pend_w, pend_length = buffers[2]
    n_led = pend_w.shape[0] - 1
    y = load_light(light, j)
    w = 0.0
    extra = 0.0
    if y[0]:
        w, extra = light_estimate(vertex, throughput, y)
    pend_w[n_led, j] = w
    pend_length[n_led, j] = path_length + extra
    if w > 0:
        k = j * (n_led + 1) + n_led
        o, d, t_max = shadow_ray(vertex[1], y[1][0], y[6])
        store_ray((shadow[0], shadow[1], shadow[3]), k, o, d, vertex[3])
        shadow[2][k] = t_max
        counters[2, j] += 1


@fn
def continue_path(surf, vertex, rng, depth, throughput, j, buffers):
    """Sample path j's next direction at ``depth`` and store its state and next ray; False where the path
    ends there (next_direction below the geometric surface or with zero weight, as trace_path)."""
    f, rays = buffers[0][0], buffers[4]
    new_dir, weight, pdf, is_delta = next_direction(surf, vertex[2], rng, depth)
    if not (weight > 0 and dot(new_dir, surf[1]) > 0):
        return False
    f[0, j] = throughput * weight
    f[2, j] = pdf
    f[3, j] = 1.0 if is_delta else 0.0
    store_vec(f, j, 4, surf[0])
    origin = vertex[1]
    direction = divide(new_dir, norm(new_dir))
    store_vec(f, j, 7, origin)
    store_vec(f, j, 10, direction)
    buffers[0][1][j] = vertex[3]
    store_ray(rays, j, ray_query(origin, direction, depth + 1), to_f32(direction), vertex[3])
    rays[3][j] = F32_INF
    buffers[5][1, j] += 1
    return True


@gpu_kernel
def wf_shade(scene, settings, depth, n, path, hits, buffers):
    """Stage 3 at ``depth``: the surface each live path of the group's n hit, its next-event estimates and
    connection with their shadow rays, and its next ray — trace_path's loop body, minus traversal.

    ``buffers`` = (pstate, light, pend, shadow, rays, counters, total), see the table above.
    """
    j = cuda.grid(1)
    pixel, samples, alive, shaded = path
    if j >= n:
        return
    shaded[j] = 0
    shadow, rays = buffers[3], buffers[4]
    slots = scene[4][0].shape[0] + 1
    for i in range(slots):
        shadow[2][j * slots + i] = NO_RAY
    prim = hits[0][j]
    key, max_depth, independent, light_paths, ambient, transient_bin_m = settings
    f = buffers[0][0]
    if alive[j] == 0 or prim < 0:
        if alive[j] != 0:  # the ray left the scene: it sees the ambient radiance, β · L_amb (trace_path)
            total = buffers[6]
            geo = scene[0]
            total[total.shape[0] - 1, j] += f[0, j] * ambient_radiance(scene[8], (geo[12], geo[13]), ambient,
                                                                       load_vec(f, j, 10))
        alive[j] = 0
        rays[3][j] = NO_RAY
        return
    geo = scene[0]
    throughput, path_length, prev_pdf, prev_delta = f[0, j], f[1, j], f[2, j], f[3, j] != 0.0
    direction = load_vec(f, j, 10)
    surf = surface_at(geo, prim, hits[1][j], hits[2][j], load_vec(f, j, 7), direction)
    segment = norm(sub(surf[0], load_vec(f, j, 4)))
    path_length = path_length + segment
    f[1, j] = path_length
    vertex = camera_vertex(geo, prim, surf, direction)
    use_mis = light_paths and depth >= 2
    bsdf_area_pdf = prev_pdf * dot(neg(direction), surf[1]) / (segment * segment) if use_mis else 0.0
    queue_next_events(scene[4], scene[3], vertex, (throughput, depth, bsdf_area_pdf, prev_delta, use_mis),
                      path_length, j, buffers)
    shaded[j] = 1
    if depth < max_depth and light_paths:
        queue_connection(vertex, throughput, path_length, j, buffers)
        shaded[j] = 2
    rng = (key, pixel[j], samples[j], independent)
    if depth == max_depth or not continue_path(surf, vertex, rng, depth, throughput, j, buffers):
        alive[j] = 0
        rays[3][j] = NO_RAY


@gpu_kernel
def wf_resolve(scene, depth, n, path, pend, occluded, total, contrib):
    """Stage 4 at ``depth``: each shaded path's (of the group's n) unoccluded next-event estimates and
    connection, as add_next_events and add_connection compute them, into its addends of this depth
    (``contrib``, zero for a path that was not shaded) and its totals."""
    j = cuda.grid(1)
    if j >= n:
        return
    shaded = path[3]
    corr_kinds, corr_table, corr_data = scene[5], scene[6], scene[7]
    nee, con = contrib
    n_corr = corr_kinds.shape[0]
    for c in range(n_corr + 1):
        nee[c, j] = 0.0
        con[c, j] = 0.0
    if shaded[j] == 0:
        return
    pend_w, pend_length = pend
    n_led = pend_w.shape[0] - 1
    for i in range(n_led):
        w = 0.0 if occluded[j * (n_led + 1) + i] else pend_w[i, j]
        tau = pend_length[i, j] / SPEED_OF_LIGHT_M_S
        nee[0, j] += w
        phase = NO_PHASE
        for c in range(n_corr):
            g, phase = channel_value(corr_kinds[c], corr_table[c], corr_data, tau, phase)
            nee[1 + c, j] += g * w
    for c in range(n_corr + 1):
        total[c, j] += nee[c, j]
    if shaded[j] == 2:
        w = 0.0 if occluded[j * (n_led + 1) + n_led] else pend_w[n_led, j]
        tau = pend_length[n_led, j] / SPEED_OF_LIGHT_M_S
        con[0, j] = w
        total[0, j] += w
        phase = NO_PHASE
        for c in range(n_corr):
            g, phase = channel_value(corr_kinds[c], corr_table[c], corr_data, tau, phase)
            wg_c = g * w
            con[1 + c, j] = wg_c
            total[1 + c, j] += wg_c


@fn
def gather_outputs(depth, n_depth, n_corr):
    """How many sums :func:`wf_gather` adds each pixel's addends of ``depth`` to: the next-event weight and
    channels (bucket depth − 1), the connection's (bucket depth, below the last depth), and at the last
    depth the replicate channels (J + 2) and the ambient sum."""
    return (1 + n_corr) * (2 if depth < n_depth else 1) + (n_corr + 3 if depth == n_depth else 0)


@fn
def in_sample_order(start, source, row, i, offsets, s0, s1):
    """``start`` + source[row, j] over the paths j of the pixel that thread i of :func:`wf_gather` serves,
    added one by one in sample order."""
    total = start
    for lane in range(s0, s1):
        if i >= offsets[lane + 1] - offsets[lane]:
            break
        total += source[row, offsets[lane] - offsets[s0] + i]
    return total


@gpu_kernel
def wf_gather(launch, depth, samples, contrib, total, sums):
    """Stage 5, after each depth's resolve: add the group's addends of ``depth`` to the pass's sums, one
    thread per pixel and sum, each sum's addends in sample order; at the last depth also the paths' totals
    to the replicate sums.

    ``launch`` as in :func:`wf_start`; thread t = o · m + i serves pixel order[i] (the m pixels of sample
    index s0 include every later index's) and sum o (:func:`gather_outputs`). ``sums`` = (nee_w (K, P),
    nee_wg (K, J, P), con_w (K, P), con_wg (K, J, P), replicate (R, J + 2, P), ambient (P,)): each pixel's addends arrive
    in the order trace_pixels adds them on the CPU (a bucket's sums take one depth's addends only). One
    thread per sum rather than per pixel: a pixel that adaptive sampling gives hundreds of samples would
    otherwise keep one thread adding for milliseconds.
    """
    t = cuda.grid(1)
    order, offsets, s0, s1 = launch[0], launch[2], launch[3], launch[4]
    nee, con = contrib
    pass_nee_w, pass_nee_wg, pass_con_w, pass_con_wg, replicate, pass_ambient = sums
    n_depth, n_corr = pass_nee_wg.shape[0], pass_nee_wg.shape[1]
    m = offsets[s0 + 1] - offsets[s0]
    if t >= m * gather_outputs(depth, n_depth, n_corr):
        return
    o = t // m
    i = t - o * m
    p = order[i]
    per_kind = 1 + n_corr
    n_con = per_kind if depth < n_depth else 0
    if o < per_kind + n_con:
        row = o % per_kind  # 0: the weight, else channel row − 1
        if o < per_kind:
            k, source, w_sum, wg_sum = depth - 1, nee, pass_nee_w, pass_nee_wg
        else:
            k, source, w_sum, wg_sum = depth, con, pass_con_w, pass_con_wg
        if row == 0:
            w_sum[k, p] = in_sample_order(w_sum[k, p], source, 0, i, offsets, s0, s1)
        else:
            wg_sum[k, row - 1, p] = in_sample_order(wg_sum[k, row - 1, p], source, row, i, offsets, s0, s1)
        return
    c = o - per_kind - n_con
    if c == n_corr + 2:  # the ambient radiance the paths saw
        pass_ambient[p] = in_sample_order(pass_ambient[p], total, n_corr + 1, i, offsets, s0, s1)
        return
    for lane in range(s0, s1):
        if i >= offsets[lane + 1] - offsets[lane]:
            break
        j = offsets[lane] - offsets[s0] + i
        replicate[samples[j] % replicate.shape[0], c, p] += total[c, j]


@gpu_kernel
def wf_transient(launch, transient_bin_m, path, pend, occluded, film):
    """Stage 5 of a transient render, after each depth's resolve: the group's unoccluded next-event and
    connection weights of ``depth`` into the path-length histogram ``film`` (P, B) (:func:`add_transient`),
    one thread per pixel (thread i serves pixel order[i]), its paths in sample order, each path's estimates
    in LED order, then its connection (as wf_resolve reads them)."""
    i = cuda.grid(1)
    order, offsets, s0, s1 = launch[0], launch[2], launch[3], launch[4]
    if i >= offsets[s0 + 1] - offsets[s0]:
        return
    p = order[i]
    shaded = path[3]
    pend_w, pend_length = pend
    slots = pend_w.shape[0]
    for lane in range(s0, s1):
        if i >= offsets[lane + 1] - offsets[lane]:
            break
        j = offsets[lane] - offsets[s0] + i
        n = 0 if shaded[j] == 0 else (slots if shaded[j] == 2 else slots - 1)
        for k in range(n):
            if not occluded[j * slots + k]:
                add_transient(film, p, pend_w[k, j], pend_length[k, j], transient_bin_m)


# ------------------------------------------------------------------ GPU: the ground truth (tofcore.tracer.stages.first_hit)
# The pixel-centre rays in two kernels around one traversal launch, and their record in three arrays that come
# back in three copies (tofcore.compiled.cuda.first_hit): as ~40 CuPy operations with a read-back each for six
# fields it took 8–9 ms of a Kinect v2 frame on an H200 (docs/benchmarks.md).
@fn
def pixel_centre_direction(frame, directions, i):
    """Pixel i's sensor-frame unit direction (``directions`` (P, 3) float32) in the scene frame: rotated by
    ``frame``'s rows 0–2 as tofcore.tracer.surface.rotate adds the products, in float64."""
    x, y, z = np.float64(directions[i, 0]), np.float64(directions[i, 1]), np.float64(directions[i, 2])
    return (x * frame[0, 0] + y * frame[0, 1] + z * frame[0, 2], x * frame[1, 0] + y * frame[1, 1] + z * frame[1, 2],
            x * frame[2, 0] + y * frame[2, 1] + z * frame[2, 2])


@gpu_kernel
def wf_first_rays(frame, directions, rays):
    """The ground truth's ray of each of the P pixels, one thread per pixel: from the lens centre (``frame``'s
    row 3) along :func:`pixel_centre_direction`, leaving the lens as a camera ray does (:func:`ray_query`), into
    ``rays`` = (origin (P, 3) float32, direction (P, 3) float32, t_max (P,) float32, ignore (P,) int32): the
    traversal's order (tofcore.gpu.traversal.closest_hits_into)."""
    i = cuda.grid(1)
    if i >= directions.shape[0]:
        return
    origin, direction, t_max, ignore = rays
    d = pixel_centre_direction(frame, directions, i)
    o = ray_query((frame[3, 0], frame[3, 1], frame[3, 2]), d, np.int64(1))
    d32 = to_f32(d)
    for a in range(3):
        origin[i, a] = o[a]
        direction[i, a] = d32[a]
    ignore[i] = -1
    t_max[i] = F32_INF


@gpu_kernel
def wf_first_hit(geo, object_ids, origin_m, frame, directions, hits, record):
    """The ground truth's record of each of the P pixels from its ray's hit ``hits`` = (prim, u, v), one thread
    per pixel (tofcore.tracer.stages.first_hit_record): ``record`` = (distance (P,) float64, the radial distance
    lens → surface; vectors (3, P, 3) float32: the world-frame position (the scene-frame point + ``origin_m``),
    the normal facing the camera, the ray's direction; ids (2, P) int32: material, object). A miss: NaN distance,
    position and normal, ids −1."""
    i = cuda.grid(1)
    if i >= directions.shape[0]:
        return
    distance, vectors, ids = record
    d = pixel_centre_direction(frame, directions, i)
    for a in range(3):
        vectors[2, i, a] = np.float32(d[a])
    prim = hits[0][i]
    if prim < 0:
        distance[i] = np.nan
        for a in range(3):
            vectors[0, i, a] = np.float32(np.nan)
            vectors[1, i, a] = np.float32(np.nan)
        ids[0, i] = -1
        ids[1, i] = -1
        return
    lens = (frame[3, 0], frame[3, 1], frame[3, 2])
    point, normal = hit_point(geo, prim, hits[1][i], hits[2][i], lens, d)
    offset = sub(point, lens)
    distance[i] = math.sqrt(offset[0] * offset[0] + offset[1] * offset[1] + offset[2] * offset[2])
    for a in range(3):
        vectors[0, i, a] = np.float32(point[a] + origin_m[a])
        vectors[1, i, a] = np.float32(normal[a])
    ids[0, i] = geo[8][prim]
    ids[1, i] = object_ids[prim]
