"""Golden hashes: CPU frames stay the same bit for bit while the code is reorganised.

Each case renders (or traces) a small frame and hashes its arrays: the raw images, the output depth, the
per-k decoded distances, the render-error estimate and the sample counts of a :func:`tofcore.render`, or
the per-bounce sums, replicate sums, ambient sums and transient histogram of a :func:`tofcore.trace`.
The cases cover 3 demo scenes × 3 presets with and without light vertices, adaptive sampling, ambient
light, the independent sampler and a transient histogram; one case runs chunks on 2 worker processes and
must hash like the same case in this process (chunking and workers never change a frame).

The hashes are SHA-256 of each array's dtype, shape and bytes, kept in ``golden_hashes.json``; NumPy
1.26 (.venv) and NumPy 2 (.venv313) gave the same hashes on the project machine. A change that is meant
to change frames (physics, presets) regenerates them::

    .venv/bin/python tests/tofcore/test_golden.py --regenerate

and says in its commit message which frames changed and why; it keeps only this CPU's set (the others can
no longer be checked: regenerate on each kind of CPU, ``--add`` keeps the others). A reorganisation that
keeps the frames adds the hashes of another kind of CPU with ``--add``. ``--show`` prints the differing
arrays.

The same cases also run on the compiled tracer (the one users get with numba installed), compared with
the NumPy frame of the same machine at test_compiled.py's tolerance: that guard holds on any machine.

Bit-level hashes hold for one set of NumPy's SIMD loops: its float64 sin, cos, exp and log differ in the
last bits between its AVX-512 loops and the C library's (which it calls below AVX-512), and between NumPy 1
and 2 with AVX-512, and float64 sums show it (the three ``trace`` cases differ; every ``render`` case, rounded
to float32, hashes the same). The file holds one set of hashes per architecture, SIMD level and NumPy
major version (:func:`signature`). Until 2026-12-01 the sets were named by the CPU's make ("AMD EPYC",
"Intel Xeon"), which is not what decides: an AMD EPYC with AVX-512 gave the Intel Xeon's hashes, and with
``NPY_DISABLE_CPU_FEATURES`` set to the AVX-512 features the older EPYCs' (AVX2); the sets were renamed
accordingly. Elsewhere the hash cases skip, saying so, and the worker/chunk case compares against the same
frame rendered in this process instead.

The hashes are those of the NumPy reference tracer: ``--regenerate``, ``--add`` and ``--show`` trace with
it (``TOFCORE_TRACER=numpy``, as the test suite does), never with the compiled tracer, whose frames agree
with it only within test_compiled.py's tolerance.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import platform
import sys
from pathlib import Path

import numpy as np
import pytest


from tofcore import Ambient, Camera, demo_scene, load_preset, render, trace

GOLDEN_FILE = Path(__file__).with_name("golden_hashes.json")
WIDTH, HEIGHT = 16, 12

#: name → (kind, scene, preset, settings). Render settings are those of tofcore.render; trace settings
#: those of tofcore.trace with the preset's camera, LEDs and correlation bank.
CASES: dict[str, tuple[str, str, str, dict]] = {
    "plane_kinect_default": ("render", "plane", "kinect_v2", dict(spp=8, max_depth=2)),
    "plane_o3d_no_light_paths": ("render", "plane", "o3d303", dict(spp=8, max_depth=3, light_paths=False)),
    "plane_xtion_ambient": ("render", "plane", "xtion2", dict(spp=8, max_depth=2, ambient="sky")),
    "corner_kinect_adaptive": ("render", "corner", "kinect_v2", dict(spp=40, max_depth=3, adaptive=True)),
    "corner_o3d_default": ("render", "corner", "o3d303", dict(spp=8, max_depth=3)),
    "corner_xtion_independent": ("render", "corner", "xtion2",
                                 dict(spp=8, max_depth=3, sampler="independent", light_paths=False)),
    "box_kinect_ambient_no_light_paths": ("render", "box_on_wall", "kinect_v2",
                                          dict(spp=8, max_depth=3, ambient="env", light_paths=False)),
    "box_o3d_adaptive": ("render", "box_on_wall", "o3d303", dict(spp=40, max_depth=2, adaptive=True)),
    "box_xtion_default": ("render", "box_on_wall", "xtion2", dict(spp=8, max_depth=4)),
    "corner_kinect_trace_transient": ("trace", "corner", "kinect_v2",
                                      dict(spp=8, max_depth=3, transient_bin_m=0.05, transient_max_m=12.0)),
    "box_xtion_trace_ambient_transient": ("trace", "box_on_wall", "xtion2",
                                          dict(spp=8, max_depth=3, ambient="sky", light_paths=False,
                                               transient_bin_m=0.1, transient_max_m=10.0)),
    "room_kinect_trace": ("trace", "room", "kinect_v2", dict(spp=8, max_depth=4)),
}
#: the same frame, traced by 2 worker processes in chunks of 48 paths: must hash like its twin.
PARALLEL_TWIN = ("corner_kinect_trace_transient", dict(workers=2, chunk_size=48))


def _ambient(name: str | None) -> Ambient | None:
    """A uniform sky, or an environment map with a bright band (both exercise the ambient stage)."""
    if name == "sky":
        return Ambient(radiance_w_m2_sr=0.02)
    if name == "env":
        env = np.full((8, 16), 0.01)
        env[5:7] = 0.2
        return Ambient(environment=env, environment_strength=1.5)
    return None


def _sensor(preset: str):
    sensor = load_preset(preset)
    return dataclasses.replace(sensor, camera=Camera.from_fov(WIDTH, HEIGHT, 60.0))


def run_case(name: str, **overrides) -> dict[str, np.ndarray]:
    """The arrays of one case, by name (``overrides`` change its settings)."""
    kind, scene_name, preset, settings = CASES[name]
    settings = dict(settings, seed=7, **overrides)
    settings.setdefault("workers", 1)
    settings["ambient"] = _ambient(settings.get("ambient"))
    scene = demo_scene(scene_name, detail=1)
    sensor = _sensor(preset)
    if kind == "render":
        settings.setdefault("adaptive", False)
        frame = render(scene, sensor, **settings)
        return {"raw": frame.raw, "depth": frame.depth, "distance_per_k": frame.distance_per_k,
                "render_error": frame.render_error, "samples": frame.samples, "valid": frame.valid,
                "amplitude": frame.amplitude, "gt_distance": frame.gt_distance}
    t = trace(scene, sensor.camera, sensor.leds, world_from_sensor=scene.metadata["world_from_sensor"],
              correlations=sensor.modulation.correlation_bank(), **settings)
    arrays = {"sample_count": t.sample_count, "signal_sum": t.signal_sum, "correlation_sum": t.correlation_sum,
              "ambient_sum": t.ambient_sum, "replicate_sum": t.replicate_sum,
              "first_hit_distance": t.first_hit.distance_m, "first_hit_normal": t.first_hit.normal}
    if t.transient_sum is not None:
        arrays["transient_sum"] = t.transient_sum
    return arrays


def digest(array: np.ndarray) -> str:
    """SHA-256 of an array's dtype, shape and bytes (C order): equal iff equal bit for bit."""
    a = np.ascontiguousarray(np.asarray(array))
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())
    return h.hexdigest()[:32]


