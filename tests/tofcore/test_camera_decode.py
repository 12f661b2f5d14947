"""The camera's decode compiled (tofcore.compiled.camera_decode) against the decoder (tofcore.sensor.decode.decode).

Tolerance: the same reason and validity for every pixel, and every float32 output (distance, amplitude, offset,
intensity, confidence) within one float32 ulp, NaN where the decoder's is NaN. Why not bit for bit: NumPy's DFT
sums go through BLAS and its cos/sin/exp/atan2 may be vectorised, either of which can round a last float64 bit
differently from the compiled code's sums in order and the C library's functions; such a float64 difference of
~1e-16 relative moves a float32 output by one ulp only where the value lies on a float32 rounding boundary, and a
reason only where a tested value (an amplitude against its floor, the unwrap residual, a dealiasing distance, an
edge-filter spread) lies within ~1e-15 relative of its threshold, which none of these images' pixels does (on
this project's machines the outputs are in fact the same bits; a reason that differs is a failure to look at).
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import subprocess
import sys
import types

import numpy as np
import pytest

import tofcore
from tofcore.errors import ConfigError
from tofcore.sensor import decode as decoding
from tofcore.sensor.modulation import ideal_raw
from tofcore.sensor.noise import NoiseStream

from .test_depth_error import _no_numba_cuda

render_module = importlib.import_module("tofcore.render")  # the module (tofcore.render is the function)
numba = pytest.importorskip("numba")

FLOAT_OUTPUTS = ("distance", "amplitude", "offset", "intensity", "confidence")

SENSORS = {
    # 3 frequencies, bilateral filter with its edge test, f/Σf output, every frequency's amplitude tested,
    # dealiasing, edge-aware filter, z range (range_scale), raw noise with gain noise, lens scattering
    "kinect_v2": ("kinect_v2", {}),
    "kinect_v2_unfiltered": ("kinect_v2", {"processing.phasor_filter": "none",
                                           "processing.unwrap_weights": "inverse_variance",
                                           "invalid.amplitude_test": "highest", "invalid.dealias_tolerance_rad": None}),
    "kinect_v2_filter_without_edge_filter": ("kinect_v2", {"invalid.edge_filter": False}),
    "o3d303": ("o3d303", {}),                                           # one 30 MHz frequency, 4 steps, radial
    "two_sine_frequencies": ("o3d303", {"modulation.kind": "cw_sine", "modulation.frequencies_hz": [20e6, 50e6],
                                        "modulation.phase_steps": [3, 5], "modulation.exposure_s": [5e-3, 5e-3]}),
}


def camera_decode():
    from tofcore.compiled import camera_decode as module

    return module


def small_sensor(preset: str, width: int = 40, **overrides):
    sensor = tofcore.load_preset(preset)
    return sensor.scaled(width / sensor.camera.width).replace(**overrides)


def camera_setup(sensor):
    """(plan, FrameSetup) of a render of the demo room by ``sensor``; ``.camera`` is the camera's DecodeSettings."""
    plan = render_module.make_plan(tofcore.demo_scene("room"), sensor, max_depth=3, ambient=None)
    return plan, render_module.frame_setup(sensor, plan)


def camera_raw(sensor, spp: int = 4, seed: int = 5):
    """(raw (R, H, W), the camera's DecodeSettings) of the demo room as a render makes them: scattering, noise."""
    scene = tofcore.demo_scene("room")
    pose = tofcore.suggested_pose(scene, sensor)
    transport = tofcore.trace(scene, sensor.camera, sensor.leds, world_from_sensor=pose,
                              correlations=sensor.modulation.correlation_bank(), spp=spp, max_depth=3, seed=3,
                              ambient=tofcore.Ambient(radiance_w_m2_sr=0.05))
    plan, setup = camera_setup(sensor)
    n_raw = len(sensor.modulation.correlation_bank())
    return render_module._camera_raw(transport, sensor, plan, NoiseStream.from_seed(seed), n_raw, setup), setup.camera


