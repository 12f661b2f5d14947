"""The compiled tracer (tofcore.compiled) against the NumPy reference: same frame, same rays, honest fall-backs.

Tolerance. The compiled kernels perform the reference's IEEE operations in the reference's order; what
may differ is the last bit of a transcendental function (the compiler's libm against NumPy's vectorised
loops), and such a bit can, rarely, move a path across a triangle edge or a lobe threshold, after which
the two paths differ entirely. So each sum (per pixel, bucket and channel) must agree to 1e-9 relative
on at least 99.5 % of the entries, and the frame totals to 1e-6. On the development machine (NumPy
1.26, numba 0.68, glibc's libm) every sum measured equal bit for bit, and the ray counts too.

Skipped where numba is not installed; the fall-back tests at the end run everywhere.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

import tofcore
from tofcore import compiled
from tofcore.compiled import tracer as compiled_tracer
from tofcore.limits import usable_cpus
from tofcore.scene.camera import Camera
from tofcore.errors import ConfigError
from tofcore.scene.material import Material, Texture
from tofcore.sensor.modulation import harmonic, phasor_correlations, sine_correlation, tabulate
from tofcore import trace, trace_progressive

needs_numba = pytest.mark.skipif(compiled.numba_version() is None, reason="numba is not installed")

SUMS = ("signal_sum", "correlation_sum", "replicate_sum", "ambient_sum", "transient_sum")
RAYS = ("camera_rays", "bounce_rays", "shadow_rays", "light_rays", "skipped_shadow_rays")


def assert_same_frame(a, b):
    """The tolerance of the module docstring, on every accumulator and the ray counts."""
    for name in SUMS:
        x, y = getattr(a, name), getattr(b, name)
        if x is None:
            assert y is None, name
            continue
        close = np.isclose(x, y, rtol=1e-9, atol=1e-12 * max(np.abs(x).max(initial=0.0), 1e-300))
        assert close.mean() >= 0.995, f"{name}: {100 * (1 - close.mean()):.2f} % of the sums differ"
        np.testing.assert_allclose(y.sum(axis=-1), x.sum(axis=-1), rtol=1e-6, atol=1e-9 * np.abs(x).max(),
                                   err_msg=name)
    # The ground truth's rays involve no transcendental function: the compiled first hits are the reference's bit
    # for bit (the compiled tracer traces them with its own kernels where they are loaded).
    for name in ("distance_m", "position_m", "normal", "material_id", "object_id", "direction"):
        np.testing.assert_array_equal(getattr(b.first_hit, name), getattr(a.first_hit, name), err_msg=name)
    for key in RAYS:
        n_a, n_b = getattr(a.stats, key), getattr(b.stats, key)
        assert abs(n_a - n_b) <= 1e-3 * max(n_a, 1), (key, n_a, n_b)
    assert (a.sample_count == b.sample_count).all()


def both(monkeypatch, *args, **kwargs):
    """(NumPy transport, compiled transport) of the same trace."""
    monkeypatch.setenv(compiled.TRACER_ENV, "numpy")
    reference = trace(*args, **kwargs)
    monkeypatch.setenv(compiled.TRACER_ENV, "compiled")
    fast = trace(*args, **kwargs)
    assert reference.stats.tracer == "numpy" and fast.stats.tracer == "compiled"
    assert fast.stats.parallel == f"numba threads: {compiled.thread_count(kwargs.get('workers', usable_cpus()))}"
    return reference, fast


def small_preset(name: str, width: int = 40):
    """A preset's sensor at ``width`` pixels, distortion and all (as tests/tofcore/test_render_error.py)."""
    sensor = tofcore.load_preset(name)
    cam = sensor.camera
    s = width / cam.width
    h = round(cam.height * s)
    cam = dataclasses.replace(cam, width=width, height=h, fx=cam.fx * s, fy=cam.fy * h / cam.height,
                              cx=cam.cx * s, cy=cam.cy * h / cam.height)
    return sensor.replace(camera=cam, **{"noise.model": "none"})