def hashes(name: str, **overrides) -> dict[str, str]:
    return {key: digest(value) for key, value in run_case(name, **overrides).items()}


BY_CPU = "by_cpu"


def simd_level() -> str:
    """The widest SIMD loops NumPy dispatches to on this machine ("AVX512_SKX", "AVX2", or "baseline"): what its
    float64 sin, cos, exp and log round by (NumPy 1.26 has AVX-512 versions of its own; below AVX-512 it calls
    the C library's). ``NPY_DISABLE_CPU_FEATURES`` lowers it."""
    try:
        from numpy._core._multiarray_umath import __cpu_features__ as features
    except ImportError:  # NumPy 1
        from numpy.core._multiarray_umath import __cpu_features__ as features
    for level in ("AVX512_SKX", "AVX2"):
        if features.get(level):
            return level
    return "baseline"


def signature() -> str:
    """What a set of hashes holds on: the architecture, NumPy's SIMD level (:func:`simd_level`) and NumPy's
    major version. Not the CPU's make: an AMD EPYC with AVX-512 hashes as the Intel Xeon does, and the same
    EPYC with NumPy's AVX-512 loops disabled as the EPYCs without it (checked on 2026-12-01)."""
    return f"{platform.machine()} {simd_level()} NumPy {np.__version__.split('.')[0]}"


def _all_golden() -> dict[str, dict[str, dict[str, str]]]:
    """:func:`signature` → case → array → hash."""
    return json.loads(GOLDEN_FILE.read_text(encoding="utf-8"))[BY_CPU]


def _golden() -> dict[str, dict[str, str]]:
    """This CPU's hashes (case → array → hash); the test skips where there are none."""
    by_cpu = _all_golden()
    if signature() not in by_cpu:
        pytest.skip(f"golden hashes were recorded on {sorted(by_cpu)}; this is {signature()!r} (bit-level "
                    f"float64 sums differ between CPUs; `test_golden.py --add` records this one's set)")
    return by_cpu[signature()]