def every_reason_raw(modulation, full_well_e: float, height: int = 14, width: int = 18, seed: int = 2):
    """Raw images (R, H, W) with a pixel of every kind: a wall at 2 m stepping to 3.4 m (flying and mixed pixels
    at the step), shot noise, no light at all (raw 0: atan2(0, 0)), ambient light only, a weak return, saturated
    charges, returns beyond and before the range, mixed returns whose frequencies disagree, on the border too."""
    rng = np.random.default_rng(seed)
    distance = np.where(np.arange(width) < width // 2, 2.0, 3.4)[None].repeat(height, 0)
    signal = 4e4 / distance ** 2
    distance[:, :3] = 0.3                                     # before the range
    distance[-3:, -4:] = 6.1                                  # beyond the Kinect v2's (the O3D303 wraps it)
    raw = ideal_raw(modulation, distance, signal, ambient_e=2e3)
    mixed = 0.5 * (ideal_raw(modulation, np.full((height, width), 1.1), 1e4, 2e3)
                   + ideal_raw(modulation, np.full((height, width), 2.9), 1e4, 2e3))
    raw[:, 5:8, 10:13] = mixed[:, 5:8, 10:13]
    raw[:, 3:5, 3:6] = ideal_raw(modulation, distance, 12.0, 50.0)[:, 3:5, 3:6]       # weak: below 50 e⁻
    raw[:, 9:11, 3:5] = 2e3 * 0.5                                                    # ambient only
    raw = np.maximum(raw + rng.normal(0.0, 1.0, raw.shape) * np.sqrt(raw), 0.0)
    raw[:, 0:2, 7:10] = 0.0                                                          # no light at all
    raw[:, 6:8, 4:6] = 3.0 * full_well_e                                             # saturated
    return np.minimum(raw, full_well_e)


def assert_decodes_agree(fast, reference):
    np.testing.assert_array_equal(fast.reason, reference.reason)
    np.testing.assert_array_equal(fast.valid, reference.valid)
    assert fast.reason.dtype == np.uint8 and fast.valid.dtype == bool
    for name in FLOAT_OUTPUTS:
        a, b = getattr(fast, name), getattr(reference, name)
        assert a.dtype == b.dtype == np.float32 and a.shape == b.shape, name
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b), err_msg=name)
        seen = ~np.isnan(b)
        np.testing.assert_array_max_ulp(a[seen], b[seen], maxulp=1)


@pytest.mark.parametrize("name", sorted(SENSORS))
def test_compiled_decode_equals_the_decoder_on_rendered_raw_images(name):
    preset, overrides = SENSORS[name]
    sensor = small_sensor(preset, **overrides)
    raw, settings = camera_raw(sensor)
    assert camera_decode().unsupported(sensor.modulation, settings, raw.shape[1:]) == ""
    reference = decoding.decode(raw, sensor.modulation, settings)
    assert reference.valid.mean() > 0.5
    assert_decodes_agree(camera_decode().decode(raw, sensor.modulation, settings), reference)


@pytest.mark.parametrize("preset", ["kinect_v2", "o3d303"])
def test_compiled_decode_equals_the_decoder_for_every_reason(preset):
    """Every reason the decoder gives (edge-filtered pixels for the Kinect v2's filters), border pixels, NaN
    distances of invalid pixels, a range scale per pixel."""
    sensor = small_sensor(preset)
    raw = every_reason_raw(sensor.modulation, sensor.readout.full_well_e)
    scale = np.random.default_rng(1).uniform(0.85, 1.0, raw.shape[1:])
    settings = camera_setup(sensor)[1].camera.replace(range_scale=scale)
    reference = decoding.decode(raw, sensor.modulation, settings)
    expected = set(decoding.Reason) - ({decoding.Reason.UNWRAPPING_FAILED, decoding.Reason.EDGE_FILTERED}
                                       if preset == "o3d303" else set())  # one frequency: no unwrapping, no filter
    assert set(np.unique(reference.reason)) == {int(r) for r in expected}
    assert_decodes_agree(camera_decode().decode(raw, sensor.modulation, settings), reference)


def test_compiled_decode_checks_as_the_decoder_does():
    """A non-finite raw image is the decoder's error (with ``check``); so are settings of the wrong type."""
    sensor = small_sensor("o3d303")
    raw = every_reason_raw(sensor.modulation, sensor.readout.full_well_e)
    raw[1, 2, 3] = np.nan
    for decode in (decoding.decode, camera_decode().decode):
        with pytest.raises(ConfigError, match="raw must be finite electrons"):
            decode(raw, sensor.modulation)
        with pytest.raises(ConfigError, match="settings must be a DecodeSettings, got dict"):
            decode(raw, sensor.modulation, {})