def odd_materials_room() -> tofcore.Scene:
    """The demo room with a mirror, a half-metal, an η = 1 dielectric, clear coats (rough over a rough base, a
    mirror coat over a mirror) and interpolated vertex normals: delta lobes, the blended Fresnel, the coat's
    lobes, shading normals apart from the geometric ones."""
    room = tofcore.demo_scene("room", detail=2)
    rng = np.random.default_rng(3)
    normals = np.zeros_like(room.vertices, dtype=np.float64)
    normals[room.triangles.ravel()] = np.repeat(room.face_normals, 3, axis=0)
    normals += 0.15 * rng.normal(size=normals.shape)
    materials = (Material(name="mirror", reflectance=0.2, roughness=0.0),
                 Material(name="half metal", metallic=0.5, ior=1.4, extinction=3.0, roughness=0.3),
                 Material(name="no fresnel", reflectance=0.9, roughness=0.8, ior=1.0),
                 Material(name="metal", metallic=1.0, ior=1.35, extinction=9.6, roughness=0.15),
                 Material(name="lacquer", reflectance=0.6, roughness=0.5, coat=1.0, coat_roughness=0.1),
                 Material(name="varnished mirror", reflectance=0.3, roughness=0.0, coat=0.5, coat_roughness=0.0))
    ids = room.material_ids % len(materials)
    return tofcore.Scene.from_arrays(room.vertices, room.triangles, ids, materials, normals=normals,
                                     name="odd room")


def room_trace_args(**changes):
    scene = tofcore.demo_scene("room", detail=3)
    kwargs = dict(world_from_sensor=tofcore.suggested_pose(scene), correlations=phasor_correlations([80e6]),
                  spp=4, max_depth=5, seed=3, workers=2)
    kwargs.update(changes)
    return (scene, Camera.from_fov(48, 40, 70.6, 60.0), [tofcore.LED(position_m=(0.025, 0.0, 0.0))]), kwargs


@needs_numba
@pytest.mark.parametrize("changes", [
    {},                                                   # the bench frame's setting, small
    {"light_paths": False, "sampler": "independent"},
    {"max_depth": 1, "seed": 0},
    {"max_depth": 2, "spp": 5},                           # 5 samples: replicates of unequal size
], ids=["default", "no-light-paths-independent", "direct-only", "depth-2"])
def test_room_frame_equals_numpy(monkeypatch, changes):
    args, kwargs = room_trace_args(**changes)
    assert_same_frame(*both(monkeypatch, *args, **kwargs))


@needs_numba
def test_the_compiled_tracer_traces_the_ground_truth_with_its_kernels(monkeypatch):
    """Once the kernels are loaded the first hits are theirs (the reference's NumPy traversal is not called);
    test_room_frame_equals_numpy checks they equal the reference's."""
    from tofcore.tracer import stages

    args, kwargs = room_trace_args(spp=1)
    monkeypatch.setenv(compiled.TRACER_ENV, "compiled")
    trace(*args, **kwargs)  # the kernels compiled or loaded

    def not_here(*_):
        raise AssertionError("the NumPy first hits were traced")

    monkeypatch.setattr(stages, "first_hit", not_here)
    assert np.isfinite(trace(*args, **kwargs).first_hit.distance_m).any()


@needs_numba
def test_mirrors_metals_and_shading_normals_equal_numpy(monkeypatch):
    scene = tofcore.demo_scene("room", detail=2)
    odd = odd_materials_room()
    leds = [tofcore.LED(position_m=(0.0, 0.0, 0.0)),  # at the pinhole: first-hit shadow rays skipped
            tofcore.LED(position_m=(-0.03, 0.01, 0.0), intensity_w_sr=2.0, kind="lambertian")]
    reference, fast = both(monkeypatch, odd, Camera.from_fov(40, 30, 70.0, 56.0), leds,
                           world_from_sensor=tofcore.suggested_pose(scene),
                           correlations=phasor_correlations([20e6, 100e6]), spp=4, max_depth=4, seed=1)
    assert reference.stats.skipped_shadow_rays > 0
    assert_same_frame(reference, fast)


