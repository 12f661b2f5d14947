"""Every function of tofcore/compiled/kernels.py against its NumPy twin, through one registry that names the pair
(:data:`tofcore.compiled.twins.TWINS`, as :data:`tofcore.backend.KERNELS` names the CUDA twins).

* **Registry** (no numba needed): every kernel function (``@fn``, ``@cpu_parallel``, ``@gpu_kernel``) has an
  entry and every entry a kernel function; every reference resolves (import the module, then the attributes
  of the qualified name), so a renamed or moved reference fails here; every dotted name in kernels.py's
  docstrings resolves too, and where a function's docstring points at reference code it names a registered
  twin.
* **Values** (numba): each function of :data:`VALUE_TESTED` is called directly from a jitted loop over inputs
  drawn with a fixed seed (edge cases added by hand) and compared by :func:`twin` with its reference on the
  same inputs. The path functions take their inputs from the NumPy stages of a small render (the odd
  materials room: a mirror, a half metal, an η = 1 dielectric, shading normals; a distorted camera; an LED at
  the pinhole and a Lambertian one beside it; every kind of correlation channel), vertex by vertex.
* **Coverage**: :data:`VALUE_TESTED` over all kernel functions, at least :data:`MIN_COVERAGE`; each listed
  function must be called as ``kernels.<name>(`` in this module and compared by a ``twin("<name>", …)``, so
  the list cannot claim what the tests do not do.

Tolerance. The kernels perform the reference's IEEE operations in the reference's order, and +, −, ×, ÷ and
√ are correctly rounded (floor and hypot come from the same C library on both sides), so such functions must
agree bit for bit (:data:`EXACT`). What can differ is the last bits of transcendental functions: the kernels
call the C library's exp, log1p, sin, cos, acos, tan and pow (through LLVM), NumPy its own vectorised loops
(SIMD code on CPUs with AVX-512), each within a few ulp of the true value. Values that pass through one are
compared to a relative 1e-12 (:data:`TRANSCENDENTAL`, ~4500 ulp: a few ulp of the function, amplified by the
few operations after it, while a wrong formula, constant or branch is off by far more), with an absolute
floor of 1e-12 × the largest reference value of the comparison for results that cancel towards zero.
Measured on the development machine (a Xeon with AVX-512, NumPy 1.26.4, numba 0.68.1, glibc): every EXACT
comparison holds bit for bit; the Beckmann D (exp), Oren–Nayar (acos, tan, pow) and everything computed
through them (f_r, pdfs, BSDF samples, next events, connections, whole paths) differ in the last bits of 2 to
21 % of the values, by at most 1.1e-15 of the comparison's largest value; the warps, emission directions,
correlation channels and light vertices agree bit for bit there too. A last-bit difference that moved a ray
across a triangle edge or a sample across a lobe threshold would fail the path tests; on random inputs that
is far rarer than one in the few hundred paths compared.

Compile time: the jitted loops are compiled once per session and not cached on disk (numba checks only the
stamp of a function's own file, so a cached loop would keep old kernels inlined: tofcore.compiled._target);
the kernel functions they call come from the kernels' own cache.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import re
import types
from pathlib import Path

import numpy as np
import pytest

import tofcore
from tofcore import backend, compiled
from tofcore import rng as tof_rng
from tofcore.compiled import setup as packing
from tofcore.compiled import twins
from tofcore.scene import bsdf, bvh, fresnel, sampling
from tofcore.scene.camera import Camera
from tofcore.scene.led import LED
from tofcore.scene.material import PARAMETER_NAMES, Material, Texture
from tofcore.sensor import modulation
from tofcore.tracer import integrator, light_paths, qmc, stages, surface
from tofcore.tracer.accumulate import Tally
from tofcore.tracer.setup import CorrelationList, TraceSettings, make_setup
from tofcore.tracer.trace import _empty_transport
from tofcore.tracer.transport import TraceStats

try:
    import numba
    from tofcore.compiled import kernels
except ImportError:  # the registry tests run without numba
    numba = kernels = None

needs_numba = pytest.mark.skipif(compiled.numba_version() is None, reason="numba is not installed")

ROOT = Path(__file__).resolve().parents[2]
KERNELS_PY = ROOT / "tofcore" / "compiled" / "kernels.py"
KERNEL_DECORATORS = {"fn", "cpu_parallel", "gpu_kernel"}

VALUE_TESTED = (
    # vectors
    "dot", "norm", "sub", "scale", "divide", "neg", "to_f32", "rotate",
    # random numbers
    "splitmix", "hash_bits", "uniform", "reverse_bits", "owen_scramble", "sobol_dim1_lookup", "sobol_dim1_bits",
    "qmc_seeds", "sample_2d", "sample_1d",
    # warps, LEDs, correlations
    "concentric_disk", "cosine_hemisphere", "led_intensity", "emission_pdf", "sample_emission", "correlation",
    "channel_value",
    # camera
    "distort_with_jacobian", "undistort_near", "camera_ray",
    # BVH and surfaces
    "ray_frame", "inverse_direction", "traverse", "intersect", "point_offset", "spawn_offset", "shadow_ray",
    "orthonormal_basis", "surface_at", "to_local", "to_world", "surface_params",
    # textures, the sky, transient bins
    "texture_sample", "perturb_normal", "ambient_radiance", "add_transient",
    # reflection
    "fresnel_dielectric", "fresnel_conductor", "specular_fresnel", "outgoing", "rough_alpha", "specular_density",
    "coat_fresnel", "reflect_visible_normal",
    "beckmann_distribution", "half_vector", "oren_nayar", "cos_azimuth_difference", "eval_terms", "pdf_terms",
    "eval_bsdf", "eval_pdf_bsdf", "sample_bsdf",
    # one path
    "camera_start", "ray_query", "next_hit", "camera_vertex", "led_estimate", "connect_led", "add_next_events",
    "light_ray", "light_vertex_at", "light_vertex", "light_estimate", "connect_light", "add_connection",
    "next_direction", "trace_path", "trace_pixels",
    # the GPU wavefront's stages of one vertex, compiled for the CPU
    "queue_next_events", "queue_connection", "continue_path",
)
"""The kernel functions a value test below calls directly and compares with their registered reference."""

MIN_COVERAGE = 0.8
"""Share of kernels.py's functions that must have a direct value test (issue 31)."""

EXACT = 0.0
"""Tolerance of functions made of +, −, ×, ÷, √, comparisons and integer operations: bit for bit."""
TRANSCENDENTAL = 1e-12
"""Relative tolerance of values that pass through exp, log1p, sin, cos, acos, tan or pow (module docstring)."""
NEWTON_BLOCK = 1e-15
"""Tolerance of rays through a distorted lens against NumPy's blocks of rays: NumPy's Newton iteration runs
until a block's slowest ray has converged, and the steps after a ray's own convergence can move its last bit
(test_camera_rays_equal_the_camera_model). One ray at a time the two agree bit for bit."""


# ------------------------------------------------------------------ the registry (no numba)
def kernel_functions() -> dict[str, ast.FunctionDef]:
    """The functions kernels.py defines with one of its decorators, by name (parsed, not imported)."""
    tree = ast.parse(KERNELS_PY.read_text(encoding="utf-8"))
    return {node.name: node for node in tree.body if isinstance(node, ast.FunctionDef)
            and {ast.unparse(d) for d in node.decorator_list} & KERNEL_DECORATORS}


def test_every_kernel_function_is_in_the_registry_and_nothing_else():
    defined = kernel_functions()
    assert len(defined) > 50, "kernels.py's decorators were not recognised"
    assert sorted(set(defined) - set(twins.TWINS)) == [], "kernel functions without an entry in TWINS"
    assert sorted(set(twins.TWINS) - set(defined)) == [], "TWINS entries without a kernel function"
    undecorated = [n.name for n in ast.parse(KERNELS_PY.read_text(encoding="utf-8")).body
                   if isinstance(n, ast.FunctionDef) and n.name not in defined]
    assert undecorated == [], "functions in kernels.py that none of its decorators compile"


def test_every_registered_reference_resolves():
    for name, value in twins.TWINS.items():
        values = value if isinstance(value, tuple) else (value,)
        if twins.references(name):
            for dotted in values:
                assert re.fullmatch(r"(tofcore|numpy)(\.\w+)+", dotted), f"{name}: {dotted!r} is not module.qualname"
                try:
                    obj = twins.resolve(dotted)
                except (ImportError, AttributeError) as exc:
                    pytest.fail(f"TWINS[{name!r}]: {dotted} does not resolve ({exc})")
                assert callable(obj), f"TWINS[{name!r}]: {dotted} is not a function"
        else:
            assert len(values) == 1 and len(values[0].split()) >= 4, f"{name}: give one reason in words"


def _reference_names() -> dict[str, list[str]]:
    """Short name → full dotted names: each module's last component and each top-level class of the reference
    code (tofcore outside tofcore.compiled and tofcore.gpu), from the files (nothing imported)."""
    names: dict[str, list[str]] = {}
    for path in sorted((ROOT / "tofcore").rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        module = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        if module.startswith(("tofcore.compiled", "tofcore.gpu")):
            continue
        names.setdefault(module.rsplit(".", 1)[-1], []).append(module)
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.ClassDef):
                names.setdefault(node.name, []).append(f"{module}.{node.name}")
    return names


DOTTED = re.compile(r"(?<![\w.])([A-Za-z_]\w*(?:\.[A-Za-z_]\w*)+)")


def _docstring_pointers(doc: str, short: dict[str, list[str]]) -> list[tuple[str, str]]:
    """(as written, full dotted name) of the names a docstring points at: ``tofcore.…``, ``numpy.…`` and
    ``head.rest`` with ``head`` a reference module or class (``bsdf.eval_bsdf``, ``Camera._ray_block``)."""
    found = []
    for written in DOTTED.findall(doc):
        head, _, rest = written.partition(".")
        if head in ("tofcore", "numpy"):
            found.append((written, written))
        elif head in short:
            if len(short[head]) > 1:
                pytest.fail(f"{written!r} is ambiguous ({short[head]}): write the full name")
            found.append((written, f"{short[head][0]}.{rest}"))
    return found


def test_kernel_docstrings_point_at_references_that_exist_and_agree_with_the_registry():
    """No stale pointer in kernels.py's docstrings: every name they give resolves, every :func:`name` is a
    kernel function, and a docstring that points at reference code names the function's registered twin."""
    tree = ast.parse(KERNELS_PY.read_text(encoding="utf-8"))
    defined = kernel_functions()
    short = _reference_names()
    docs = {"module": ast.get_docstring(tree) or ""}
    docs.update((node.name, ast.get_docstring(node) or "") for node in tree.body if isinstance(node, ast.FunctionDef))
    docs.update((f"after line {node.lineno}", node.value.value) for node in tree.body
                if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)
                and isinstance(node.value.value, str) and node is not tree.body[0])
    stale, disagree = [], []
    for where, doc in docs.items():
        for local in re.findall(r":func:`~?\.?(\w+)`", doc):
            if local not in defined:
                stale.append(f"{where}: :func:`{local}` is not a kernel function")
        pointers = _docstring_pointers(doc, short)
        for written, full in pointers:
            if full.startswith("tofcore.compiled") and compiled.numba_version() is None:
                continue  # those modules need numba to import
            try:
                twins.resolve(full)
            except (ImportError, AttributeError):
                stale.append(f"{where}: {written}{f' ({full})' if full != written else ''} does not exist")
        reference_code = {full for _, full in pointers if not full.startswith(("tofcore.compiled", "tofcore.gpu"))}
        registered = set(twins.references(where)) if where in twins.TWINS else set()
        if registered and reference_code and not reference_code & registered:
            disagree.append(f"{where}: the docstring names {sorted(reference_code)}, TWINS {sorted(registered)}")
    assert stale == [], "stale pointers in kernels.py's docstrings:\n" + "\n".join(stale)
    assert disagree == [], "docstrings and TWINS disagree:\n" + "\n".join(disagree)