def test_the_decoder_takes_what_the_kernels_do_not(monkeypatch):
    """camera_decode.supports names why it cannot decode (a pulsed sensor, a batch of images, too many wraps) and
    camera_decode.decode refuses those; render._camera_decoder picks the kernels only for the GPU's compiled
    wavefront and what they support."""
    from tests import fakecupy

    module = camera_decode()
    kinect, xtion = small_sensor("kinect_v2"), small_sensor("xtion2")
    settings = decoding.DecodeSettings(phasor_filter="bilateral", edge_filter=True)
    assert module.unsupported(kinect.modulation, settings, (30, 40)) == ""
    assert "pulsed" in module.unsupported(xtion.modulation, settings, (30, 40))
    assert "not one (H, W) image" in module.unsupported(kinect.modulation, settings, (3, 30, 40))
    many_wraps = dataclasses.replace(kinect.modulation, frequencies_hz=(80e6, 80.0001e6, 120e6))
    assert "wrap candidates" in module.unsupported(many_wraps, settings, (30, 40))
    with pytest.raises(ConfigError, match="camera_decode: cannot decode a pulsed sensor"):
        module.decode(np.ones((2, 4, 4)), xtion.modulation)

    fakecupy.install(monkeypatch)
    on_gpu = types.SimpleNamespace(replicate_sum=fakecupy.asarray(np.zeros(3)),
                                   stats=types.SimpleNamespace(tracer="compiled"))
    array_program = types.SimpleNamespace(replicate_sum=on_gpu.replicate_sum,
                                          stats=types.SimpleNamespace(tracer="numpy"))
    on_cpu = types.SimpleNamespace(replicate_sum=np.zeros(3), stats=types.SimpleNamespace(tracer="compiled"))
    choose = render_module._camera_decoder
    assert choose(on_gpu, kinect, settings, (30, 40)) is module.decode
    assert choose(on_gpu, xtion, settings, (30, 40)) is decoding.decode
    assert choose(on_gpu, kinect, settings, (3, 30, 40)) is decoding.decode
    assert choose(array_program, kinect, settings, (30, 40)) is decoding.decode
    assert choose(on_cpu, kinect, settings, (30, 40)) is decoding.decode


SIMULATED_GPU_DECODE = r"""
import numpy as np, sys
from tofcore.compiled import camera_decode
from tofcore.sensor import decode as decoding
import tofcore
data = np.load(sys.argv[1], allow_pickle=True)
sensor = tofcore.load_preset("kinect_v2")
raw = data["raw"]
settings = decoding.DecodeSettings(**data["settings"].item())
h, w = raw.shape[1:]
images = np.empty((len(camera_decode.OUTPUT_IMAGES), h * w), dtype=np.float32)
reason, valid = np.empty(h * w, dtype=np.uint8), np.empty(h * w, dtype=np.bool_)
camera_decode.launch_cuda(camera_decode.cuda_build(), raw.reshape(raw.shape[0], -1),
                          camera_decode.tables(sensor.modulation, settings),
                          np.ascontiguousarray(settings.range_scale, dtype=np.float64).reshape(-1), w, images, reason,
                          valid, np)
np.savez(sys.argv[2], reason=reason.reshape(h, w), valid=valid.reshape(h, w),
         **dict(zip(camera_decode.OUTPUT_IMAGES, images.reshape(-1, h, w))))
"""