@needs_numba
def test_constant_ambient_light_equals_numpy(monkeypatch):
    """Rays that leave the open corner see a constant ambient radiance: β · L_amb into the ambient sums and
    the replicates' ambient channel, as the NumPy tracer adds them."""
    scene = tofcore.demo_scene("corner", detail=2)
    reference, fast = both(monkeypatch, scene, Camera.from_fov(24, 18, 90.0), [tofcore.LED(position_m=(0.02, 0, 0))],
                           world_from_sensor=tofcore.suggested_pose(scene), correlations=phasor_correlations([80e6]),
                           spp=3, max_depth=3, seed=4, ambient=tofcore.Ambient(radiance_w_m2_sr=0.25))
    assert (reference.ambient_sum > 0).mean() > 0.2  # rays do leave the scene
    assert_same_frame(reference, fast)


@needs_numba
def test_thin_lens_and_sine_bank_equal_numpy(monkeypatch):
    sensor = small_preset("o3d303", 32)
    camera = dataclasses.replace(sensor.camera, aperture_radius_m=0.004, focus_distance_m=1.5)
    sine = dataclasses.replace(sensor.modulation, kind="cw_sine", duty_cycle=0.5)
    scene = tofcore.demo_scene("box_on_wall", detail=2)
    assert_same_frame(*both(monkeypatch, scene, camera, sensor.leds,
                            world_from_sensor=tofcore.suggested_pose(scene),
                            correlations=sine.correlation_bank(), spp=3, max_depth=3, seed=2))


@needs_numba
@pytest.mark.parametrize("preset", ["kinect_v2", "xtion2"])
def test_rendered_depth_equals_numpy(monkeypatch, preset):
    """Whole renders (distorted Kinect camera with its square-wave bank; the pulsed Xtion), decoded depth."""
    sensor = small_preset(preset)
    scene = tofcore.demo_scene("room", detail=2)
    frames = {}
    for tracer in ("numpy", "compiled"):
        monkeypatch.setenv(compiled.TRACER_ENV, tracer)
        frames[tracer] = tofcore.render(scene, sensor, spp=4, seed=5, max_depth=3)
        assert frames[tracer].stats["transport"]["tracer"] == tracer
    a, b = frames["numpy"], frames["compiled"]
    same = (np.isclose(a.depth, b.depth, rtol=1e-9, atol=1e-9) | (np.isnan(a.depth) & np.isnan(b.depth)))
    assert same.mean() >= 0.995
    assert (a.valid == b.valid).mean() >= 0.995
    np.testing.assert_allclose(b.raw, a.raw, rtol=1e-6, atol=1e-9 * np.abs(a.raw).max())


@needs_numba
def test_adaptive_allocation_and_thread_count_do_not_change_the_frame(monkeypatch):
    """Uneven samples per pixel (adaptive sampling) and 1 or 2 threads: each pixel is one thread's sum."""
    args, kwargs = room_trace_args(spp=6)
    counts = np.random.default_rng(0).integers(0, 4, size=48 * 40)

    def run(tracer: str, workers: int):
        monkeypatch.setenv(compiled.TRACER_ENV, tracer)
        return list(trace_progressive(*args, **{**kwargs, "workers": workers},
                                      allocate=lambda transport, n: counts))[-1]

    reference = run("numpy", 2)
    one, two = run("compiled", 1), run("compiled", 2)
    for name in SUMS:
        assert np.array_equal(getattr(one, name), getattr(two, name)), name
    assert_same_frame(reference, two)