def test_value_tests_cover_the_kernels():
    """At least MIN_COVERAGE of kernels.py's functions are value-tested; each one listed really is: this module
    calls ``kernels.<name>(…)`` and compares it with ``twin("<name>", …)``, against a registered reference."""
    defined = kernel_functions()
    tree = ast.parse(Path(__file__).read_text(encoding="utf-8"))
    called = {node.func.attr for node in ast.walk(tree) if isinstance(node, ast.Call)
              and isinstance(node.func, ast.Attribute) and isinstance(node.func.value, ast.Name)
              and node.func.value.id == "kernels"}
    compared = {node.args[0].value for node in ast.walk(tree) if isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name) and node.func.id == "twin" and node.args
                and isinstance(node.args[0], ast.Constant)}
    assert len(set(VALUE_TESTED)) == len(VALUE_TESTED)
    assert sorted(set(VALUE_TESTED) - set(defined)) == [], "VALUE_TESTED names no kernel function"
    assert [n for n in VALUE_TESTED if not twins.references(n)] == [], "value-tested without a registered reference"
    assert sorted(set(VALUE_TESTED) - called) == [], "listed as value-tested but never called here"
    assert sorted(set(VALUE_TESTED) - compared) == [], "listed as value-tested but never compared by twin()"
    assert sorted(compared - set(VALUE_TESTED)) == [], "compared by twin() but missing from VALUE_TESTED"
    coverage = len(VALUE_TESTED) / len(defined)
    untested = sorted(set(defined) - set(VALUE_TESTED))
    print(f"\nkernel functions with a direct twin test: {len(VALUE_TESTED)}/{len(defined)} = {coverage:.1%}; "
          f"without: {', '.join(untested)}")
    assert coverage >= MIN_COVERAGE, f"{coverage:.1%} of kernels.py's functions have a value test"


# ------------------------------------------------------------------ comparing a kernel with its twin
def twin(name: str, got, ref, tolerance: float = EXACT, what: str = "") -> None:
    """Kernel function ``name``'s values ``got`` against its reference's ``ref`` on the same inputs: bit for bit
    (:data:`EXACT`; NaN equals NaN) or to ``tolerance`` relative (:data:`TRANSCENDENTAL`)."""
    got, ref = np.asarray(got), np.asarray(ref)
    message = f"kernels.{name} against {twins.TWINS[name]}{' ' + what if what else ''}"
    assert got.shape == ref.shape, f"{message}: shape {got.shape} against {ref.shape}"
    assert got.size > 0, f"{message}: nothing compared"
    if tolerance == EXACT:
        np.testing.assert_array_equal(got, ref, err_msg=message)
    else:
        finite = np.isfinite(ref)
        scale = float(np.abs(ref[finite]).max(initial=0.0)) if ref.dtype.kind == "f" else 0.0
        np.testing.assert_allclose(got, ref, rtol=tolerance, atol=tolerance * scale, err_msg=message)


def jitted(function):
    """``numba.njit``, compiled on the first call (once per session; not cached, see the module docstring)."""
    return numba.njit(function) if numba is not None else function


def draws(stream: int) -> np.random.Generator:
    """The fixed-seed generator of one test's inputs."""
    return np.random.default_rng((31, stream))


@jitted
def _vec(a, i):
    return a[i, 0], a[i, 1], a[i, 2]


@jitted
def _put(out, i, v):
    out[i, 0] = v[0]
    out[i, 1] = v[1]
    out[i, 2] = v[2]


# ------------------------------------------------------------------ random numbers (tofcore.rng, tofcore.tracer.qmc)
@jitted
def _random_numbers(key, pixel, sample, dim, x, seed):
    n = len(pixel)
    bits = np.empty((n, 10), np.uint64)
    floats = np.empty((n, 7))
    for i in range(n):
        bits[i, 0] = kernels.splitmix(x[i])
        bits[i, 1] = kernels.hash_bits(key, pixel[i], sample[i], dim)
        bits[i, 2] = kernels.reverse_bits(x[i] & np.uint64(0xFFFFFFFF))
        bits[i, 3] = kernels.owen_scramble(x[i] & np.uint64(0xFFFFFFFF), seed[i])
        bits[i, 4] = kernels.sobol_dim1_lookup(x[i] & np.uint64(0xFFFFFFFF))
        bits[i, 5] = kernels.sobol_dim1_bits(x[i] & np.uint64(0xFFFFFFFF))
        bits[i, 6], bits[i, 7], bits[i, 8], bits[i, 9] = kernels.qmc_seeds(key, pixel[i], sample[i], dim)
        floats[i, 0] = kernels.uniform(key, pixel[i], sample[i], dim)
        floats[i, 1], floats[i, 2] = kernels.sample_2d(key, pixel[i], sample[i], dim, False)
        floats[i, 3] = kernels.sample_1d(key, pixel[i], sample[i], dim, False)
        floats[i, 4], floats[i, 5] = kernels.sample_2d(key, pixel[i], sample[i], dim, True)
        floats[i, 6] = kernels.sample_1d(key, pixel[i], sample[i], dim, True)
    return bits, floats