def test_cuda_build_of_the_decode_in_the_simulator(tmp_path):
    """The same file compiled for CUDA, run by numba's CUDA simulator on every kind of Kinect v2 pixel (all three
    passes): the decoder's reasons and outputs within the tolerance above. tests/tofcore/test_gpu.py-style GPU
    tests below check the device itself."""
    sensor = tofcore.load_preset("kinect_v2")
    raw = every_reason_raw(sensor.modulation, sensor.readout.full_well_e, height=10, width=14)
    scale = np.random.default_rng(1).uniform(0.85, 1.0, raw.shape[1:])
    fields = dict(min_amplitude_e=50.0, min_amplitude_snr=3.0, read_noise_e=20.0, gain_noise=0.012,
                  saturation_e=sensor.readout.full_well_e, range_m=(0.5, 4.5), range_scale=scale,
                  unwrap_weights="frequency", phasor_filter="bilateral", amplitude_test="every",
                  dealias_tolerance_rad=0.6108653, edge_filter=True, edge_delta_scale=1.0)
    np.savez(tmp_path / "in.npz", raw=raw, settings=np.array(fields, dtype=object))
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1", NUMBA_CACHE_DIR=str(tmp_path))
    run = subprocess.run([sys.executable, "-W", "ignore", "-c", SIMULATED_GPU_DECODE, str(tmp_path / "in.npz"),
                          str(tmp_path / "out.npz")], env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    reference = decoding.decode(raw, sensor.modulation, decoding.DecodeSettings(**fields))
    reasons = set(np.unique(reference.reason))
    assert {int(decoding.Reason.EDGE_FILTERED), int(decoding.Reason.UNWRAPPING_FAILED)} <= reasons
    simulated = decoding.Decoded(**dict(np.load(tmp_path / "out.npz")))
    assert_decodes_agree(simulated, reference)


needs_numba_cuda = pytest.mark.skipif(bool(_no_numba_cuda()),
                                      reason=f"needs numba-cuda and a CUDA GPU: {_no_numba_cuda()}")


def host_decoded(decoded) -> decoding.Decoded:
    from tofcore import backend

    return decoding.Decoded(**{f: backend.to_host(getattr(decoded, f)) for f in decoding.Decoded.__dataclass_fields__})


def assert_device_decodes_agree(fast, reference, at_most: float = 1e-4):
    """The CUDA kernels against the CuPy decoder: CUDA's atan2/exp/cos/sin round an ulp from CuPy's (and each
    compiler fuses multiply-adds where it chooses), so a tested value within ~1e-15 of its threshold may go either
    way: the same reason but at most ``at_most`` of the pixels (and one), float32 outputs of the pixels valid in
    both within 1e-6 (m, e⁻ relative)."""
    differ = fast.reason != reference.reason
    assert differ.sum() <= max(1, at_most * differ.size), f"{differ.sum()} of {differ.size} reasons differ"
    both = fast.valid & reference.valid
    assert both.mean() > 0.3
    np.testing.assert_allclose(fast.distance[both], reference.distance[both], rtol=0, atol=1e-6)
    np.testing.assert_allclose(fast.confidence[both], reference.confidence[both], rtol=0, atol=1e-6)
    for name in ("amplitude", "offset", "intensity"):
        np.testing.assert_allclose(getattr(fast, name), getattr(reference, name), rtol=1e-6, atol=1e-6, err_msg=name)


@pytest.mark.gpu
@needs_numba_cuda
@pytest.mark.parametrize("name", ["kinect_v2", "o3d303"])
def test_cuda_decode_equals_the_cupy_decoder(name):
    """The three kernels and the CuPy decoder on the same device raw images: the room's at 128 pixels wide."""
    import cupy as cp

    preset, overrides = SENSORS[name]
    sensor = small_sensor(preset, width=128, **overrides)
    raw, settings = camera_raw(sensor)
    if settings.range_scale is not None:
        settings = settings.replace(range_scale=cp.asarray(settings.range_scale))
    device_raw = cp.asarray(raw)
    reference = host_decoded(decoding.decode(device_raw, sensor.modulation, settings))
    fast = host_decoded(camera_decode().decode(device_raw, sensor.modulation, settings))
    assert_device_decodes_agree(fast, reference)


@pytest.mark.gpu
@needs_numba_cuda
def test_gpu_render_with_the_kernels_equals_the_cupy_decoder_path(monkeypatch):
    """A GPU render on the compiled wavefront decodes the camera's images with the kernels; the same render with
    the CuPy decoder (render._camera_decoder patched) gives the same frame within the tolerance above."""
    monkeypatch.setenv("TOFCORE_TRACER", "compiled")
    module = camera_decode()
    calls = []
    kernels_decode = module.decode

    def counted(*args, **kwargs):
        calls.append(1)
        return kernels_decode(*args, **kwargs)

    monkeypatch.setattr(module, "decode", counted)
    scene, sensor = tofcore.demo_scene("room"), small_sensor("kinect_v2", width=128)
    settings = dict(spp=4, max_depth=3, seed=7, device="gpu")
    fast = tofcore.render(scene, sensor, **settings)
    assert calls and fast.stats["transport"]["tracer"] == "compiled"
    monkeypatch.setattr(render_module, "_camera_decoder", lambda *args: decoding.decode)
    reference = tofcore.render(scene, sensor, **settings)
    same_raw = np.all(np.abs(fast.raw - reference.raw) <= 1e-9 * np.abs(reference.raw).max(axis=0), axis=0)
    assert same_raw.mean() > 0.998
    assert np.mean(fast.reason[same_raw] != reference.reason[same_raw]) <= 1e-3
    both = fast.valid & reference.valid & same_raw
    np.testing.assert_allclose(fast.depth[both], reference.depth[both], rtol=0, atol=1e-6)