@needs_numba
def test_kernels_match_their_numpy_twins():
    """Sobol' samples and hashes bit for bit; BVH closest and any hits as BVH.intersect/occluded."""
    import numba

    from tofcore.compiled import kernels, setup
    from tofcore import rng
    from tofcore.tracer import qmc
    from tofcore.tracer.surface import MaterialTable

    key = rng.seed_key(7)
    pixel = np.arange(500, dtype=np.int64) * 37
    sample = np.arange(500, dtype=np.int64) % 23

    @numba.njit
    def samples(key, pixel, sample, dim, independent):
        out = np.empty((len(pixel), 3))
        for i in range(len(pixel)):
            out[i, 0], out[i, 1] = kernels.sample_2d(key, pixel[i], sample[i], dim, independent)
            out[i, 2] = kernels.sample_1d(key, pixel[i], sample[i], dim, independent)
        return out

    for sampler in qmc.SAMPLERS:
        got = samples(key, pixel, sample, 5, sampler == "independent")
        u, v = qmc.sample_2d(key, pixel, sample, 5, sampler)
        assert np.array_equal(got[:, 0], u) and np.array_equal(got[:, 1], v)
        assert np.array_equal(got[:, 2], qmc.sample_1d(key, pixel, sample, 5, sampler))

    scene = tofcore.demo_scene("room", detail=4)
    geo = setup.scene_arrays(scene, MaterialTable(scene))
    r = np.random.default_rng(1)
    lo, hi = scene.bounds
    o = (lo + (hi - lo) * (0.1 + 0.8 * r.random((3000, 3)))).astype(np.float32)
    d = r.normal(size=(3000, 3))
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    t_max = (r.random(3000) * 3).astype(np.float32)

    @numba.njit
    def hits(geo, o, d, t_max, any_hit):
        prim = np.empty(len(o), np.int64)
        t = np.empty(len(o), np.float32)
        work = (np.zeros(kernels.N_COUNTERS, np.int64), np.empty(kernels.STACK_SIZE, np.int64),
                np.empty(kernels.STACK_T_SIZE, np.float32), np.zeros(1))
        for i in range(len(o)):
            h = kernels.intersect(geo, (o[i, 0], o[i, 1], o[i, 2]), (d[i, 0], d[i, 1], d[i, 2]), t_max[i], -1,
                                  any_hit, work)
            t[i], prim[i] = h[0], h[1]
        return t, prim

    t, prim = hits(geo, o, d, np.full(3000, np.inf, np.float32), False)
    ref = scene.bvh.intersect(o, d, workers=1)
    assert np.array_equal(prim, ref.prim) and np.array_equal(t[prim >= 0], ref.t[ref.prim >= 0])
    _, blocked = hits(geo, o, d, t_max, True)
    assert np.array_equal(blocked >= 0, scene.bvh.occluded(o, d, t_max, workers=1))


# ------------------------------------------------------------------ textures, sky maps, histograms, waveforms
@needs_numba
def test_textured_room_under_a_sky_map_with_a_transient_histogram_equals_numpy(monkeypatch):
    """The textured demo room (reflectance, roughness, metallic textures and a normal map, bilinear with
    repeat) open to its sky map, with a transient histogram: every sum and every bin at the module's
    tolerance. The histogram's addends are the reference's, added in sample order rather than in the
    reference's per-chunk order: a few ulps apart, inside the tolerance."""
    scene = tofcore.demo_scene("textured_room", detail=2)
    reference, fast = both(monkeypatch, scene, Camera.from_fov(48, 40, 70.6, 60.0),
                           [tofcore.LED(position_m=(0.025, 0.0, 0.0))], world_from_sensor=tofcore.suggested_pose(scene),
                           correlations=phasor_correlations([80e6]), spp=3, max_depth=4, seed=3, workers=2,
                           ambient=tofcore.demo_ambient("textured_room"), transient_bin_m=0.05, transient_max_m=12.0)
    assert (reference.ambient_sum > 0).mean() > 0.5  # the sky is seen through the open ceiling
    assert reference.transient_sum.sum() > 0
    assert_same_frame(reference, fast)


@needs_numba
def test_custom_waveforms_given_as_data_equal_numpy(monkeypatch):
    """A harmonic series (the Kinect's third and fifth harmonics) and a tabulated waveform trace compiled
    and give the reference's sums."""
    args, kwargs = room_trace_args(spp=2, max_depth=3)
    square_ish = harmonic(80e6, (0.5, 0.4, 0.0, -0.05, 0.0, 0.02), (0.1, 0.0, 0.03, 0.0, -0.01))
    table = tabulate(functools.partial(sine_correlation, f_hz=16e6, offset_fraction=0.25), 1 / 16e6, samples=512)
    assert_same_frame(*both(monkeypatch, *args, **{**kwargs, "correlations": [square_ish, table]}))


