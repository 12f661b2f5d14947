"""The compiled render-error estimate (tofcore.compiled.depth_error) against the NumPy one (tofcore.render).

Both compute σ of the output depth and the unwrap flips from the same replicate sums; the compiled one takes
its DFT sums in order where NumPy's go through BLAS, and rebuilds the flips' filtered phasors from the DFT
bin where NumPy goes through A cos φ, A sin φ: the two agree to rounding. Tolerance: σ to 1e-9 relative (the
differences are a few ulp, ~1e-14, amplified at most by the 1/|Z|² of weak pixels); the flips exactly, as
a spread exactly at the threshold does not occur in these frames (if one did, one pixel could differ).
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import subprocess
import sys

import numpy as np
import pytest

import tofcore

render_module = importlib.import_module("tofcore.render")  # the module (tofcore.render is the function)
numba = pytest.importorskip("numba")


def small_sensor(preset: str, width: int = 48, **overrides):
    sensor = tofcore.load_preset(preset)
    return sensor.scaled(width / sensor.camera.width).replace(**overrides)


def transport_of(sensor, scene_name: str = "room", spp: int = 8):
    scene = tofcore.demo_scene(scene_name)
    return tofcore.trace(scene, sensor.camera, sensor.leds, world_from_sensor=tofcore.suggested_pose(scene, sensor),
                         correlations=sensor.modulation.correlation_bank(), spp=spp, max_depth=3, seed=3,
                         ambient=tofcore.Ambient(radiance_w_m2_sr=0.05))


SENSORS = {
    "kinect_v2": ("kinect_v2", {}),                                     # 3 frequencies, bilateral, f/Σf output
    "kinect_v2_unfiltered": ("kinect_v2", {"processing.phasor_filter": "none",
                                           "processing.unwrap_weights": "inverse_variance"}),
    "o3d303": ("o3d303", {}),                                           # one 30 MHz frequency, 4 steps, radial
    "two_sine_frequencies": ("o3d303", {"modulation.kind": "cw_sine", "modulation.frequencies_hz": [20e6, 50e6],
                                        "modulation.phase_steps": [3, 5], "modulation.exposure_s": [5e-4, 5e-4]}),
}


@pytest.mark.parametrize("name", sorted(SENSORS))
def test_compiled_estimate_equals_the_numpy_estimate(name):
    from tofcore.compiled import depth_error

    preset, overrides = SENSORS[name]
    sensor = small_sensor(preset, **overrides)
    assert depth_error.unsupported(sensor) == ""
    transport = transport_of(sensor)
    n_raw = len(sensor.modulation.correlation_bank())
    sigma, flips = render_module.render_error(transport, sensor, n_raw)  # a CPU transport: the array program
    fast_sigma, fast_flips = depth_error.render_error(transport, sensor, n_raw, render_module.flip_threshold_m(sensor))
    assert fast_sigma.shape == sigma.shape and fast_flips.dtype == bool
    np.testing.assert_array_equal(np.isnan(fast_sigma), np.isnan(sigma))
    seen = ~np.isnan(sigma)
    assert seen.mean() > 0.5
    np.testing.assert_allclose(fast_sigma[seen], sigma[seen], rtol=1e-9, atol=0)
    np.testing.assert_array_equal(fast_flips, flips)


def test_compiled_estimate_sees_the_flips_of_a_noisy_pass():
    """At 4 spp the Kinect v2's replicates disagree on the wrap at a share of the pixels (the demo frame: 2.5 %
    at 16 spp): both estimates flag the same pixels, so the test above is not won by an all-False map."""
    from tofcore.compiled import depth_error

    sensor = small_sensor("kinect_v2")
    transport = transport_of(sensor, spp=4)
    n_raw = len(sensor.modulation.correlation_bank())
    _, flips = render_module.render_error(transport, sensor, n_raw)
    _, fast_flips = depth_error.render_error(transport, sensor, n_raw, render_module.flip_threshold_m(sensor))
    assert flips.sum() >= 5
    np.testing.assert_array_equal(fast_flips, flips)


def test_a_pulsed_sensor_keeps_the_array_program():
    from tofcore.compiled import depth_error

    assert "pulsed" in depth_error.unsupported(tofcore.load_preset("xtion2"))


SIMULATED_GPU_ESTIMATE = r"""
import numpy as np, tofcore, importlib, sys
sys.path.insert(0, sys.argv[1])
from test_depth_error import small_sensor, transport_of
from tofcore.compiled import depth_error
render_module = importlib.import_module("tofcore.render")
sensor = small_sensor("kinect_v2", width=16)
transport = transport_of(sensor)
n_raw = len(sensor.modulation.correlation_bank())
threshold = render_module.flip_threshold_m(sensor)
sigma, flips = depth_error.render_error(transport, sensor, n_raw, threshold)       # the CPU build
build = depth_error.cuda_build()
from tofcore.tracer.estimator import replicate_counts
h, w = transport.height, transport.width
counts = replicate_counts(transport.sample_count).astype(np.int64)
channels, freqs, settings = depth_error.tables(sensor, n_raw, threshold)
scale = np.abs(sensor.camera.pixel_center_directions()[..., 2]).reshape(-1).astype(np.float64)
table = np.empty((counts.shape[0] + 1, freqs.shape[0], 6, h * w))
g_sigma, g_flips = np.empty(h * w), np.zeros(h * w, dtype=np.bool_)
blocks = (h * w + 127) // 128
build.phasors_kernel[blocks, 128](transport.replicate_sum, counts, channels, freqs, table)
build.error_kernel[blocks, 128](table, counts, transport.first_hit.distance_m.reshape(-1).astype(np.float64), scale,
                                freqs, settings, w, g_sigma, g_flips)
