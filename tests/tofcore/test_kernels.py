"""The kernel table (:data:`tofcore.backend.KERNELS`): every reference function, its CUDA twin and the docs agree.

One parametrised test per entry of the table, in three parts:

* ``table`` (always): the reference is marked with :func:`~tofcore.backend.device_twin` under its own name,
  the twin exists with the same parameters, every entry has inputs below, and the kernel tables of
  ``tofcore/gpu/__init__.py`` and ``docs/architecture.md`` name it;
* ``fake`` (always): ``tests/fakecupy.py`` arrays reach the twin, host arrays the reference;
* ``cuda`` (marked ``gpu``; skipped without CuPy and a CUDA device): the twin on the GPU gives the
  reference's values bit for bit on the inputs below (the domain's edges included).
"""

from __future__ import annotations

import importlib
import inspect
from pathlib import Path

import numpy as np
import pytest

import tofcore
from tofcore import backend, rng
from tofcore.scene import fresnel
from tofcore.sensor import modulation, noise
from tofcore.tracer import qmc

from tests import fakecupy

ROOT = Path(__file__).resolve().parents[2]


def _random_rays(n: int = 200_000):
    """Random rays inside the room's box (no exact ties between triangles), with random t_max and no ignore."""
    scene = tofcore.demo_scene("room")
    g = np.random.default_rng(11)
    lo, hi = scene.vertices.min(axis=0), scene.vertices.max(axis=0)
    origins = (lo + (hi - lo) * g.random((n, 3))).astype(np.float32)
    dirs = g.standard_normal((n, 3))
    dirs = (dirs / np.linalg.norm(dirs, axis=1, keepdims=True)).astype(np.float32)
    t_max = (g.random(n) * 2 * np.linalg.norm(hi - lo)).astype(np.float32)
    return scene.bvh, origins, dirs, t_max