def test_tabulated_waveform_is_within_its_interpolation_bound():
    """tabulate(g, T, M): |g − table| ≤ h² max|g''| / 8, h = T / M; for the sine ½ + cos(2πfτ)/π,
    max|g''| = 4π² f² / π."""
    f = 80e6
    g = functools.partial(sine_correlation, f_hz=f, offset_fraction=0.0)
    tau = np.random.default_rng(2).uniform(0, 5 / f, 10_000)
    for m in (64, 1024):
        bound = (1 / (f * m)) ** 2 * 4 * np.pi * f**2 / 8
        error = np.abs(tabulate(g, 1 / f, samples=m)(tau) - g(tau)).max()
        assert bound / 4 < error <= bound, (m, error, bound)


# ------------------------------------------------------------------ fall-backs (run with or without numba)
@needs_numba
def test_only_python_code_as_a_correlation_falls_back_to_numpy_and_says_why(monkeypatch):
    """Every feature compiles; a correlation channel given as a Python function runs on NumPy, and the
    reason says how to give it as data."""
    monkeypatch.setenv(compiled.TRACER_ENV, "auto")
    args, kwargs = room_trace_args(spp=1, max_depth=2)
    t = trace(*args, **{**kwargs, "correlations": [lambda tau: np.cos(tau)]})
    assert t.stats.tracer == "numpy" and t.stats.as_dict()["tracer"] == "numpy"
    assert "correlation channel 0 (<lambda>) is Python code" in t.stats.tracer_reason
    assert "modulation.harmonic or .tabulate" in t.stats.tracer_reason
    scene = args[0]
    textured = tofcore.Scene.from_arrays(
        scene.vertices, scene.triangles, scene.material_ids,
        [Material(name="tex", reflectance_texture=Texture(np.full((2, 2), 0.5)))] * len(scene.materials),
        uvs=np.zeros((len(scene.vertices), 2)))
    for changes in ({"ambient": tofcore.Ambient(environment=np.full((4, 8), 0.2))},
                    {"transient_bin_m": 0.1, "transient_max_m": 20.0}, {}):
        t = trace(textured if not changes else scene, *args[1:], **{**kwargs, **changes})
        assert (t.stats.tracer, t.stats.tracer_reason) == ("compiled", ""), changes


def test_numpy_forced_or_numba_missing(monkeypatch):
    args, kwargs = room_trace_args(spp=1, max_depth=1)
    monkeypatch.setenv(compiled.TRACER_ENV, "numpy")
    t = trace(*args, **kwargs)
    assert (t.stats.tracer, t.stats.tracer_reason) == ("numpy", "TOFCORE_TRACER=numpy")
    monkeypatch.setenv(compiled.TRACER_ENV, "auto")
    monkeypatch.setattr(compiled_tracer, "numba_version", lambda: None)  # where the choice asks
    t = trace(*args, **kwargs)
    assert t.stats.tracer == "numpy" and "numba is not installed" in t.stats.tracer_reason


def test_forcing_the_compiled_tracer_where_it_cannot_run_is_an_error(monkeypatch):
    args, kwargs = room_trace_args(spp=1, max_depth=1)
    monkeypatch.setenv(compiled.TRACER_ENV, "compiled")
    with pytest.raises(ConfigError, match="is Python code the compiled tracer cannot run"):
        trace(*args, **{**kwargs, "correlations": [lambda tau: np.cos(tau)]})
    monkeypatch.setenv(compiled.TRACER_ENV, "fast")
    with pytest.raises(ConfigError, match=r"TOFCORE_TRACER must be one of \['auto', 'numpy', 'compiled'\], got 'fast'"):
        trace(*args, **kwargs)