@needs_numba
def test_random_numbers_equal_tofcore_rng_and_qmc():
    """Hashes, scrambles, Sobol' points and both samplers' uniforms, bit for bit (integer arithmetic)."""
    g = draws(1)
    n = 2000
    key = tof_rng.seed_key(7)
    pixel = g.integers(0, 1 << 22, n)
    sample = np.concatenate([np.arange(n // 2), g.integers(0, 1 << 33, n - n // 2)])  # large indices too
    x = g.integers(0, np.iinfo(np.uint64).max, n, dtype=np.uint64, endpoint=True)
    x[:34] = np.concatenate([np.uint64(1) << np.arange(32, dtype=np.uint64), [0, 0xFFFFFFFF]])
    x32 = (x & np.uint64(0xFFFFFFFF)).astype(np.uint32)
    seed = g.integers(0, 1 << 32, n, dtype=np.uint64)
    for dim in (0, 1, 7, 1_000_001):
        bits, floats = _random_numbers(key, pixel, sample, dim, x, seed)
        twin("splitmix", bits[:, 0], tof_rng._splitmix(x.copy()))
        twin("hash_bits", bits[:, 1], tof_rng.bits(key, pixel, sample, dim))
        twin("reverse_bits", bits[:, 2], qmc.reverse_bits(x32))
        twin("owen_scramble", bits[:, 3], qmc.owen_scramble(x32, seed.astype(np.uint32)))
        twin("sobol_dim1_lookup", bits[:, 4], qmc.sobol_2d(x32)[1])
        twin("sobol_dim1_bits", bits[:, 5], qmc.sobol_2d(x32)[1])
        twin("qmc_seeds", bits[:, 6:10].T, np.array(qmc._seeds(key, pixel, sample, dim)), what=f"dim {dim}")
        twin("uniform", floats[:, 0], tof_rng.uniform(key, pixel, sample, dim))
        twin("sample_2d", floats[:, 1:3].T, np.array(qmc.sample_2d(key, pixel, sample, dim, "sobol")))
        twin("sample_1d", floats[:, 3], qmc.sample_1d(key, pixel, sample, dim, "sobol"))
        twin("sample_2d", floats[:, 4:6].T, np.array(qmc.sample_2d(key, pixel, sample, dim, "independent")))
        twin("sample_1d", floats[:, 6], qmc.sample_1d(key, pixel, sample, dim, "independent"))


# ------------------------------------------------------------------ vectors, frames, offsets, shadow rays
@jitted
def _surf(rows, i):
    """The kernels' surface tuple from row i of (N, SURFACE_ROWS) rows: position, ng, tangent, bitangent, ns, the
    material record (the material table's fields)."""
    return ((rows[i, 0], rows[i, 1], rows[i, 2]), (rows[i, 3], rows[i, 4], rows[i, 5]),
            (rows[i, 6], rows[i, 7], rows[i, 8]), (rows[i, 9], rows[i, 10], rows[i, 11]),
            (rows[i, 12], rows[i, 13], rows[i, 14]),
            kernels.surface_params(rows[i, 15], rows[i, 16], rows[i, 17], rows[i, 18], rows[i, 19], rows[i, 20],
                                   rows[i, 21]))


@jitted
def _put_surf(rows, i, surf):
    """Row i of (N, SURFACE_ROWS) rows from the kernels' surface tuple (:func:`_surf` backwards)."""
    position, ng, tangent, bitangent, ns, params = surf  # a heterogeneous tuple takes constant indices only
    for k, v in enumerate((position, ng, tangent, bitangent, ns)):
        rows[i, 3 * k], rows[i, 3 * k + 1], rows[i, 3 * k + 2] = v
    rows[i, 15], rows[i, 16], rows[i, 17], rows[i, 18], rows[i, 19], rows[i, 20], rows[i, 21] = params


def surface_rows(surf: surface.Surface) -> np.ndarray:
    """(N, SURFACE_ROWS) rows of a NumPy :class:`~tofcore.tracer.surface.Surface` for :func:`_surf`."""
    p = surf.params
    return np.ascontiguousarray(np.column_stack([surf.position, surf.geometric_normal, surf.tangent, surf.bitangent,
                                                 surf.shading_normal, *(getattr(p, name) for name in PARAMETER_NAMES)]),
                                dtype=np.float64)


SURFACE_ROWS = 15 + len(PARAMETER_NAMES)
"""Columns of a surface row: five vectors and the material record."""


@jitted
def _vectors(a, b, s, rot, unit, d32, margin, rows):
    n = len(a)
    v3 = np.empty((9, n, 3))
    f32 = np.empty((6, n, 3), np.float32)
    scalars = np.empty((4, n))
    t_max = np.empty(n, np.float32)
    for i in range(n):
        x, y, d = _vec(a, i), _vec(b, i), _vec(d32, i)
        scalars[0, i] = kernels.dot(x, y)
        scalars[1, i] = kernels.norm(x)
        scalars[2, i] = kernels.point_offset(x, kernels.SPAWN_RELATIVE)
        scalars[3, i] = kernels.point_offset(x, kernels.LEAVE_RELATIVE)
        _put(v3[0], i, kernels.sub(x, y))
        _put(v3[1], i, kernels.scale(x, s[i]))
        _put(v3[2], i, kernels.divide(x, s[i]))
        _put(v3[3], i, kernels.neg(x))
        _put(v3[4], i, kernels.rotate(x, rot))
        tangent, bitangent = kernels.orthonormal_basis(_vec(unit, i))
        _put(v3[5], i, tangent)
        _put(v3[6], i, bitangent)
        surf = _surf(rows, i)
        _put(v3[7], i, kernels.to_local(surf, x))
        _put(v3[8], i, kernels.to_world(surf, x))
        _put(f32[0], i, kernels.to_f32(x))
        b1, b2 = kernels.ray_frame(d)
        _put(f32[1], i, b1)
        _put(f32[2], i, b2)
        _put(f32[3], i, kernels.inverse_direction(d))
        o, direction, t_max[i] = kernels.shadow_ray(x, y, margin[i])
        _put(f32[4], i, o)
        _put(f32[5], i, direction)
    return v3, f32, scalars, t_max


def unit_vectors(g: np.random.Generator, n: int) -> np.ndarray:
    d = g.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@needs_numba
def test_vector_helpers_frames_offsets_and_shadow_rays_equal_numpy():
    """Vectors, shading frames, ray offsets, the traversal's ray frame and inverse direction, shadow rays: bit for
    bit (the same +, −, ×, ÷, √ in the same order; float32 where the BVH works in float32)."""
    g = draws(2)
    n = 1000
    a = g.normal(scale=3.0, size=(n, 3))
    b = g.normal(scale=3.0, size=(n, 3))
    a[:3], b[3] = 0.0, a[3]                      # zero vectors; a shadow ray of length 0
    a[4] = (1e-4, -2e-4, 5e-4)                   # below the 1 mm offset floor
    s = g.normal(size=n)
    s[:2] = (0.0, -0.0)
    rot = tofcore.look_at((0.3, -2.0, 1.2), (0.0, 0.0, 1.0))[:3, :3].copy()
    unit = unit_vectors(g, n)
    unit[:4] = ((0, 0, 1), (0, 0, -1), (1, 0, 0), (0, -1, 0))
    d32 = unit_vectors(g, n).astype(np.float32)
    d32[:6] = ((0, 0, 1), (0, 0, -1), (1e-31, -1e-31, 1), (-0.0, 0.0, -1), (1e-30, -1e-30, 1), (0.6, 0.8, 0))
    margin = g.random(n) * 1e-3
    tangent, bitangent = surface.orthonormal_basis(unit)
    shading = surface.Surface(position=b, geometric_normal=unit, tangent=tangent, bitangent=bitangent,
                              shading_normal=unit,
                              params=bsdf.SurfaceParams(**{k: np.full(n, 0.5) for k in PARAMETER_NAMES}))
    v3, f32, scalars, t_max = _vectors(a, b, s, rot, unit, d32, margin, surface_rows(shading))
    twin("dot", scalars[0], surface.dot(a, b))
    twin("norm", scalars[1], np.linalg.norm(a, axis=1))
    twin("point_offset", scalars[2], surface.point_offset(a, surface.SPAWN_RELATIVE))
    twin("point_offset", scalars[3], surface.point_offset(a, surface.LEAVE_RELATIVE))
    with np.errstate(divide="ignore", invalid="ignore"):
        twin("sub", v3[0], np.subtract(a, b))
        twin("scale", v3[1], np.multiply(a, s[:, None]))
        twin("divide", v3[2], np.divide(a, s[:, None]))
    twin("neg", v3[3], np.negative(a))
    twin("rotate", v3[4], surface.rotate(a, rot))
    twin("orthonormal_basis", v3[5:7], np.array(surface.orthonormal_basis(unit)))
    twin("to_local", v3[7], shading.to_local(a))
    twin("to_world", v3[8], shading.to_world(a))
    twin("to_f32", f32[0], a.astype(np.float32))
    twin("ray_frame", f32[1:3], np.array(bvh._ray_frame(d32)))
    box_records, _ = bvh._ray_records(np.zeros((n, 3), np.float32), d32, np.ones(n, np.float32), 2)
    twin("inverse_direction", f32[3], box_records[:, 0].reshape(n, 7)[:, 3:6])
    origin, direction, reference_t_max = surface.shadow_ray(a, b, margin)
    twin("shadow_ray", f32[4], origin)
    twin("shadow_ray", f32[5], direction)
    twin("shadow_ray", t_max, reference_t_max)


# ------------------------------------------------------------------ warps, LEDs, correlation channels
@jitted
def _warps_and_leds(u1, u2, cos_axis, intensity_w_sr, kinds, table, data, tau):
    n = len(u1)
    disk = np.empty((n, 2))
    hemisphere = np.empty((n, 3))
    led = np.empty((2, 2, n))  # kind (point, Lambertian) × (intensity, pdf)
    emission = np.empty((2, n, 3))
    for i in range(n):
        disk[i, 0], disk[i, 1] = kernels.concentric_disk(u1[i], u2[i])
        _put(hemisphere, i, kernels.cosine_hemisphere(u1[i], u2[i]))
        for k, kind in enumerate((kernels.POINT, kernels.LAMBERTIAN)):
            led[k, 0, i] = kernels.led_intensity(np.int64(kind), intensity_w_sr, cos_axis[i])
            led[k, 1, i] = kernels.emission_pdf(np.int64(kind), cos_axis[i])
            _put(emission[k], i, kernels.sample_emission(np.int64(kind), u1[i], u2[i]))
    channels = np.empty((2, len(kinds), len(tau)))  # correlation, channel_value (the channels in order)
    for j in range(len(kinds)):
        for i in range(len(tau)):
            channels[0, j, i] = kernels.correlation(kinds[j], table[j], data, tau[i])
    for i in range(len(tau)):
        phase = kernels.NO_PHASE
        for j in range(len(kinds)):
            channels[1, j, i], phase = kernels.channel_value(kinds[j], table[j], data, tau[i], phase)
    return disk, hemisphere, led, emission, channels


def correlation_channels() -> CorrelationList:
    """Channels of every kind the kernels know: phasor, sine, square (duty ½ and not), pulsed, a harmonic series
    and a table (custom waveforms as data)."""
    sine = modulation.CorrelationBank(kind="cw_sine", frequencies_hz=(30e6,), offsets=((0.0, 0.25, 0.5),),
                                      duty_cycle=0.5, pulse_width_s=None)
    square = modulation.CorrelationBank(kind="cw_square", frequencies_hz=(80e6, 16e6),
                                        offsets=((0.0, 1 / 3, 2 / 3), (0.0, 0.75)), duty_cycle=0.5, pulse_width_s=None)
    pulsed = modulation.CorrelationBank(kind="pulsed", frequencies_hz=(), offsets=(), duty_cycle=0.5,
                                        pulse_width_s=20e-9)
    odd_duty = [functools.partial(modulation.square_correlation, f_hz=120e6, offset_fraction=2 / 3, duty=d)
                for d in (0.3, 0.7)]
    custom = [modulation.harmonic(80e6, (0.5, 0.4, 0.0, -0.05), (0.1, 0.02, 0.01)),
              modulation.tabulate(functools.partial(modulation.sine_correlation, f_hz=16e6, offset_fraction=0.25),
                                  1 / 16e6, samples=64)]
    return CorrelationList(tuple(modulation.phasor_correlations([20e6, 80e6]) + sine.functions()
                                 + square.functions() + odd_duty + pulsed.functions() + custom))


@needs_numba
def test_warps_leds_and_correlations_equal_numpy():
    """Disk and hemisphere warps and the point LED's sphere (sin, cos: to 1e-12); LED intensities and pdfs, square
    and pulsed channels bit for bit; phasor and sine channels (cos) to 1e-12."""
    g = draws(3)
    n = 2000
    u1, u2 = g.random((2, n))
    u1[:4], u2[:4] = (0.5, 0.25, 0.5, 0.75), (0.5, 0.5, 0.9, 0.25)  # the disk's centre, its axes, a diagonal
    cos_axis = g.uniform(-1.0, 1.0, n)
    cos_axis[:2] = (0.0, -0.0)
    channels = correlation_channels()
    kinds, table, data = packing.correlation_table(channels)
    assert sorted(set(kinds.tolist())) == [0, 1, 2, 3, 4, 5]  # every kind (tofcore.compiled.layout)
    tau = np.concatenate([g.uniform(-5e-9, 1e-7, n), [0.0, 1 / 80e6, 0.5 / 80e6, 20e-9, 40e-9, -1e-9]])
    disk, hemisphere, led, emission, got = _warps_and_leds(u1, u2, cos_axis, 2.5, kinds, table, data, tau)
    twin("concentric_disk", disk.T, np.array(sampling.sample_concentric_disk(u1, u2)), TRANSCENDENTAL)
    twin("cosine_hemisphere", hemisphere, sampling.sample_cosine_hemisphere(u1, u2), TRANSCENDENTAL)
    for k, kind in enumerate(("point", "lambertian")):
        reference = LED(intensity_w_sr=2.5, kind=kind)
        twin("led_intensity", led[k, 0], reference.intensity(cos_axis), what=kind)
        twin("emission_pdf", led[k, 1], reference.emission_pdf(cos_axis), what=kind)
        twin("sample_emission", emission[k], reference.sample_emission(u1, u2), TRANSCENDENTAL, what=kind)
    for j, g_j in enumerate(channels.functions):
        exact = g_j.func in (modulation.square_correlation, modulation.pulsed_correlation,
                             modulation.tabulated_correlation)
        twin("correlation", got[0, j], g_j(tau), EXACT if exact else TRANSCENDENTAL, what=f"channel {j}: {g_j}")
        # the phasor's cos and sin from one sincos per frequency: the sin channel ≈ 1e-15 from the reference's
        # cos(2πfτ − π/2), within the transcendental tolerance of the channel's largest value
        twin("channel_value", got[1, j], g_j(tau), EXACT if exact else TRANSCENDENTAL, what=f"channel {j}: {g_j}")
    phasor_cos = [j for j, g_j in enumerate(channels.functions)
                  if g_j.func is modulation.phasor_component and g_j.keywords["quarter"] == 0]
    assert phasor_cos and np.array_equal(got[1, phasor_cos], got[0, phasor_cos])  # q = 0: the same bits


# ------------------------------------------------------------------ textures, the sky, transient bins (scene, tracer)
@jitted
def _textures_sky_bins(textures, uv, directions, sky, radiance, lengths, weights, bin_m, n_bins, normal_inputs, geo):
    n = len(uv)
    lookup = np.empty((3, n), np.float32)  # the first image's channel, the normal map's channels 0 and 2
    sky_radiance = np.empty(len(directions))
    film = np.zeros((1, n_bins))
    bent = np.empty((len(normal_inputs[0]), 3))
    for i in range(n):
        lookup[0, i] = kernels.texture_sample(textures, 0, uv[i, 0], uv[i, 1], 0)
        lookup[1, i] = kernels.texture_sample(textures, 1, uv[i, 0], uv[i, 1], 0)
        lookup[2, i] = kernels.texture_sample(textures, 1, uv[i, 0], uv[i, 1], 2)
    for i in range(len(directions)):
        sky_radiance[i] = kernels.ambient_radiance(sky, textures, radiance, _vec(directions, i))
    for i in range(len(lengths)):
        kernels.add_transient(film, 0, weights[i], lengths[i], bin_m)
    prim, n_in, rgb = normal_inputs
    for i in range(len(prim)):
        _put(bent, i, kernels.perturb_normal(geo, prim[i], _vec(n_in, i), (rgb[i, 0], rgb[i, 1], rgb[i, 2])))
    return lookup, sky_radiance, film, bent


@needs_numba
def test_textures_sky_map_normal_maps_and_transient_bins_equal_numpy():
    """Bilinear texture lookups with repeat (float32, bit for bit) at texel centres, edges, negative and large
    UVs; the environment map's radiance (atan2: 1e-12) with the poles clamped; the transient split between
    bin centres, bins out of range dropped (the same addends, bit for bit, in this order); normal maps (the
    tangent from the UVs, degenerate UVs falling back to the basis): bit for bit."""
    g = draws(12)
    albedo = Texture(g.random((5, 7)), "albedo")
    normal = Texture(g.uniform(0.2, 0.8, (4, 6, 3)), "bumps")
    sky = Texture(g.uniform(0.0, 2.0, (8, 16)), "sky")
    slots, textures, sky_index = packing.texture_store([Material(reflectance_texture=albedo, normal_texture=normal)],
                                                       sky)
    assert slots.tolist() == [[0, -1, -1, 1]] and sky_index == 2
    uv = np.concatenate([g.uniform(-3.0, 4.0, (500, 2)), [[0.0, 0.0], [1.0, 1.0], [0.5 / 7, 1 - 0.5 / 5],
                                                          [-1e-9, 0.999999], [12.25, -7.5]]])
    directions = unit_vectors(g, 300)
    directions[:3] = ((0, 0, 1), (0, 0, -1), (-1, 0, 0))
    ambient = tofcore.Ambient(radiance_w_m2_sr=0.05, environment=sky, environment_strength=1.7)
    strength = float(np.float32(ambient.environment_strength))
    lengths = np.concatenate([g.uniform(-0.5, 13.0, 400), [0.0, 0.05, 0.1, 11.95, 12.0, 30.0]])
    weights = g.random(len(lengths))
    setup, packed = room_setup()
    prim = g.integers(0, len(setup.scene.triangles), 200)
    n_in = unit_vectors(g, 200)
    rgb = g.uniform(0.0, 1.0, (200, 3)).astype(np.float32)
    lookup, sky_radiance, film, bent = _textures_sky_bins(
        textures, uv, directions, np.array([strength, float(sky_index)]), 0.05, lengths, weights, 0.1, 120,
        (prim, n_in, rgb), packed.geo)
    twin("texture_sample", lookup[0], albedo.sample(uv))
    twin("texture_sample", lookup[1:], normal.sample(uv)[:, [0, 2]].T, what="(an RGB image's channels 0, 2)")
    twin("ambient_radiance", sky_radiance, ambient.radiance(directions), TRANSCENDENTAL)
    film_ref = np.zeros((1, 120))
    tally = types.SimpleNamespace(out=types.SimpleNamespace(transient_sum=film_ref), transient_bin_m=0.1, n_pix=1,
                                  p0=0, p1=1)
    for w, length in zip(weights, lengths):  # one addend at a time: the kernels' order
        Tally._add_transient(tally, np.zeros(1, np.int64), np.array([w]), np.array([length]))
    twin("add_transient", film, film_ref)
    twin("perturb_normal", bent, surface._perturb(setup.table, prim, n_in, rgb))
    values = (0.25, 0.5, 0.75, 1.5, 2.5, 0.6, 0.125)
    reference = bsdf.SurfaceParams(**dict(zip(PARAMETER_NAMES, values)))
    assert tuple(f.name for f in dataclasses.fields(bsdf.SurfaceParams)) == PARAMETER_NAMES
    twin("surface_params", np.array(_params(np.array([values]), 0)),
         [getattr(reference, name)[0] for name in PARAMETER_NAMES], what="(fields in the material table's order)")


# ------------------------------------------------------------------ reflection (tofcore.scene.fresnel, bsdf, sampling)
@jitted
def _params(p, i):
    return kernels.surface_params(p[i, 0], p[i, 1], p[i, 2], p[i, 3], p[i, 4], p[i, 5], p[i, 6])


@jitted
def _reflection(params, wo, wi, u, outgoing, pair_valid, pair_h, pair_scalars):
    """Every reflection function on point i's parameters and directions; ``outgoing`` (F_d(θ_o), P_s, F_c(θ_o),
    P_c) and the pair's terms are the reference's, as inputs of the functions that take them."""
    n = len(wo)
    scalars = np.empty((18, n))
    h = np.empty((2, n, 3))
    terms = np.empty((8, n))
    sampled = np.empty((2, n, 3))
    sample_terms = np.empty((3, n))
    for i in range(n):
        p, o, w = _params(params, i), _vec(wo, i), _vec(wi, i)
        _put(sampled[1], i, kernels.reflect_visible_normal(o, u[i, 3], u[i, 1], u[i, 2], u[i, 0]))
        scalars[0, i] = kernels.fresnel_dielectric(w[2], p[3])
        scalars[1, i] = kernels.fresnel_conductor(w[2], p[3], p[4])
        scalars[2, i] = kernels.specular_fresnel(p, w[2])
        scalars[3, i], scalars[4, i], scalars[13, i], scalars[14, i] = kernels.outgoing(p, o[2])
        scalars[5, i] = kernels.rough_alpha(p[1])
        scalars[6, i] = kernels.beckmann_distribution(w[2], u[i, 3])
        scalars[7, i] = kernels.oren_nayar(p[0], p[1], w[2], o[2], u[i, 4])
        scalars[8, i] = kernels.cos_azimuth_difference(o, w)
        scalars[9, i] = kernels.eval_bsdf(p, o, w)
        scalars[10, i], scalars[11, i] = kernels.eval_pdf_bsdf(p, o, w)
        pair = (pair_scalars[0, i], pair_valid[i], _vec(pair_h, i), pair_scalars[1, i], pair_scalars[2, i],
                pair_scalars[3, i], pair_scalars[4, i], pair_scalars[5, i])
        scalars[12, i] = kernels.pdf_terms(o, (outgoing[1, i], outgoing[3, i]), pair)
        scalars[15, i] = kernels.specular_density(o, _vec(pair_h, i), pair_scalars[1, i], pair_scalars[4, i],
                                                  pair_scalars[5, i])
        scalars[16, i] = kernels.coat_fresnel(p, o[2])
        _put(h[0], i, kernels.half_vector(o, w))
        f, (t_cos_i, valid, t_h, t_cos_oh, t_alpha, t_distribution, t_coat_alpha, t_coat_distribution) = \
            kernels.eval_terms(p, o, w, outgoing[0, i], outgoing[2, i])
        terms[0, i], terms[1, i], terms[2, i] = f, t_cos_i, 1.0 if valid else 0.0
        terms[3, i], terms[4, i], terms[5, i] = t_cos_oh, t_alpha, t_distribution
        terms[6, i], terms[7, i] = t_coat_alpha, t_coat_distribution
        _put(h[1], i, t_h)
        s_wi, weight, pdf, is_delta = kernels.sample_bsdf(p, o, u[i, 0], u[i, 1], u[i, 2])
        _put(sampled[0], i, s_wi)
        sample_terms[0, i], sample_terms[1, i], sample_terms[2, i] = weight, pdf, 1.0 if is_delta else 0.0
    return scalars, h, terms, sampled, sample_terms


def reflection_inputs(n: int):
    """(SurfaceParams, wo, wi, uniforms (n, 5): u_lobe, u1, u2, an α, a cos φ) with every branch of the model:
    dielectrics, metals and blends; mirrors, σ just below the mirror threshold, rough; η = 1, η < 1 (total
    internal reflection); ρ = 0; directions below the surface, on the normal, opposite, mirrored."""
    g = draws(4)
    reflectance = g.random(n)
    reflectance[::7] = 0.0
    roughness = g.uniform(0.0, 1.2, n)
    roughness[::5] = 0.0
    roughness[1::11] = 0.5 * bsdf.SMOOTH_ROUGHNESS_RAD
    metallic = g.choice([0.0, 1.0, 0.5, 0.25], n)
    ior = g.uniform(1.0, 3.0, n)
    ior[::9] = 1.0
    ior[4::13] = 0.7
    extinction = g.uniform(0.0, 8.0, n)
    params = bsdf.SurfaceParams(reflectance=reflectance, roughness=roughness, metallic=metallic, ior=ior,
                                extinction=extinction)
    wo = unit_vectors(g, n)
    wo[:, 2] = np.abs(wo[:, 2])
    wo[::10, 2] *= -1.0
    wi = unit_vectors(g, n)
    wo[:3] = ((0, 0, 1), (0, 0, 1), (0.6, 0, 0.8))
    wi[:3] = ((0, 0, 1), (0.6, 0.0, 0.8), (-0.6, 0, -0.8))
    wi[3::17] = wo[3::17] * (-1.0, -1.0, 1.0)  # the mirror direction
    u = g.random((n, 5))
    u[:, 3] = g.uniform(0.0, 2.0, n)          # α of the Beckmann D
    u[:5, 3] = (0.0, 1e-60, 1e-3, 0.5, 5.0)
    u[:, 4] = g.uniform(-1.0, 1.0, n)         # cos φ of Oren–Nayar
    u[:4, 0] = (0.0, bsdf.MIN_LOBE_PROBABILITY, 0.5, np.nextafter(1.0, 0.0))
    return params, wo, wi, u


def _coated(params: bsdf.SurfaceParams, n: int) -> bsdf.SurfaceParams:
    """The points of ``params`` half of them under a clear coat: weights 0.3 and 1, a mirror coat, one just below
    the mirror threshold and rough ones."""
    g = draws(5)
    coat = g.choice([0.0, 0.0, 0.3, 1.0], n)
    coat_roughness = g.choice([0.0, 0.5 * bsdf.SMOOTH_ROUGHNESS_RAD, 0.05, 0.4], n)
    return dataclasses.replace(params, coat=coat, coat_roughness=coat_roughness)


@needs_numba
def test_reflection_equals_fresnel_bsdf_and_sampling():
    """Fresnel terms, lobe probabilities, the half vector and α bit for bit; everything through the Beckmann D
    (exp), Oren–Nayar (acos, sin, tan, pow) or a sampled microfacet normal (log1p, sin, cos) to 1e-12."""
    params, wo, wi, u = reflection_inputs(3000)
    params = _coated(params, 3000)
    coated = params.coat > 0.0
    cos_o, cos_i = wo[:, 2], wi[:, 2]
    out = bsdf._outgoing(params, cos_o)
    pair = bsdf._pair(params, wo, wi)
    # the kernels' coat terms are 0 at a point without a coat (the reference computes them for the whole batch)
    coat_alpha, coat_distribution = (np.where(coated, a, 0.0) for a in (pair.coat_alpha, pair.coat_distribution))
    pair_scalars = np.array([pair.cos_i, pair.cos_oh, pair.alpha, pair.distribution, coat_alpha, coat_distribution])
    outgoing = np.array([out.fresnel_o, out.probability, np.where(coated, out.coat_fresnel_o, 0.0),
                         out.coat_probability])
    matrix = np.column_stack([getattr(params, k) for k in PARAMETER_NAMES])
    scalars, h, terms, sampled, sample_terms = _reflection(matrix, wo, wi, u, outgoing, pair.valid, pair.h,
                                                           pair_scalars)
    twin("fresnel_dielectric", scalars[0], fresnel.fresnel_dielectric(cos_i, params.ior))
    twin("fresnel_conductor", scalars[1], fresnel.fresnel_conductor(cos_i, params.ior, params.extinction))
    twin("specular_fresnel", scalars[2], bsdf.specular_fresnel(params, cos_i))
    twin("outgoing", np.vstack([scalars[3:5], scalars[13:15]]), outgoing)
    twin("rough_alpha", scalars[5], bsdf._rough_alpha(params.roughness))
    twin("beckmann_distribution", scalars[6], sampling.beckmann_distribution(cos_i, u[:, 3]), TRANSCENDENTAL)
    twin("oren_nayar", scalars[7], bsdf.oren_nayar(params.reflectance, params.roughness, cos_i, cos_o, u[:, 4]),
         TRANSCENDENTAL)
    # one square root of the product where the reference multiplies two hypot calls: 4e-16 relative
    twin("cos_azimuth_difference", scalars[8], bsdf.cos_azimuth_difference(wo, wi), TRANSCENDENTAL)
    twin("eval_bsdf", scalars[9], bsdf.eval_bsdf(params, wo, wi), TRANSCENDENTAL)
    twin("eval_pdf_bsdf", scalars[10:12], np.array(bsdf.eval_pdf_bsdf(params, wo, wi)), TRANSCENDENTAL)
    twin("pdf_terms", scalars[12], bsdf._pdf(wo, out.probability, pair, out.coat_probability))
    rough_coat = (pair.cos_oh > 0.0) & (coat_alpha > 0.0)
    twin("specular_density", scalars[15], np.where(rough_coat, sampling.pdf_vcavity_visible_normal(
        wo, pair.h, coat_alpha, distribution=coat_distribution) * (1.0 / (4.0 * np.where(rough_coat, pair.cos_oh, 1.0))),
        0.0))
    twin("coat_fresnel", scalars[16], np.where(coated, fresnel.fresnel_dielectric(cos_o, bsdf.COAT_IOR), 0.0))
    twin("half_vector", h[0], bsdf._half_vector(wo, wi))
    twin("eval_terms", terms[0], bsdf._eval(params, wo, wi, cos_o, out.fresnel_o, pair, out.coat_fresnel_o),
         TRANSCENDENTAL)
    twin("eval_terms", terms[1:3], np.array([pair.cos_i, pair.valid]), what="(cos θ_i, valid)")
    twin("eval_terms", h[1], pair.h, what="(h)")
    twin("eval_terms", terms[3:5], np.array([pair.cos_oh, pair.alpha]), what="(ω_o·ω_h, α)")
    twin("eval_terms", terms[5], pair.distribution, TRANSCENDENTAL, what="(D)")
    twin("eval_terms", terms[6:8], np.array([coat_alpha, coat_distribution]), TRANSCENDENTAL, what="(the coat's α, D)")
    s = bsdf.sample_bsdf(params, wo, u[:, 0], u[:, 1], u[:, 2])
    twin("sample_bsdf", sampled[0], s.wi, TRANSCENDENTAL, what="(wi)")
    alpha = u[:, 3]  # 0 (a mirror) for the first point
    twin("reflect_visible_normal", sampled[1], bsdf._reflect(
        wo, sampling.sample_vcavity_visible_normal(wo, alpha, u[:, 1], u[:, 2], u[:, 0]), alpha), TRANSCENDENTAL)
    twin("sample_bsdf", sample_terms[0:2], np.array([s.weight, s.pdf]), TRANSCENDENTAL, what="(weight, pdf)")
    twin("sample_bsdf", sample_terms[2], s.is_delta, what="(is_delta)")
    assert 0 < s.is_delta.sum() < len(wo) and (s.weight == 0).any() and (s.weight > 0).any()
    coat_mirror = s.is_delta & coated & (params.coat_roughness < bsdf.SMOOTH_ROUGHNESS_RAD)
    assert coat_mirror.any() and (s.is_delta & coated & (params.roughness < bsdf.SMOOTH_ROUGHNESS_RAD)).any()


# ------------------------------------------------------------------ camera (tofcore.scene.camera)
@jitted
def _camera(cam, table, x, y, pixel, jitter):
    n = len(x)
    distorted = np.empty((5, n))
    undistorted = np.empty((2, n))
    rays = np.empty((2, n, 3))
    width = np.int64(cam[0])
    for i in range(n):
        xd, yd, j_xx, j_xy, j_yy = kernels.distort_with_jacobian(cam, x[i], y[i])
        distorted[0, i], distorted[1, i], distorted[2, i], distorted[3, i], distorted[4, i] = xd, yd, j_xx, j_xy, j_yy
        row = pixel[i] // width
        col = pixel[i] - row * width
        u_d = (col + (jitter[i, 0] - 0.5 - cam[3])) / cam[1]
        v_d = (row + (jitter[i, 1] - 0.5 - cam[4])) / cam[2]
        undistorted[0, i], undistorted[1, i] = kernels.undistort_near(cam, table, u_d, v_d, row, col)
        origin, direction = kernels.camera_ray(cam, table, pixel[i], jitter[i, 0], jitter[i, 1], jitter[i, 2],
                                               jitter[i, 3])
        _put(rays[0], i, origin)
        _put(rays[1], i, direction)
    return distorted, undistorted, rays


@needs_numba
def test_camera_rays_equal_the_camera_model():
    """OpenCV distortion and its Jacobian, Newton's inverse from the tabulated pixel centre, camera rays (pinhole,
    distorted, thin lens). Bit for bit, except a thin lens's disk sample (sin, cos: 1e-12).

    The reference is called one sample at a time where Newton's method runs: the kernel stops each sample's
    iteration at its own convergence, NumPy a block's at its slowest sample's, and a step after convergence
    can still move the last bit, so NumPy's value of a sample depends on the other samples of its block (on
    this distorted camera about a third of the coordinates of a block differ by an ulp, < 4e-16; checked
    below on the whole block to 1e-15).
    """
    g = draws(5)
    n = 400
    cameras = {"pinhole": Camera.from_fov(32, 24, 70.0),
               "distorted": Camera.from_fov(32, 24, 75.0, k1=0.09, k2=-0.27, k3=0.09, p1=0.002, p2=-0.001),
               "thin lens": Camera.from_fov(32, 24, 60.0, k1=-0.05, p2=0.001, aperture_radius_m=0.004,
                                            focus_distance_m=1.5)}
    x, y = g.uniform(-0.6, 0.6, (2, n))
    jitter = g.random((n, 4))
    jitter[:2, :2] = (0.0, 0.0), (np.nextafter(1.0, 0.0), 0.5)
    for label, cam in cameras.items():
        pixel = g.integers(0, cam.width * cam.height, n)
        pixel[:2] = (0, cam.width * cam.height - 1)
        distorted, undistorted, rays = _camera(packing.camera_numbers(cam), packing.camera_table(cam), x, y, pixel,
                                               jitter)
        twin("distort_with_jacobian", distorted, np.array(cam._distort_with_jacobian(x, y)), what=label)
        row, col = np.divmod(pixel, cam.width)
        u_d = (col + (jitter[:, 0] - 0.5 - cam.cx)) / cam.fx
        v_d = (row + (jitter[:, 1] - 0.5 - cam.cy)) / cam.fy
        one_by_one = [cam._ray_block(pixel[i:i + 1], *jitter[i:i + 1].T) for i in range(n)]
        origins, directions = (np.concatenate(parts) for parts in zip(*one_by_one))
        lens = TRANSCENDENTAL if cam.aperture_radius_m > 0 else EXACT
        twin("camera_ray", rays[0], origins, lens, what=label)
        twin("camera_ray", rays[1], directions, lens, what=label)
        block = cam._ray_block(pixel, *jitter.T)
        np.testing.assert_allclose(rays[1], block[1], rtol=0, atol=1e-15, err_msg=label)
        if cam.has_distortion:
            reference = np.array([np.concatenate(v) for v in zip(*(
                cam._undistort_near(u_d[i:i + 1], v_d[i:i + 1], row[i:i + 1], col[i:i + 1]) for i in range(n)))])
            twin("undistort_near", undistorted, reference, what=label)
            np.testing.assert_allclose(undistorted, cam._undistort_near(u_d, v_d, row, col), rtol=0, atol=1e-15)


# ------------------------------------------------------------------ BVH traversal and surfaces (scene, tracer.surface)
def odd_materials_room() -> tofcore.Scene:
    """The demo room with a mirror, a half metal, an η = 1 dielectric, a metal and interpolated vertex normals:
    delta lobes, the blended Fresnel, shading normals apart from the geometric ones (as test_compiled.py); the
    walls textured (reflectance, roughness, a normal map) and the metal's metallic mask too; the half metal under
    a clear coat."""
    room = tofcore.demo_scene("room", detail=2)
    g = draws(6)
    normals = np.zeros_like(room.vertices, dtype=np.float64)
    normals[room.triangles.ravel()] = np.repeat(room.face_normals, 3, axis=0)
    normals += 0.15 * g.normal(size=normals.shape)
    materials = (Material(name="mirror", reflectance=0.2, roughness=0.0),
                 Material(name="half metal", metallic=0.5, ior=1.4, extinction=3.0, roughness=0.3, coat=0.7,
                          coat_roughness=0.2),
                 Material(name="no fresnel", reflectance=0.9, roughness=0.8, ior=1.0),
                 Material(name="metal", metallic=1.0, ior=1.35, extinction=9.6, roughness=0.15,
                          metallic_texture=Texture(g.choice([0.0, 1.0], (4, 4)), "mask")),
                 Material(name="walls", reflectance=0.7, roughness=0.6,
                          reflectance_texture=Texture(g.random((8, 6)), "albedo"),
                          roughness_texture=Texture(g.uniform(0.0, 1.0, (5, 7)), "gloss"),
                          normal_texture=Texture(g.uniform(0.3, 0.7, (6, 4, 3)), "bumps")))
    ids = room.material_ids % len(materials)
    uvs = room.vertices[:, :2] * (0.7, 0.4) + room.vertices[:, 2:] * 0.9  # a plane projection: repeats, tilts
    return tofcore.Scene.from_arrays(room.vertices, room.triangles, ids, materials, normals=normals, uvs=uvs,
                                     name="odd room")


@functools.lru_cache(maxsize=1)
def room_setup():
    """(TraceSetup, Packed) of a small render of the odd room: 12 × 10 distorted pinhole camera, an LED at the
    pinhole (first-hit shadow rays skipped) and a Lambertian one beside it, every kind of correlation channel,
    max_depth 3, light vertices on."""
    scene = odd_materials_room()
    camera = Camera.from_fov(12, 10, 70.0, k1=0.05, k2=-0.02, p1=0.001)
    leds = (LED(position_m=(0.0, 0.0, 0.0)), LED(position_m=(-0.03, 0.01, 0.0), intensity_w_sr=2.0, kind="lambertian"))
    settings = TraceSettings(world_from_sensor=tofcore.suggested_pose(tofcore.demo_scene("room", detail=2)),
                             correlations=correlation_channels(), max_depth=3, seed=5, transient_bin_m=0.1,
                             transient_max_m=12.0)
    setup = make_setup(scene, camera, leds, settings, backend.select_device("cpu"))
    assert setup.light_paths and setup.skip_first_shadow.tolist() == [True, False]
    return setup, packing.pack(setup)


@jitted
def _scene_queries(geo, o, d, t_max, ignore, o64, d64, prim, u, v):
    """traverse (closest, any hit) and intersect per ray; surface_at and spawn_offset per hit."""
    n = len(o)
    t = np.empty((3, n), np.float32)
    hit = np.empty((3, n), np.int64)
    bary = np.empty((2, 2, n), np.float32)
    work = (np.zeros(kernels.N_COUNTERS, np.int64), np.empty(kernels.STACK_SIZE, np.int64),
            np.empty(kernels.STACK_T_SIZE, np.float32), np.zeros(1))
    bvh_arrays = (geo[0], geo[1], geo[2], geo[3])
    for i in range(n):
        ray_o, ray_d = _vec(o, i), _vec(d, i)
        t[0, i], hit[0, i], bary[0, 0, i], bary[0, 1, i] = kernels.traverse(bvh_arrays, ray_o, ray_d, t_max[i],
                                                                             ignore[i], False, work[1], work[2])
        t[1, i], hit[1, i], _, _ = kernels.traverse(bvh_arrays, ray_o, ray_d, t_max[i], ignore[i], True, work[1],
                                                    work[2])
        t[2, i], hit[2, i], bary[1, 0, i], bary[1, 1, i] = kernels.intersect(geo, ray_o, ray_d, t_max[i], ignore[i],
                                                                             False, work)
    m = len(prim)
    rows = np.empty((m, SURFACE_ROWS))
    offset = np.empty(m)
    for i in range(m):
        surf = kernels.surface_at(geo, prim[i], u[i], v[i], _vec(o64, i), _vec(d64, i))
        _put_surf(rows, i, surf)
        offset[i] = kernels.spawn_offset(geo, prim[i], surf[0], surf[1])
    return t, hit, bary, rows, offset


@needs_numba
def test_traversal_and_surfaces_equal_the_bvh_and_surface_at():
    """Closest and any hits (with t_max and an ignored triangle) as BVH.intersect/occluded, the surface where a
    float64 ray hits (also grazing its triangle's plane) as surface_at, the spawn offset: bit for bit."""
    setup, packed = room_setup()
    scene, geo = setup.scene, packed.geo
    g = draws(7)
    n = 3000
    lo, hi = scene.bounds
    o = (lo + (hi - lo) * (0.05 + 0.9 * g.random((n, 3)))).astype(np.float32)
    d = unit_vectors(g, n).astype(np.float32)
    d[:3] = ((0, 0, 1), (0, 0, -1), (1, 0, 0))  # axis-parallel: zero direction components
    t_max = np.where(g.random(n) < 0.5, np.float32(np.inf), (g.random(n) * 3).astype(np.float32))
    closest = scene.bvh.intersect(o, d, workers=1)
    ignore = np.where(g.random(n) < 0.3, closest.prim, -1).astype(np.int64)  # as a ray leaving that triangle
    reference = scene.bvh.intersect(o, d, t_max, ignore, workers=1)
    hits = np.flatnonzero(reference.prim >= 0)
    o64 = o[hits].astype(np.float64) + g.normal(scale=1e-6, size=(len(hits), 3))
    d64 = d[hits].astype(np.float64)
    d64 /= np.linalg.norm(d64, axis=1, keepdims=True)
    grazing = hits[:40:4]  # rays in their triangle's plane: the barycentric position
    ng = scene.face_normals[reference.prim[grazing]].astype(np.float64)
    d64[:40:4] = np.cross(ng, unit_vectors(g, len(grazing)))
    d64[:40:4] /= np.linalg.norm(d64[:40:4], axis=1, keepdims=True)
    prim, u, v = reference.prim[hits].astype(np.int64), reference.u[hits], reference.v[hits]
    t, hit, bary, rows, offset = _scene_queries(geo, o, d, t_max, ignore, o64, d64, prim, u, v)
    assert 0.2 < len(hits) / n < 1.0
    uv = np.array([reference.u, reference.v])[:, hits]
    twin("traverse", hit[0], reference.prim, what="(prim)")
    twin("traverse", t[0][hits], reference.t[hits], what="(t)")
    twin("traverse", bary[0][:, hits], uv, what="(u, v)")
    twin("intersect", hit[2], reference.prim, what="(prim)")
    twin("intersect", t[2][hits], reference.t[hits], what="(t)")
    twin("intersect", bary[1][:, hits], uv, what="(u, v)")
    twin("traverse", hit[1] >= 0, scene.bvh.occluded(o, d, t_max, ignore, workers=1), what="(any hit)")
    with np.errstate(invalid="ignore"):  # the reference's masked-out ray-plane point of exactly grazing rays: inf·0
        surf = surface.surface_at(scene, setup.table, prim, u, v, o64, d64)
    twin("surface_at", rows, surface_rows(surf))
    corners = setup.table.vertices[setup.table.triangles[prim]]
    twin("spawn_offset", offset, surface.spawn_offset(surf.position, surf.geometric_normal, corners))


# ------------------------------------------------------------------ one path: the stages, vertex by vertex
def without_shadow_tests(setup):
    """The set-up with a scene whose BVH occludes nothing: the stages' estimates before their shadow tests."""
    clear = types.SimpleNamespace(occluded=lambda origins, *args, **kwargs: np.zeros(len(origins), bool))
    return dataclasses.replace(setup, scene=types.SimpleNamespace(bvh=clear))


@functools.lru_cache(maxsize=1)
def stage_levels():
    """The NumPy stages of two samples a pixel of :func:`room_setup`, for vertices 1 and 2: per level, the state
    that reaches the vertex, the hits, the shaded state and vertex, and what each stage gives there."""
    setup, _ = room_setup()
    free = without_shadow_tests(setup)
    n_pix = setup.camera.width * setup.camera.height
    pixel, sample = integrator.chunk_samples(np, 0, np.zeros(n_pix, np.int64), np.full(n_pix, 2, np.int64))
    stats = TraceStats()
    state = stages.camera_rays(setup, pixel, sample)
    light = light_paths.trace_light_vertices(setup, stats, state.pixel, state.sample)
    first, levels = state, []
    for k in (1, 2):
        hit_state, hits, _ = stages.intersect(setup, state, k, stats)
        shaded, vertex = stages.shade(setup, hit_state, hits, k)
        leds = range(len(setup.leds))
        levels.append(types.SimpleNamespace(
            k=k, arriving=state, hit_state=hit_state, hits=hits, shaded=shaded, vertex=vertex,
            to_led=[stages._to_led(setup, shaded, vertex, i, stats) for i in leds],
            to_led_free=[stages._to_led(free, shaded, vertex, i, stats) for i in leds],
            next_event=stages.next_event(setup, shaded, vertex, stats),
            connect=light_paths.connect(setup, shaded, vertex, light, stats),
            connect_free=light_paths.connect(free, shaded, vertex, light, stats),
            light_vertex=stages.light_vertex(setup, shaded, vertex, light, stats),
            scattered=stages.scatter(setup, shaded, vertex)))
        state = levels[-1].scattered
    return setup, first, light, levels


def light_rows(setup, light, rows: np.ndarray):
    """(found (N,), surface rows (N, SURFACE_ROWS), rest (N, 7): y → LED, |y − LED|, emitted, p_B, margin) of the light
    vertices ``rows`` (−1: none), the margin as light_paths.connect computes it."""
    found = rows >= 0
    take = np.where(found, rows, 0)
    y = light.surface.take(take)
    corners = setup.table.vertices[setup.table.triangles[light.prim[take]]]
    margin = 4.0 * surface.spawn_offset(y.position, y.geometric_normal, corners)
    rest = np.column_stack([light.to_led[take], light.led_distance[take], light.emitted[take], light.pdf_area[take],
                            margin])
    return found, surface_rows(y), np.ascontiguousarray(rest)


@jitted
def _camera_paths(scene, key, independent, pixel, sample, origin, direction, depth, prev_prim):
    """camera_start per sample; ray_query and next_hit of the rays (origin, direction) at ``depth``."""
    n, m = len(pixel), len(origin)
    start = np.empty((2, n, 3))
    query = np.empty((m, 3), np.float32)
    hit = np.empty(m, np.int64)
    bary = np.empty((2, m), np.float32)
    work = (np.zeros(kernels.N_COUNTERS, np.int64), np.empty(kernels.STACK_SIZE, np.int64),
            np.empty(kernels.STACK_T_SIZE, np.float32), np.zeros(1))
    for i in range(n):
        o, d = kernels.camera_start(scene, (key, pixel[i], sample[i], independent))
        _put(start[0], i, o)
        _put(start[1], i, d)
    for i in range(m):
        _put(query, i, kernels.ray_query(_vec(origin, i), _vec(direction, i), depth))
        hit[i], bary[0, i], bary[1, i] = kernels.next_hit(scene[0], _vec(origin, i), _vec(direction, i), depth,
                                                          prev_prim[i], work)
    return start, query, hit, bary


@jitted
def _vertices(scene, key, independent, pixel, sample, depth, use_mis, rows, spawn, wo, prim, direction, throughput,
              area_pdf, prev_delta, path_length, light_found, light_surface, light_rest):
    """Every stage at the vertices (rows, spawn, wo, prim) that the rays ``direction`` reached at ``depth``."""
    geo, frame, leds, corr_kinds = scene[0], scene[3], scene[4], scene[5]
    n, n_led, n_corr, n_depth = len(rows), leds[0].shape[0], corr_kinds.shape[0], depth + 1
    work = (np.zeros(kernels.N_COUNTERS, np.int64), np.empty(kernels.STACK_SIZE, np.int64),
            np.empty(kernels.STACK_T_SIZE, np.float32), np.zeros(n_corr))
    vertex_out = np.empty((2, n, 3))
    to_led = np.empty((2, n_led, 2, n))       # (estimate, shadow-tested) × LED × (w, distance)
    to_light = np.empty((2, 2, n))            # (estimate, shadow-tested) × (w_B, extra length)
    added = np.empty((2, n, 1 + n_corr))      # (next events, connection) × (w, w·g_j)
    scattered = np.empty((n, 7))              # direction xyz, weight, pdf, is_delta, kept
    for i in range(n):
        surf = _surf(rows, i)
        spawned, local_wo = kernels.camera_vertex(geo, np.int64(prim[i]), surf, _vec(direction, i))[1:3]
        _put(vertex_out[0], i, spawned)
        _put(vertex_out[1], i, local_wo)
        vertex = (surf, _vec(spawn, i), _vec(wo, i), np.int64(prim[i]))
        state = (throughput[i], depth, area_pdf[i], prev_delta[i], use_mis)
        for led in range(n_led):
            to_led[0, led, 0, i], to_led[0, led, 1, i], _ = kernels.led_estimate(frame, leds, vertex, state, led)
            to_led[1, led, 0, i], to_led[1, led, 1, i] = kernels.connect_led(geo, frame, leds, vertex, state, led,
                                                                             work)
        y = _surf(light_surface, i)
        light = (light_found[i], y, _vec(light_rest, i), light_rest[i, 3], light_rest[i, 4], light_rest[i, 5],
                 light_rest[i, 6])
        to_light[0, 0, i], to_light[0, 1, i] = 0.0, 0.0
        to_light[1, 0, i], to_light[1, 1, i] = 0.0, 0.0
        if light_found[i]:
            to_light[0, 0, i], to_light[0, 1, i] = kernels.light_estimate(vertex, throughput[i], light)
            to_light[1, 0, i], to_light[1, 1, i] = kernels.connect_light(geo, vertex, throughput[i], light, work)
        sums = (np.zeros(n_depth), np.zeros((n_depth, n_corr)), np.zeros(n_depth), np.zeros((n_depth, n_corr)),
                np.zeros(n_corr + 2), np.zeros((1, 0)))
        kernels.add_next_events(scene, vertex, state, path_length[i], (0, 0.0), sums, work)
        kernels.add_connection(scene, vertex, state, path_length[i], light, (0, 0.0), sums, work)
        added[0, i, 0], added[1, i, 0] = sums[0][depth - 1], sums[2][depth]
        added[0, i, 1:], added[1, i, 1:] = sums[1][depth - 1], sums[3][depth]
        new_dir, weight, pdf, is_delta = kernels.next_direction(surf, vertex[2], (key, pixel[i], sample[i],
                                                                                  independent), depth)
        kept = weight > 0 and kernels.dot(new_dir, surf[1]) > 0
        _put(scattered, i, kernels.divide(new_dir, kernels.norm(new_dir)))
        scattered[i, 3], scattered[i, 4] = throughput[i] * weight, pdf
        scattered[i, 5], scattered[i, 6] = 1.0 if is_delta else 0.0, 1.0 if kept else 0.0
    return vertex_out, to_led, to_light, added, scattered


@needs_numba
def test_camera_rays_hits_and_vertices_equal_the_stages():
    """camera_start, ray_query and next_hit as stages.camera_rays and stages.intersect (bit for bit), and at
    vertices 1 and 2 of the NumPy paths (vertex 2 with MIS), with the same inputs: camera_vertex as
    stages.shade (bit for bit); next events, light-vertex connections (before and after their shadow tests)
    and their sums as stages._to_led, light_paths.connect, stages.next_event and stages.light_vertex; the
    sampled next direction as stages.scatter (1e-12: the BSDF's transcendentals)."""
    setup, packed = room_setup()
    first, light, levels = stage_levels()[1:]
    scene = packed.scene()
    key, independent = packed.key, packed.independent
    blocked = []  # (next events, connections) that their shadow test zeroed, per level
    for level in levels:
        k, arriving, shaded, vertex = level.k, level.arriving, level.shaded, level.vertex
        start, query, hit, bary = _camera_paths(scene, key, independent, first.pixel, first.sample, arriving.origin,
                                                arriving.direction, k, arriving.prev_prim.astype(np.int64))
        if k == 1:  # one path at a time, as in test_camera_rays_equal_the_camera_model (Newton's method)
            one_by_one = [stages.camera_rays(setup, first.pixel[i:i + 1], first.sample[i:i + 1])
                          for i in range(len(first))]
            twin("camera_start", start[0], np.concatenate([s.origin for s in one_by_one]))
            twin("camera_start", start[1], np.concatenate([s.direction for s in one_by_one]))
            twin("camera_start", start, np.array([first.origin, first.direction]), NEWTON_BLOCK, what="(a block)")
            twin("ray_query", query, surface.leaving(arriving.origin, arriving.direction), what="(the lens)")
        else:
            twin("ray_query", query, arriving.origin.astype(np.float32), what="(a spawn point)")
        rows = np.searchsorted(arriving.path, level.hit_state.path)  # the rays that hit, in the arriving state
        twin("next_hit", np.flatnonzero(hit >= 0), rows, what=f"(which rays hit, depth {k})")
        twin("next_hit", hit[rows], level.hits.prim, what=f"(prim, depth {k})")
        twin("next_hit", bary[:, rows], np.array([level.hits.u, level.hits.v]), what=f"(u, v, depth {k})")

        found, y_rows, y_rest = light_rows(setup, light, light.row[shaded.path])
        area_pdf = vertex.area_pdf if vertex.area_pdf is not None else np.zeros(len(shaded))
        vertex_out, to_led, to_light, added, scattered = _vertices(
            scene, key, independent, shaded.pixel, shaded.sample, k, setup.light_paths and k >= 2,
            surface_rows(vertex.surface), vertex.spawn, vertex.wo, vertex.prim.astype(np.int64),
            level.hit_state.direction, shaded.throughput, area_pdf, shaded.prev_delta, shaded.length, found, y_rows,
            y_rest)
        at = f"(vertex {k})"
        twin("camera_vertex", vertex_out, np.array([vertex.spawn, vertex.wo]), what=at)
        for i in range(len(setup.leds)):
            twin("led_estimate", to_led[0, i], np.array(level.to_led_free[i]), TRANSCENDENTAL, what=f"{at} LED {i}")
            twin("connect_led", to_led[1, i], np.array(level.to_led[i]), TRANSCENDENTAL, what=f"{at} LED {i}")
        twin("light_estimate", to_light[0], np.array(level.connect_free), TRANSCENDENTAL, what=at)
        twin("connect_light", to_light[1], np.array(level.connect), TRANSCENDENTAL, what=at)
        nee, lv = level.next_event, level.light_vertex
        twin("add_next_events", added[0], np.column_stack([nee.weight, nee.correlation.T]), TRANSCENDENTAL, what=at)
        twin("add_connection", added[1], np.column_stack([lv.weight, lv.correlation.T]), TRANSCENDENTAL, what=at)
        assert (nee.weight > 0).any() and (lv.weight > 0).any()
        blocked.append(((to_led[0, :, 0] > to_led[1, :, 0]).sum(), (to_light[0, 0] > to_light[1, 0]).sum()))

        scattered_state = level.scattered
        kept = np.searchsorted(shaded.path, scattered_state.path)
        twin("next_direction", np.flatnonzero(scattered[:, 6]), kept, what=f"{at} (paths that go on)")
        twin("next_direction", scattered[kept, :3], scattered_state.direction, TRANSCENDENTAL, what=at)
        twin("next_direction", scattered[kept, 3:5].T, np.array([scattered_state.throughput, scattered_state.prev_pdf]),
             TRANSCENDENTAL, what=at)
        twin("next_direction", scattered[kept, 5], scattered_state.prev_delta, what=at)
    assert levels[1].shaded.prev_delta.any()  # a mirror bounce reached vertex 2
    assert np.sum(blocked, axis=0).all(), f"no shadow test of next events or connections blocked: {blocked}"


@jitted
def _light_rays(scene, key, independent, pixel, sample):
    """light_ray and light_vertex per sample: ray (index, origin xyz, direction xyz, pdf, query xyz, f32
    direction xyz) and vertex (found, surface rows, rest as in light_rows)."""
    geo, frame, leds = scene[0], scene[3], scene[4]
    n = len(pixel)
    ray_out = np.empty((n, 8))
    ray_f32 = np.empty((2, n, 3), np.float32)
    found = np.empty(n, np.bool_)
    rows = np.empty((n, SURFACE_ROWS))
    rest = np.empty((n, 7))
    work = (np.zeros(kernels.N_COUNTERS, np.int64), np.empty(kernels.STACK_SIZE, np.int64),
            np.empty(kernels.STACK_T_SIZE, np.float32), np.zeros(1))
    for i in range(n):
        rng = (key, pixel[i], sample[i], independent)
        index, origin, direction, pdf_dir, query, dir_f32 = kernels.light_ray(frame, leds, rng)
        ray_out[i, 0], ray_out[i, 7] = index, pdf_dir
        ray_out[i, 1], ray_out[i, 2], ray_out[i, 3] = origin
        ray_out[i, 4], ray_out[i, 5], ray_out[i, 6] = direction
        _put(ray_f32[0], i, query)
        _put(ray_f32[1], i, dir_f32)
        light = kernels.light_vertex(geo, frame, leds, rng, work)
        found[i] = light[0]
        _put_surf(rows, i, light[1])
        rest[i, 0], rest[i, 1], rest[i, 2] = light[2]
        rest[i, 3], rest[i, 4], rest[i, 5], rest[i, 6] = light[3], light[4], light[5], light[6]
    return ray_out, ray_f32, found, rows, rest


@jitted
def _light_vertices_at(scene, ray_out, ray_f32, prim, u, v):
    """light_vertex_at of the rays ``ray_out``/``ray_f32`` (:func:`_light_rays`) at the hits (prim, u, v)."""
    geo, leds = scene[0], scene[4]
    n = len(prim)
    found = np.empty(n, np.bool_)
    rows = np.empty((n, SURFACE_ROWS))
    rest = np.empty((n, 7))
    for i in range(n):
        ray = (np.int64(ray_out[i, 0]), (ray_out[i, 1], ray_out[i, 2], ray_out[i, 3]),
               (ray_out[i, 4], ray_out[i, 5], ray_out[i, 6]), ray_out[i, 7], _vec(ray_f32[0], i), _vec(ray_f32[1], i))
        light = kernels.light_vertex_at(geo, leds, ray, np.int64(prim[i]), u[i], v[i])
        found[i] = light[0]
        _put_surf(rows, i, light[1])
        rest[i, 0], rest[i, 1], rest[i, 2] = light[2]
        rest[i, 3], rest[i, 4], rest[i, 5], rest[i, 6] = light[3], light[4], light[5], light[6]
    return found, rows, rest


@needs_numba
def test_light_vertices_equal_trace_light_vertices():
    """Each sample's light ray (LED choice, emission direction: sin, cos) and light vertex — where it hits, the
    surface there facing the LED, emitted power, area density, the margin of shadow rays to it — as
    light_paths.trace_light_vertices gives them (1e-12), whether found bit for bit."""
    setup, packed = room_setup()
    first, light = stage_levels()[1:3]
    scene = packed.scene()
    ray_out, ray_f32, found, rows, rest = _light_rays(scene, packed.key, packed.independent, first.pixel, first.sample)
    ref_found, ref_rows, ref_rest = light_rows(setup, light, light.row)
    assert ref_found.mean() > 0.5 and len(np.unique(ray_out[:, 0])) == len(setup.leds)  # a closed room: most hit
    hits = np.flatnonzero(ref_found)
    twin("light_ray", -ray_out[hits, 4:7], light.to_led, TRANSCENDENTAL, what="(direction)")
    twin("light_ray", ray_out[:, 1:4], setup.led_positions[ray_out[:, 0].astype(np.int64)], what="(origin)")
    twin("light_ray", ray_f32[0], surface.leaving(ray_out[:, 1:4], ray_out[:, 4:7]), what="(query)")
    twin("light_ray", ray_f32[1], ray_out[:, 4:7].astype(np.float32), what="(f32 direction)")
    twin("light_vertex", found, ref_found, what="(found)")
    twin("light_vertex", rows[hits], ref_rows[hits], TRANSCENDENTAL, what="(surface of y)")
    twin("light_vertex", rest[hits], ref_rest[hits], TRANSCENDENTAL, what="(y → LED, distance, emitted, p_B, margin)")
    # light_vertex_at on the kernel's rays, hit as the NumPy BVH hits them (the reference's own intersection)
    hit = setup.scene.bvh.intersect(ray_f32[0], ray_f32[1], workers=1)
    found_at, rows_at, rest_at = _light_vertices_at(scene, ray_out, ray_f32, hit.prim.astype(np.int64), hit.u, hit.v)
    twin("light_vertex_at", found_at, ref_found, what="(found)")
    twin("light_vertex_at", rows_at[hits], ref_rows[hits], TRANSCENDENTAL, what="(surface of y)")
    twin("light_vertex_at", rest_at[hits], ref_rest[hits], TRANSCENDENTAL, what="(the rest)")


@jitted
def _trace_paths(scene, settings, first, counts, n_depth, n_rep, n_bins):
    """trace_path over samples [first[p], first[p] + counts[p]) of every pixel, summed as trace_pixels sums."""
    n_pix, n_corr = len(counts), scene[5].shape[0]
    n_ch = n_corr + 2
    signal_sum = np.zeros((n_depth, n_pix))
    correlation_sum = np.zeros((n_depth, n_corr, n_pix))
    replicate_sum = np.zeros((n_rep, n_ch, n_pix))
    film = np.zeros((n_pix, n_bins))
    for p in range(n_pix):
        nee_w, con_w = np.zeros(n_depth), np.zeros(n_depth)
        nee_wg, con_wg = np.zeros((n_depth, n_corr)), np.zeros((n_depth, n_corr))
        total = np.zeros(n_ch)
        work = (np.zeros(kernels.N_COUNTERS, np.int64), np.empty(kernels.STACK_SIZE, np.int64),
                np.empty(kernels.STACK_T_SIZE, np.float32), np.zeros(n_corr))
        for sample in range(first[p], first[p] + counts[p]):
            kernels.trace_path(scene, settings, p, sample, (nee_w, nee_wg, con_w, con_wg, total, film), work)
            for c in range(n_ch):
                replicate_sum[sample % n_rep, c, p] += total[c]
        for k in range(n_depth):
            signal_sum[k, p] += con_w[k]
            signal_sum[k, p] += nee_w[k]
            for j in range(n_corr):
                correlation_sum[k, j, p] += con_wg[k, j]
                correlation_sum[k, j, p] += nee_wg[k, j]
    return signal_sum, correlation_sum, replicate_sum, film


@needs_numba
def test_whole_paths_equal_the_integrator():
    """trace_path (summed per pixel as trace_pixels sums) and trace_pixels itself against
    integrator.trace_chunk on the same pixels and samples: the sums per bucket, channel and replicate (1e-12:
    the transcendentals on the way) and the ray counts (bit for bit)."""
    setup, packed = room_setup()
    n_pix = setup.camera.width * setup.camera.height
    first = np.zeros(n_pix, np.int64)
    counts = np.arange(n_pix, dtype=np.int64) % 4 + 1  # 1 to 4 samples: replicates of unequal size
    reference = _empty_transport(setup, None, TraceStats())
    stats = integrator.trace_chunk(setup, reference, 0, n_pix, first=first, counts=counts)
    scene = packed.scene()
    settings = packed.settings()
    n_depth, n_rep = reference.signal_sum.shape[0], reference.replicate_sum.shape[0]
    sums = _trace_paths(scene, settings, first, counts, n_depth, n_rep, reference.transient_sum.shape[1])
    assert reference.transient_sum.sum() > 0
    for name, got in zip(("signal_sum", "correlation_sum", "replicate_sum", "transient_sum"), sums):
        twin("trace_path", got, getattr(reference, name), TRANSCENDENTAL, what=name)
    out = (np.zeros_like(reference.signal_sum), np.zeros_like(reference.correlation_sum),
           np.zeros_like(reference.replicate_sum), np.zeros_like(reference.ambient_sum),
           np.zeros_like(reference.transient_sum), np.zeros((n_pix, kernels.N_COUNTERS), np.int64))
    kernels.trace_pixels(scene, settings, (0, n_pix, first, counts), out)
    for name, got in zip(("signal_sum", "correlation_sum", "replicate_sum", "ambient_sum", "transient_sum"), out):
        twin("trace_pixels", got, getattr(reference, name), TRANSCENDENTAL, what=name)
    rays = [stats.camera_rays, stats.bounce_rays, stats.shadow_rays, stats.light_rays, stats.skipped_shadow_rays]
    twin("trace_pixels", out[5].sum(axis=0), rays, what="(camera, bounce, shadow, light, skipped shadow rays)")
    assert (reference.signal_sum > 0).all(axis=1).any() and stats.skipped_shadow_rays > 0


@jitted
def _wavefront_vertices(scene, key, independent, pixel, sample, depth, use_mis, rows, spawn, wo, prim, throughput,
                        area_pdf, prev_delta, path_length, light_found, light_surface, light_rest):
    """The GPU wavefront's stages of one vertex (wf_shade's calls), compiled for the CPU, into buffers laid out
    as tofcore.compiled.cuda lays them out."""
    frame, leds = scene[3], scene[4]
    n, slots = len(rows), leds[0].shape[0] + 1
    pstate = (np.zeros((13, n)), np.full(n, -1, np.int32))
    light = np.zeros((kernels.LIGHT_COLUMNS, n))
    pend = (np.zeros((slots, n)), np.zeros((slots, n)))
    shadow = (np.zeros((n * slots, 3), np.float32), np.zeros((n * slots, 3), np.float32),
              np.full(n * slots, kernels.NO_RAY, np.float32), np.full(n * slots, -1, np.int32))
    rays = (np.zeros((n, 3), np.float32), np.zeros((n, 3), np.float32), np.full(n, -1, np.int32),
            np.full(n, kernels.NO_RAY, np.float32))
    counters = np.zeros((kernels.N_COUNTERS, n), np.int64)
    buffers = (pstate, light, pend, shadow, rays, counters, np.zeros((scene[5].shape[0] + 2, n)))
    went_on = np.zeros(n, np.bool_)
    for j in range(n):
        surf = _surf(rows, j)
        vertex = (surf, _vec(spawn, j), _vec(wo, j), np.int64(prim[j]))
        kernels.queue_next_events(leds, frame, vertex, (throughput[j], depth, area_pdf[j], prev_delta[j], use_mis),
                                  path_length[j], j, buffers)
        kernels.store_light(light, j, (light_found[j], _surf(light_surface, j), _vec(light_rest, j), light_rest[j, 3],
                                       light_rest[j, 4], light_rest[j, 5], light_rest[j, 6]))
        kernels.queue_connection(vertex, throughput[j], path_length[j], j, buffers)
        went_on[j] = kernels.continue_path(surf, vertex, (key, pixel[j], sample[j], independent), depth,
                                           throughput[j], j, buffers)
    return pstate, pend, shadow, rays, counters, went_on


@needs_numba
def test_the_wavefronts_vertex_stages_equal_the_stages():
    """The GPU wavefront's stages of a vertex, compiled for the CPU, at vertices 1 and 2 of the NumPy paths:
    queue_next_events as stages._to_led (its estimates before the shadow test, and the shadow rays it traces or
    skips), queue_connection as light_paths.connect (likewise), continue_path as stages.scatter (the next state
    and ray of the paths that go on): 1e-12 where the BSDF's transcendentals enter, else bit for bit."""
    setup, packed = room_setup()
    light, levels = stage_levels()[2:]
    scene = packed.scene()
    n_led = len(setup.leds)
    for level in levels:
        k, shaded, vertex = level.k, level.shaded, level.vertex
        n, at = len(shaded), f"(vertex {k})"
        found, y_rows, y_rest = light_rows(setup, light, light.row[shaded.path])
        area_pdf = vertex.area_pdf if vertex.area_pdf is not None else np.zeros(n)
        pstate, pend, shadow, rays, counters, went_on = _wavefront_vertices(
            scene, packed.key, packed.independent, shaded.pixel, shaded.sample, k, setup.light_paths and k >= 2,
            surface_rows(vertex.surface), vertex.spawn, vertex.wo, vertex.prim.astype(np.int64), shaded.throughput,
            area_pdf, shaded.prev_delta, shaded.length, found, y_rows, y_rest)
        slot_o, slot_d, slot_t, slot_ignore = (a.reshape((n, n_led + 1) + a.shape[1:]) for a in shadow)

        w = np.array([w_i for w_i, _ in level.to_led_free])
        length = np.array([shaded.length + distance for _, distance in level.to_led_free])
        twin("queue_next_events", pend[0][:n_led], w, TRANSCENDENTAL, what=at)
        twin("queue_next_events", pend[1][:n_led], length, what=f"{at} (path length)")
        skipped = (w > 0) & ((k == 1) & setup.skip_first_shadow)[:, None]
        traced = (w > 0) & ~skipped
        twin("queue_next_events", slot_t[:, :n_led].T >= 0, traced, what=f"{at} (which shadow rays)")
        for i in np.flatnonzero(traced.any(axis=1)):  # at the first hit, the pinhole LED's are all skipped
            rows = np.flatnonzero(traced[i])
            margin = surface.point_offset(setup.led_positions[i][None])
            expected = surface.shadow_ray(vertex.spawn[rows], setup.led_positions[i], margin)
            got = (slot_o[rows, i], slot_d[rows, i], slot_t[rows, i])
            twin("queue_next_events", np.column_stack(got), np.column_stack(expected), what=f"{at} LED {i} (rays)")
            twin("queue_next_events", slot_ignore[rows, i], vertex.prim[rows], what=f"{at} LED {i} (ignore)")

        w_b, extra = level.connect_free
        twin("queue_connection", pend[0][n_led], w_b, TRANSCENDENTAL, what=at)
        twin("queue_connection", pend[1][n_led], shaded.length + extra, what=f"{at} (path length)")
        twin("queue_connection", slot_t[:, n_led] >= 0, w_b > 0, what=f"{at} (which shadow rays)")
        rows = np.flatnonzero(w_b > 0)
        expected = surface.shadow_ray(vertex.spawn[rows], y_rows[rows, :3], y_rest[rows, 6])
        got = (slot_o[rows, n_led], slot_d[rows, n_led], slot_t[rows, n_led])
        twin("queue_connection", np.column_stack(got), np.column_stack(expected), what=f"{at} (rays)")
        twin("queue_connection", slot_ignore[rows, n_led], vertex.prim[rows], what=f"{at} (ignore)")
        twin("queue_next_events", counters[[2, 4]], np.array([traced.sum(axis=0) + (w_b > 0), skipped.sum(axis=0)]),
             what=f"{at} (shadow rays traced with the connection's, skipped)")

        scattered = level.scattered
        kept = np.searchsorted(shaded.path, scattered.path)
        f = pstate[0][:, kept]
        twin("continue_path", np.flatnonzero(went_on), kept, what=f"{at} (paths that go on)")
        twin("continue_path", f[[0, 2]], np.array([scattered.throughput, scattered.prev_pdf]), TRANSCENDENTAL, what=at)
        twin("continue_path", f[10:13].T, scattered.direction, TRANSCENDENTAL, what=f"{at} (direction)")
        twin("continue_path", np.vstack([f[3], f[4:10]]).T,
             np.column_stack([scattered.prev_delta, scattered.prev_point, scattered.origin]),
             what=f"{at} (delta, previous point, origin)")
        twin("continue_path", pstate[1][kept], scattered.prev_prim, what=f"{at} (previous triangle)")
        twin("continue_path", rays[0][kept], scattered.origin.astype(np.float32), what=f"{at} (ray origin)")
        twin("continue_path", rays[1][kept], scattered.direction.astype(np.float32), TRANSCENDENTAL,
             what=f"{at} (ray direction)")
        twin("continue_path", rays[2][kept], scattered.prev_prim, what=f"{at} (ray's ignored triangle)")
        twin("continue_path", counters[1], went_on, what=f"{at} (bounce rays)")
        assert (rays[3][kept] == np.inf).all() and (rays[3][~went_on] == kernels.NO_RAY).all()


# ------------------------------------------------------------------ the node test's vector instructions
def random_nodes(rng, n: int):
    """(planes, nodes, ex, ey, ez, o, inv, best t) of ``n`` random node tests: planes of 1,000 node records with
    1 % NaN and 1 % inf, entry-plane rows of both signs, float32 rays."""
    planes = rng.normal(size=(7 * 1000, 4)).astype(np.float32)
    planes[rng.random(planes.shape) < 0.01] = np.nan
    planes[rng.random(planes.shape) < 0.01] = np.inf
    nodes = rng.integers(0, 999, n) * 7
    ex, ey, ez = rng.choice([0, 3], n), rng.choice([1, 4], n), rng.choice([2, 5], n)
    o = rng.normal(size=(n, 3)).astype(np.float32)
    inv = (1 / rng.normal(size=(n, 3))).astype(np.float32)
    best = (3 * np.abs(rng.normal(size=n))).astype(np.float32)
    return planes, nodes, ex, ey, ez, o, inv, best


def slab_tests():
    """(kernels.slab_test over many node tests, the same tests one child at a time as the scalar traversal
    wrote them): each returns (hit masks (n,), entry distances (n, 4))."""
    from tofcore.compiled import kernels

    @numba.njit
    def vector(planes, nodes, ex, ey, ez, o, inv, best):
        masks, entries = np.empty(len(nodes), np.int64), np.empty((len(nodes), 4), np.float32)
        for i in range(len(nodes)):
            mask, t = kernels.slab_test(planes, nodes[i], ex[i], ey[i], ez[i], (o[i, 0], o[i, 1], o[i, 2]),
                                        (inv[i, 0], inv[i, 1], inv[i, 2]), best[i])
            masks[i] = mask
            for c in range(4):
                entries[i, c] = t[c]
        return masks, entries

    @numba.njit
    def scalar(planes, nodes, ex, ey, ez, o, inv, best):
        masks, entries = np.empty(len(nodes), np.int64), np.empty((len(nodes), 4), np.float32)
        for i in range(len(nodes)):
            node, mask = nodes[i], 0
            for c in range(4):
                near_x = (planes[node + ex[i], c] - o[i, 0]) * inv[i, 0]
                far_x = (planes[node + 3 - ex[i], c] - o[i, 0]) * inv[i, 0]
                near_y = (planes[node + ey[i], c] - o[i, 1]) * inv[i, 1]
                far_y = (planes[node + 5 - ey[i], c] - o[i, 1]) * inv[i, 1]
                near_z = (planes[node + ez[i], c] - o[i, 2]) * inv[i, 2]
                far_z = (planes[node + 7 - ez[i], c] - o[i, 2]) * inv[i, 2]
                t_in = max(max(max(near_x, near_y), near_z), np.float32(0.0))
                entries[i, c] = t_in
                if t_in <= min(min(min(far_x, far_y), far_z), best[i]):
                    mask |= 1 << c
            masks[i] = mask
        return masks, entries

    return vector, scalar


@pytest.mark.skipif(numba is None, reason="numba is not installed")
def test_the_vector_slab_test_is_the_scalar_one_bit_for_bit():
    """kernels.slab_test (LLVM vector instructions) gives the scalar loop's hit masks and entry distances, NaN and
    inf planes included: the traversal, and so every hit, is unchanged by it."""
    vector, scalar = slab_tests()
    args = random_nodes(np.random.default_rng(7), 20_000)
    (masks, entries), (ref_masks, ref_entries) = vector(*args), scalar(*args)
    np.testing.assert_array_equal(masks, ref_masks)
    np.testing.assert_array_equal(entries.view(np.int32), ref_entries.view(np.int32))
    assert 0 < np.count_nonzero(masks) < len(masks)  # hits and misses both tested