@pytest.mark.parametrize("name", sorted(CASES))
def test_frame_hashes_are_unchanged(name, monkeypatch):
    """The NumPy reference's frames, whatever TOFCORE_TRACER says (the compiled tracer is held to them at
    test_compiled.py's tolerance below, not bit for bit)."""
    monkeypatch.setenv("TOFCORE_TRACER", "numpy")
    expected = _golden().get(name)
    if expected is None:  # a case changed on purpose and not yet re-recorded on this kind of CPU
        pytest.skip(f"golden case {name!r} has no hashes for {signature()!r}; record them with --add on such a CPU")
    got = hashes(name)
    changed = sorted(k for k in expected.keys() | got.keys() if expected.get(k) != got.get(k))
    assert not changed, (f"golden case {name!r}: arrays changed bit for bit: {changed} (an intentional physics "
                         f"change regenerates them: see this file's docstring)")


def _numba_installed() -> bool:
    from tofcore import compiled

    return compiled.numba_version() is not None


COMPILED_AGREEMENT = 0.995
"""Share of each array's entries the compiled tracer must give to 1e-9 relative (tests/tofcore/test_compiled.py
states why: the compiler's libm may round a transcendental function's last bit differently, which, rarely,
moves a path across a triangle edge or a lobe threshold); the arrays' totals agree to 1e-6."""


@pytest.mark.skipif(not _numba_installed(), reason="numba is not installed")
@pytest.mark.parametrize("name", sorted(CASES))
def test_the_compiled_tracer_gives_each_golden_frame(name, monkeypatch):
    """The same cases on the tracer users get by default (compiled with numba): the NumPy frame of this
    machine — whose hashes the test above guards on the machine they were recorded on — at the stated
    tolerance, on any machine."""
    monkeypatch.setenv("TOFCORE_TRACER", "numpy")
    reference = run_case(name)
    monkeypatch.setenv("TOFCORE_TRACER", "compiled")  # an error, not a fall-back, where it cannot run the case
    fast = run_case(name)
    assert reference.keys() == fast.keys()
    for key, x in reference.items():
        y = fast[key]
        assert x.shape == y.shape and x.dtype == y.dtype, key
        if x.dtype == bool or np.issubdtype(x.dtype, np.integer):
            assert (x == y).mean() >= COMPILED_AGREEMENT, key
            continue
        scale = np.nanmax(np.abs(x), initial=0.0)
        close = np.isclose(x, y, rtol=1e-9, atol=1e-12 * max(scale, 1e-300)) | (np.isnan(x) & np.isnan(y))
        assert close.mean() >= COMPILED_AGREEMENT, f"{key}: {100 * (1 - close.mean()):.2f} % of the values differ"
        np.testing.assert_allclose(np.nansum(y), np.nansum(x), rtol=1e-6, atol=1e-9 * max(scale, 1e-300), err_msg=key)


def test_workers_and_chunks_do_not_change_the_frame():
    twin, overrides = PARALLEL_TWIN
    assert hashes(twin, **overrides) == hashes(twin)


def _regenerate(keep_others: bool) -> None:
    """Record this CPU's hashes; drop the other CPUs' sets unless ``keep_others`` (``--add``)."""
    by_cpu = _all_golden() if GOLDEN_FILE.exists() else {}
    old = by_cpu.get(signature(), {})
    table = {name: hashes(name) for name in sorted(CASES)}
    for name, new in table.items():
        changed = sorted(k for k in new if old.get(name, {}).get(k) != new[k])
        print(f"{name}: {'changed ' + ', '.join(changed) if changed else 'unchanged'}")
    by_cpu = {**(by_cpu if keep_others else {}), signature(): table}
    GOLDEN_FILE.write_text(json.dumps({BY_CPU: by_cpu}, indent=1, sort_keys=True) + "\n", encoding="utf-8")
    print(f"wrote {GOLDEN_FILE}: {sorted(by_cpu)}")


def _show() -> None:
    golden = _golden()
    for name in sorted(CASES):
        got = hashes(name)
        changed = sorted(k for k in got if golden.get(name, {}).get(k) != got[k])
        print(f"{name}: {'DIFFERS ' + ', '.join(changed) if changed else 'ok'}")


if __name__ == "__main__":
    os.environ["TOFCORE_TRACER"] = "numpy"  # the reference's hashes, as under pytest (tests/conftest.py)
    if "--regenerate" in sys.argv[1:] or "--add" in sys.argv[1:]:
        _regenerate(keep_others="--add" in sys.argv[1:])
    elif "--show" in sys.argv[1:]:
        _show()
    else:
        sys.exit("usage: test_golden.py --regenerate | --add | --show   (pytest runs the checks)")