SIMULATED_GPU_PASS = """
import numpy as np, tofcore
from tofcore import backend
from tofcore.compiled import cuda, setup
from tofcore.scene.camera import Camera
from tofcore.sensor.modulation import phasor_correlations
from tofcore.tracer.setup import TraceSettings, make_setup
from tofcore.tracer import qmc
def same(a, b, what):  # Python's libm against NumPy's SIMD loops: the last bits of cos, exp, log may differ
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15 * np.abs(b).max(), err_msg=what)
scene, cam = tofcore.demo_scene("room", detail=4), Camera.from_fov(6, 5, 60.0)
leds = [tofcore.LED(position_m=(0.03, 0, 0)), tofcore.LED(position_m=(-0.03, 0, 0))]
shared = dict(world_from_sensor=tofcore.suggested_pose(scene), correlations=phasor_correlations([80e6]),
              max_depth=4, seed=3)
counts = np.arange(30) % 4
ref = tofcore.trace(scene, cam, leds, device="cpu", spp=3, progressive=False, allocate=lambda t, n: counts,
                    **shared)
packed = setup.pack(make_setup(scene, cam, leds, TraceSettings(**shared), backend.select_device("cpu")))
for groups_of in (10 ** 6, 7):  # one group, and groups of at most 7 paths (several sample indices each)
    cuda.MAX_GROUP_PATHS = groups_of
    out = cuda.Sums(np.zeros((4, 30)), np.zeros((4, 2, 30)), np.zeros((qmc.REPLICATES, 4, 30)), np.zeros(30))
    n = cuda.trace_pass(cuda.upload(packed, scene.bvh), out, np.zeros(30, np.int64), counts, threads_per_block=32)
    for name in ("signal_sum", "correlation_sum", "replicate_sum"):
        same(getattr(out, name), getattr(ref, name), f"{groups_of} {name}")
    assert n[1:4].tolist() == [ref.stats.bounce_rays, ref.stats.shadow_rays, ref.stats.light_rays], n
    assert n[0] == counts.sum() and ref.stats.camera_rays == counts.sum() + 30  # + the first-hit rays
# a finished trace's device scene serves the next trace of its layout (another seed: new key, same arrays),
# and traces it as a fresh one does
shared["seed"] = 4
packed = setup.pack(make_setup(scene, cam, leds, TraceSettings(**shared), backend.select_device("cpu")))
sums = []
for turn in range(2):
    device_scene = cuda.upload(packed, scene.bvh)
    out = cuda.Sums(np.zeros((4, 30)), np.zeros((4, 2, 30)), np.zeros((qmc.REPLICATES, 4, 30)), np.zeros(30))
    cuda.trace_pass(device_scene, out, np.zeros(30, np.int64), counts, threads_per_block=32)
    sums.append(out)
    if turn == 0:
        fresh = device_scene
        cuda.release(fresh)
        moved = np.array(shared["world_from_sensor"], dtype=float)
        moved[0, 3] += 0.1  # other contents first: another seed and camera position
        cuda.upload(setup.pack(make_setup(scene, cam, leds, TraceSettings(**dict(shared, seed=9, world_from_sensor=moved)),
                                          backend.select_device("cpu"))), scene.bvh)
        cuda.release(fresh)
assert device_scene is fresh
for name in ("signal_sum", "correlation_sum", "replicate_sum"):
    np.testing.assert_array_equal(getattr(sums[1], name), getattr(sums[0], name), err_msg=f"reused {name}")
# constant ambient light: rays that leave the open corner see β · L_amb
corner, camera = tofcore.demo_scene("corner", detail=2), Camera.from_fov(5, 4, 90.0)
lit = dict(world_from_sensor=tofcore.suggested_pose(corner), correlations=phasor_correlations([80e6]), max_depth=3,
           seed=5, ambient=tofcore.Ambient(radiance_w_m2_sr=0.25))
ref = tofcore.trace(corner, camera, leds[:1], device="cpu", spp=2, progressive=False, **lit)
assert (ref.ambient_sum > 0).any()
packed = setup.pack(make_setup(corner, camera, leds[:1], TraceSettings(**lit), backend.select_device("cpu")))
out = cuda.Sums(np.zeros((3, 20)), np.zeros((3, 2, 20)), np.zeros((qmc.REPLICATES, 4, 20)), np.zeros(20))
cuda.trace_pass(cuda.upload(packed, corner.bvh), out, np.zeros(20, np.int64), np.full(20, 2, np.int64),
                threads_per_block=32)
for name in ("signal_sum", "correlation_sum", "replicate_sum", "ambient_sum"):
    same(getattr(out, name), getattr(ref, name), f"ambient {name}")
# the textured room under its sky map, a harmonic channel and a transient histogram (its addends in another
# order than the reference's: a few ulps apart)
from tofcore.sensor.modulation import harmonic
room = tofcore.demo_scene("textured_room", detail=2)
lit = dict(world_from_sensor=tofcore.suggested_pose(room), max_depth=3, seed=6,
           correlations=phasor_correlations([80e6]) + [harmonic(16e6, (0.5, 0.3, 0.05), (0.1, 0.02))],
           ambient=tofcore.demo_ambient("textured_room"), transient_bin_m=0.1, transient_max_m=8.0)
ref = tofcore.trace(room, camera, leds, device="cpu", spp=2, progressive=False, **lit)
assert (ref.ambient_sum > 0).any() and ref.transient_sum.sum() > 0
packed = setup.pack(make_setup(room, camera, leds, TraceSettings(**lit), backend.select_device("cpu")))
out = cuda.Sums(np.zeros((3, 20)), np.zeros((3, 3, 20)), np.zeros((qmc.REPLICATES, 5, 20)), np.zeros(20))
out.transient_sum = np.zeros((20, 80))
cuda.MAX_GROUP_PATHS = 7
cuda.trace_pass(cuda.upload(packed, room.bvh), out, np.zeros(20, np.int64), np.full(20, 2, np.int64),
                threads_per_block=32)
for name in ("signal_sum", "correlation_sum", "replicate_sum", "ambient_sum", "transient_sum"):
    same(getattr(out, name), getattr(ref, name), f"textured {name}")
# the ground truth's kernels: the reference's record field by field (a room seen through its open side:
# misses too), twice on the kept device scene with the camera moved between
from tofcore.tracer import stages
from tofcore.tracer.transport import TraceStats
pose = np.array(tofcore.suggested_pose(room), dtype=float)
for turn in range(2):
    ts = make_setup(room, Camera.from_fov(7, 5, 150.0), leds, TraceSettings(**dict(lit, world_from_sensor=pose)),
                    backend.select_device("cpu"))
    device_scene, stats = cuda.upload(setup.pack(ts), room.bvh), TraceStats()
    got, want = cuda.first_hit(device_scene, ts, stats, threads_per_block=32), stages.first_hit(ts, TraceStats())
    assert stats.camera_rays == 35 and 0 < (want.material_id >= 0).sum() < 35 or turn, want.material_id
    for name in ("distance_m", "position_m", "normal", "material_id", "object_id", "direction"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), f"first hit {turn} {name}"
    cuda.release(device_scene)
    pose[:3, 3] += (0.3, 0.2, 0.0)
print("ok")
"""