def _samples(n: int = 1_000_000):
    g = np.random.default_rng(0)
    pixel = g.integers(0, 1 << 22, n)
    sample = np.concatenate([np.arange(n // 2), g.integers(0, 1 << 33, n - n // 2)])  # large indices too
    return pixel, sample


def _fresnel_inputs(n: int = 1_000_000):
    """cos θ over [0, 1] plus grazing, normal, out-of-range and tiny values; η < 1 (TIR) and > 1; k ≥ 0."""
    g = np.random.default_rng(3)
    cos = np.concatenate([g.random(n), [0.0, 1.0, -0.1, 1.1, 1e-300]])
    eta = np.concatenate([g.uniform(0.05, 4.0, n), [1.0, 1.52, 0.5, 1.0, 1.0]])
    k = np.concatenate([g.uniform(0.0, 8.0, n), [0.0, 0.0, 3.0, 0.0, 0.0]])
    return cos, eta, k


def _cases(name: str) -> list[tuple[tuple, int | None]]:
    """Host argument tuples for reference ``name``; the int is the argument that goes to the device."""
    key = rng.seed_key(99)
    if name.endswith("rng.uniform"):
        pixel, sample = _samples()
        return [((key, pixel, sample, dim), (1, 2)) for dim in (0, 3, 17, 1000)]
    if name.endswith(("qmc.scrambled_2d", "qmc.scrambled_1d")):
        pixel, sample = _samples()
        return [((key, pixel, sample, dim), (1, 2)) for dim in (0, 1, 7, 1_000_001)]
    if name.endswith("fresnel_dielectric"):
        cos, eta, _ = _fresnel_inputs()
        return [((cos, eta), (0, 1))]
    if name.endswith("fresnel_conductor"):
        return [(_fresnel_inputs(), (0, 1, 2))]
    if name.endswith("square_correlation"):
        g = np.random.default_rng(4)
        tau = np.concatenate([g.uniform(0, 2e-7, 1_000_000), [0.0, 1 / 80e6, -1e-9]])
        return [((tau, f, o, d), (0,)) for f, o, d in ((80e6, 0.0, 0.5), (16e6, 1 / 3, 0.5), (120e6, 2 / 3, 0.3),
                                                       (30e6, 0.75, 0.7))]
    if name.endswith("noise.poisson"):
        g = np.random.default_rng(5)  # every branch: inversion, PTRS near 10 (most rejections), Gaussian
        mean = np.concatenate([g.uniform(0.0, 10.0, 300_000), g.uniform(10.0, 12.0, 300_000),
                               np.exp(g.uniform(np.log(12.0), np.log(1e12), 400_000)),
                               [0.0, 9.999999999999998, 10.0, 1e10, 1e300 ** 0 * 3e15]])
        return [((mean, noise.NoiseStream.from_seed(seed).key, dim), (0,)) for seed, dim in ((0, 0), (7, 64))]
    if name.endswith("BVH.intersect"):
        bvh, o, d, _ = _random_rays()
        return [((bvh, o, d), (1, 2))]
    if name.endswith("BVH.occluded"):
        bvh, o, d, t_max = _random_rays()
        return [((bvh, o, d, t_max), (1, 2, 3))]
    raise KeyError(name)


def _reference(name: str):
    """The marked reference function of table key ``name`` (a method through its class)."""
    parts = name.split(".")
    for split in range(len(parts) - 1, 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:split]))
        except ModuleNotFoundError:
            continue
        for part in parts[split:]:
            obj = getattr(obj, part)
        return obj
    raise ImportError(name)


def _values(result):
    """The arrays of a result (a tuple, a ``Hits`` record or one array) as host NumPy arrays."""
    if isinstance(result, tuple):
        return [backend.to_host(r) for r in result]
    if hasattr(result, "prim"):
        return [backend.to_host(getattr(result, k)) for k in ("t", "prim", "u", "v")]
    return [backend.to_host(result)]


NAMES = sorted(backend.KERNELS)


def test_every_reference_with_a_device_twin_is_in_the_table():
    """No stray marks: every function that dispatches to a kernel is a key of the table (walks the modules)."""
    marked = set()
    for module in (rng, qmc, fresnel, modulation, noise, importlib.import_module("tofcore.scene.bvh")):
        for _, obj in inspect.getmembers(module):
            candidates = [obj] + ([m for _, m in inspect.getmembers(obj)] if inspect.isclass(obj) else [])
            marked |= {c.device_twin for c in candidates if isinstance(getattr(c, "device_twin", None), str)}
    assert marked == set(NAMES)


@pytest.mark.parametrize("name", NAMES)
def test_table(name):
    reference = _reference(name)
    assert getattr(reference, "device_twin", None) == name, f"{name} is not marked @device_twin"
    kernel = backend.twin(name)
    skip = 1 if "BVH." in name else 0  # a method's self is the kernel's first parameter (the BVH)
    assert list(inspect.signature(kernel).parameters)[skip:] == list(inspect.signature(reference).parameters)[skip:], \
        f"{backend.KERNELS[name]} must take the parameters of {name}"
    short = name.rsplit(".", 2)[-2:] if "BVH" in name else name.rsplit(".", 1)[-1:]
    for doc in (ROOT / "tofcore" / "gpu" / "__init__.py", ROOT / "docs" / "architecture.md"):
        assert ".".join(short) in doc.read_text(encoding="utf-8"), f"{doc.name}: the kernel table lacks {name}"


@pytest.mark.parametrize("name", NAMES)
def test_fake_device_arrays_reach_the_twin(name, monkeypatch):
    fakecupy.install(monkeypatch)
    module, function = backend.KERNELS[name].split(":")
    calls = []
    real = getattr(importlib.import_module(module), function)
    monkeypatch.setattr(importlib.import_module(module), function,
                        lambda *a, **k: calls.append(1) or real(*a, **k))
    args, on_device = _cases(name)[0]
    small = tuple(a[:64] if isinstance(a, np.ndarray) and a.ndim >= 1 else a for a in args)
    host = _values(_reference(name)(*small))
    assert not calls
    device_args = tuple(fakecupy.asarray(a) if i in on_device else a for i, a in enumerate(small))
    got = _values(_reference(name)(*device_args))
    assert calls == [1]
    for g, h in zip(got, host):
        np.testing.assert_array_equal(g, h)


def _cuda_available() -> str | None:
    try:
        backend.select_device("gpu")
    except backend.GpuUnavailable as exc:
        return str(exc)
    return None


@pytest.mark.gpu
@pytest.mark.parametrize("name", NAMES)
def test_cuda_twin_equals_reference(name):
    why = _cuda_available()
    if why is not None:
        pytest.skip(f"needs CuPy and a CUDA GPU: {why}")
    import cupy as cp

    reference = _reference(name)
    for args, on_device in _cases(name):
        host = _values(reference(*args))
        got = _values(reference(*(cp.asarray(a) if i in on_device else a for i, a in enumerate(args))))
        if "BVH.intersect" in name:  # a different triangle only on an exact tie in t (random rays: none seen)
            np.testing.assert_array_equal(got[0], host[0])
            same = got[1] == host[1]
            assert same.mean() > 0.9999
            got, host = [g[same] for g in got], [h[same] for h in host]
        for g, h in zip(got, host):
            np.testing.assert_array_equal(g, h)