assert np.array_equal(np.isnan(g_sigma.reshape(h, w)), np.isnan(sigma))
seen = ~np.isnan(sigma)
assert np.allclose(g_sigma.reshape(h, w)[seen], sigma[seen], rtol=1e-12, atol=0)
assert np.array_equal(g_flips.reshape(h, w), flips)
per_k = depth_error.clean_per_k(transport, sensor, n_raw)                           # the CPU build
g_per_k = np.empty((transport.max_depth, h * w))
build.clean_kernel[blocks, 128](np.ascontiguousarray(transport.correlation_sum[:, :n_raw]), transport.ambient_sum,
                                transport.sample_count, channels, freqs, settings, g_per_k)
g_per_k = g_per_k.reshape(per_k.shape).astype(np.float32)
assert np.array_equal(np.isnan(g_per_k), np.isnan(per_k))
assert np.allclose(g_per_k[~np.isnan(per_k)], per_k[~np.isnan(per_k)], rtol=0, atol=1e-6)
print("ok", int(np.isfinite(sigma).sum()))
"""


def test_cuda_build_of_the_estimate_in_the_simulator(tmp_path):
    """The same file compiled for CUDA, run by numba's CUDA simulator: the CPU build's flips, and its σ to 1e-12
    relative (the simulator runs the scalar functions in Python, whose math.hypot is CPython's own, not the
    C library's that the CPU build calls: an ulp apart). tests/tofcore/test_gpu.py checks the device."""
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1", NUMBA_CACHE_DIR=str(tmp_path))
    here = os.path.dirname(os.path.abspath(__file__))
    run = subprocess.run([sys.executable, "-W", "ignore", "-c", SIMULATED_GPU_ESTIMATE, here], env=env,
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.startswith("ok")


def _no_numba_cuda() -> str:
    from tofcore import backend, compiled

    try:
        backend.select_device("gpu")
    except backend.GpuUnavailable as exc:
        return str(exc)
    return compiled.cuda_unavailable() or ""


@pytest.mark.gpu
@pytest.mark.skipif(bool(_no_numba_cuda()), reason=f"needs numba-cuda and a CUDA GPU: {_no_numba_cuda()}")
def test_cuda_estimate_equals_the_cpu_estimate(monkeypatch):
    """The CUDA kernels on the wavefront's transport (a 128-pixel-wide Kinect v2 room) against the CPU build on
    the same sums read back: the same flips, σ to 1e-9 relative (CUDA's exp, atan2 and hypot are an ulp from
    glibc's); the per-k ground truth to a micrometre, with at most one pixel's validity on the tolerance's edge."""
    from tofcore import backend
    from tofcore.compiled import depth_error

    monkeypatch.setenv("TOFCORE_TRACER", "compiled")
    sensor = small_sensor("kinect_v2", width=128)
    scene = tofcore.demo_scene("room")
    pose = tofcore.suggested_pose(scene, sensor)
    on_device = tofcore.trace(scene, sensor.camera, sensor.leds, world_from_sensor=pose,
                              correlations=sensor.modulation.correlation_bank(), spp=8, max_depth=3, seed=3,
                              device="gpu")
    assert on_device.stats.tracer == "compiled" and backend.namespace(on_device.replicate_sum) is not np
    first_hit = dataclasses.replace(on_device.first_hit, distance_m=backend.to_host(on_device.first_hit.distance_m))
    on_host = dataclasses.replace(on_device, replicate_sum=backend.to_host(on_device.replicate_sum),
                                  sample_count=backend.to_host(on_device.sample_count), first_hit=first_hit)
    n_raw = len(sensor.modulation.correlation_bank())
    threshold = render_module.flip_threshold_m(sensor)
    sigma, flips = depth_error.render_error(on_host, sensor, n_raw, threshold)
    g_sigma, g_flips = (backend.to_host(a) for a in depth_error.render_error(on_device, sensor, n_raw, threshold))
    np.testing.assert_array_equal(np.isnan(g_sigma), np.isnan(sigma))
    seen = ~np.isnan(sigma)
    assert seen.mean() > 0.5
    np.testing.assert_allclose(g_sigma[seen], sigma[seen], rtol=1e-9, atol=0)
    assert (g_flips != flips).sum() <= 1
    on_host_sums = dataclasses.replace(on_host, correlation_sum=backend.to_host(on_device.correlation_sum),
                                       ambient_sum=backend.to_host(on_device.ambient_sum))
    per_k = depth_error.clean_per_k(on_host_sums, sensor, n_raw)
    g_per_k = backend.to_host(depth_error.clean_per_k(on_device, sensor, n_raw))
    assert (np.isnan(g_per_k) != np.isnan(per_k)).sum() <= 1
    both = ~np.isnan(g_per_k) & ~np.isnan(per_k)
    np.testing.assert_allclose(g_per_k[both], per_k[both], rtol=0, atol=1e-6)


@pytest.mark.parametrize("name", sorted(SENSORS))
def test_compiled_per_k_ground_truth_equals_the_decoders(name):
    """depth_error.clean_per_k (the GPU's per-k ground truth) against render._decode_clean_per_k (decode.decode
    with the clean settings): the same NaN pixels (no modulated signal, frequencies that disagree beyond the
    unwrap tolerance), distances to 1e-6 m (float32 output; the inputs agree to rounding)."""
    from tofcore.compiled import depth_error

    preset, overrides = SENSORS[name]
    sensor = small_sensor(preset, **overrides)
    transport = transport_of(sensor)
    n_raw = len(sensor.modulation.correlation_bank())
    plan = render_module.make_plan(tofcore.demo_scene("room"), sensor, max_depth=3, ambient=None)
    setup = render_module.frame_setup(sensor, plan)
    reference = render_module._decode_clean_per_k(transport, sensor, n_raw, setup).astype(np.float32)
    fast = depth_error.clean_per_k(transport, sensor, n_raw)
    assert fast.shape == reference.shape == (transport.max_depth, transport.height, transport.width)
    assert np.isfinite(reference).mean() > 0.5
    mismatch = np.isnan(fast) != np.isnan(reference)
    assert mismatch.mean() <= 1e-3, f"{mismatch.sum()} pixels differ in validity"
    both = ~np.isnan(fast) & ~np.isnan(reference)
    np.testing.assert_allclose(fast[both], reference[both], rtol=0, atol=1e-6)