@needs_numba
def test_cuda_build_of_the_kernels_traces_the_numpy_frame_in_the_simulator(tmp_path):
    """The CUDA build of kernels.py — the wavefront's stages, groups of several sample indices, uneven sample
    counts, two LEDs, a reused device scene, constant ambient light, textures, a sky map, a harmonic channel,
    a transient histogram — run by numba's CUDA simulator on the CPU gives the NumPy tracer's sums with the
    same rays: bit for bit where NumPy's transcendental functions round as Python's libm does (AMD EPYC),
    within 1e-12 relative elsewhere (an Intel Xeon: NumPy's SIMD cos/exp/log differ in the last bit). The
    driver's indexing and sum order are checked in CI; tests/tofcore/test_gpu.py checks the device."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1", TOFCORE_TRACER="numpy", NUMBA_CACHE_DIR=str(tmp_path))
    run = subprocess.run([sys.executable, "-W", "ignore", "-c", SIMULATED_GPU_PASS], env=env, capture_output=True,
                         text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.startswith("ok")


@needs_numba
@pytest.mark.parametrize("counts", [np.full(50, 3), np.zeros(7, np.int64), np.zeros(0, np.int64),
                                    np.random.default_rng(1).integers(0, 9, 1000),
                                    np.r_[np.random.default_rng(2).integers(0, 3, 100), 70_000]],
                         ids=["uniform", "zeros", "empty", "adaptive", "past 16 bits"])
def test_the_wavefronts_launch_plan_orders_pixels_by_decreasing_count_stably(counts):
    """cuda.launch_plan's order (a uniform pass as it is, 16-bit keys where the counts allow) is the stable
    argsort of −counts, and active[s] counts the pixels with more than s samples."""
    from tofcore.compiled import cuda

    order, active = cuda.launch_plan(counts)
    np.testing.assert_array_equal(order, np.argsort(-np.asarray(counts, np.int64), kind="stable"))
    np.testing.assert_array_equal(active, [(counts > s).sum() for s in range(int(counts.max(initial=0)))])


@needs_numba
def test_the_kernels_material_record_is_read_by_the_tables_names():
    """kernels.surface_params builds the record in the material table's order, so params[layout.<NAME>] is
    the parameter of that name (tofcore.scene.material.PARAMETERS)."""
    import numba

    from tofcore.compiled import kernels, layout

    values = tuple(float(i + 1) for i in range(len(layout.MATERIAL_COLUMNS)))
    record = numba.njit(lambda v: kernels.surface_params(*v))(values)  # kernel functions have no Python wrapper
    for name, value in zip(layout.MATERIAL_COLUMNS, values):
        assert record[getattr(layout, name.upper())] == value, name


@needs_numba
def test_the_wavefronts_light_table_round_trips_a_light_vertex():
    """store_light / load_light (the GPU wavefront's light table) compiled for the CPU: the same tuple back,
    bit for bit (numba types the heterogeneous tuple as the CUDA build does)."""
    import numba

    from tofcore.compiled import kernels

    surf = ((1.0, 2.0, 3.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.6, 0.8),
            (0.5, 0.2, 0.0, 1.5, 0.0, 0.4, 0.1))
    light = (True, surf, (0.0, -0.6, -0.8), 2.5, 0.125, 3.0e-2, 1e-6)
    table = np.zeros((kernels.LIGHT_COLUMNS, 3))
    numba.njit(lambda t, v: kernels.store_light(t, 1, v))(table, light)  # kernel functions have no Python wrapper
    assert numba.njit(lambda t: kernels.load_light(t, 1))(table) == light
    assert not table[:, [0, 2]].any()  # the other paths' columns untouched


@needs_numba
def test_sobol_bit_by_bit_equals_the_lookup_tables():
    """The GPU build's Sobol' dimension 2 (a loop over the index's bits: constant-memory tables serialise a
    warp) is the CPU build's table lookup, number for number: every single-bit index, and 20,000 random ones."""
    import numba

    from tofcore.compiled import kernels

    @numba.njit
    def both(indices):
        out = np.empty((len(indices), 2), np.uint64)
        for k in range(len(indices)):
            out[k, 0], out[k, 1] = kernels.sobol_dim1_bits(indices[k]), kernels.sobol_dim1_lookup(indices[k])
        return out

    rng = np.random.default_rng(5)
    indices = np.concatenate([np.uint64(1) << np.arange(32, dtype=np.uint64), [0, 0xFFFFFFFF],
                              rng.integers(0, 2 ** 32, 20_000, dtype=np.uint64)]).astype(np.uint64)
    bits, lookup = both(indices).T
    differ = np.flatnonzero(bits != lookup)
    assert differ.size == 0, [hex(int(i)) for i in indices[differ[:5]]]


@needs_numba
def test_a_kernel_function_called_from_python_says_it_is_for_jitted_code():
    """The scalar kernel functions are built without numba's Python wrapper (a third of their first compile): a
    call from Python raises a TypeError naming the function, and never reaches the missing wrapper (which would
    crash the interpreter)."""
    import numba

    from tofcore.compiled import kernels

    with pytest.raises(TypeError, match="dot is compiled for calls from jitted code only"):
        kernels.dot((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    assert numba.njit(lambda: kernels.dot((1.0, 2.0, 3.0), (4.0, 5.0, 6.0)))() == 32.0
