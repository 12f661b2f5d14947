"""Numerical stability at the edges: every case ends in finite values or a flagged invalid pixel.

The table of cases, outcomes and bounds is in docs/numerics.md; keep the two in step.
"""

import dataclasses

import numpy as np
import pytest

import tofcore
from tofcore import LED, Camera, Material, Scene
from tofcore.sensor.decode import DecodeSettings, decode
from tofcore.output.frame import Reason
from tofcore.sensor.modulation import Modulation, ideal_raw
from tofcore.sensor.presets import load_preset
from tofcore.render import render
from tofcore.sensor.config import Noise, Scattering

C = tofcore.SPEED_OF_LIGHT_M_S


def check_frame(frame):
    """No NaN outside invalid pixels, no inf anywhere, NaN depth exactly where invalid."""
    for name in ("depth", "distance", "amplitude", "offset", "intensity", "raw", "confidence"):
        assert not np.isinf(getattr(frame, name)).any(), name
    assert np.isfinite(frame.depth[frame.valid]).all()
    assert np.isnan(frame.depth[~frame.valid]).all()
    assert np.isfinite(frame.amplitude).all() and np.isfinite(frame.raw).all()
    assert ((frame.reason == Reason.VALID) == frame.valid).all()


def clean_sensor(w=24, h=18, hfov=50.0, **changes):
    s = load_preset("kinect_v2")
    return dataclasses.replace(s, camera=Camera.from_fov(w, h, hfov), noise=Noise(model="none"),
                               scattering=Scattering(model="none"), **changes)


def plane_scene(distance_m: float, size_m: float, material: Material) -> tuple[Scene, np.ndarray]:
    """A square plane facing the sensor at ``distance_m`` (identity-like pose looking along +y)."""
    s = size_m / 2
    v = np.array([[-s, distance_m, -s], [s, distance_m, -s], [s, distance_m, s], [-s, distance_m, s]], np.float32)
    scene = Scene.from_arrays(v, [[0, 1, 2], [0, 2, 3]], materials=[material])
    return scene, tofcore.look_at((0, 0, 0), (0, 1, 0))


@pytest.mark.parametrize("material", [
    Material(roughness=0.0), Material(roughness=1e-4), Material(roughness=1.3),
    Material(ior=1.0), Material(ior=1.0001, roughness=0.2),
    Material(metallic=1.0, ior=0.2, extinction=100.0, roughness=0.1),
    Material(metallic=0.5, ior=1.5, extinction=3.0, roughness=0.0),
], ids=["rough0", "rough1e-4", "rough1.3", "ior1", "ior1.0001", "k100", "half-metal-mirror"])
def test_materials_at_their_limits_render_finite(material):
    scene = tofcore.demo_scene("corner")
    scene = Scene.from_arrays(scene.vertices, scene.triangles, materials=[material])
    frame = render(scene, clean_sensor(), tofcore.suggested_pose(tofcore.demo_scene("corner")),
                   spp=4, max_depth=4, seed=0)
    check_frame(frame)


def test_grazing_incidence_89_9_degrees():
    """A floor seen at 89.9° from its normal: finite everywhere; pixels with too little light are flagged."""
    scene, _ = plane_scene(2.0, 4.0, Material(reflectance=0.8, roughness=0.3))
    # Look along the plane y = 2 (a wall) from a point 3.5 mm in front of it.
    pose = tofcore.look_at((0.0, 2.0 - 2.0 * np.tan(np.radians(0.1)), 0.0), (0.0, 2.0 - 2.0 * np.tan(np.radians(0.1)), 2.0),
                           up=(1.0, 0.0, 0.0))
    frame = render(scene, clean_sensor(hfov=10.0), pose, spp=2, max_depth=3, seed=0)
    check_frame(frame)


@pytest.mark.parametrize("scale", [1e-3, 1e3], ids=["millimetres", "kilometres"])
def test_scenes_in_millimetres_and_kilometres(scale):
    """Path lengths stay exact relative to the scene: the direct distance of a plane scaled by 1e-3 or 1e3
    matches its first-hit distance to 1e-6 relative (a sine sensor with the range scaled too)."""
    scene, pose = plane_scene(2.0 * scale, 4.0 * scale, Material(reflectance=0.8, roughness=0.0, ior=1.0))
    f_hz = 16e6 / scale
    sensor = clean_sensor(hfov=10.0, leds=(LED(intensity_w_sr=scale**2),),
                          modulation=Modulation(kind="cw_sine", frequencies_hz=(f_hz,), exposure_s=(8e-3,)),
                          range_m=(0.1 * scale, 9.0 * scale))
    frame = render(scene, sensor, pose, spp=1, max_depth=1, seed=0)
    check_frame(frame)
    assert frame.valid.all()
    # One jittered sample per pixel vs the pixel centre: the footprint spans < 0.05 % of the distance.
    np.testing.assert_allclose(frame.distance, frame.gt_distance, rtol=5e-4)


def test_led_one_centimetre_from_a_surface_saturates_cleanly():
    scene, pose = plane_scene(0.01, 0.5, Material(reflectance=0.9))
    frame = render(scene, clean_sensor(), pose, spp=1, max_depth=2, seed=0)
    check_frame(frame)
    assert (frame.reason == Reason.SATURATED).any()


def test_zero_signal_is_no_return():
    """A scene behind the sensor: zero signal in every bucket (atan2(0, 0)) → NO_RETURN, no NaN leaks."""
    scene, _ = plane_scene(-2.0, 4.0, Material())
    frame = render(scene, clean_sensor(), tofcore.look_at((0, 0, 0), (0, 1, 0)), spp=1, max_depth=2)
    check_frame(frame)
    assert (frame.reason == Reason.NO_RETURN).all()


# --- decoding on synthetic raw images -------------------------------------------------------------------

SINE = Modulation(kind="cw_sine", frequencies_hz=(80e6,))


def test_distance_exactly_at_and_at_ten_times_the_ambiguity_distance():
    d_amb = SINE.ambiguity_distances_m()[0]
    raw = ideal_raw(SINE, np.array([d_amb, 10 * d_amb, 10.5 * d_amb]), signal_e=1e4, ambient_e=100.0)
    out = decode(raw, SINE, DecodeSettings(range_m=(0.0, d_amb)))
    assert np.isfinite(out.distance[:2]).all()
    # A round trip of exactly n ambiguity distances aliases to 0 (or d_amb, the same phase) to 1e-9 m.
    assert (np.minimum(out.distance[:2], d_amb - out.distance[:2]) < 1e-6).all()
    np.testing.assert_allclose(out.distance[2], 0.5 * d_amb, atol=1e-6)


def test_120_mhz_phase_at_100_m():
    """Float64 phases: at 100 m a 120 MHz phase is ~500 rad; decoding keeps micrometres."""
    mod = Modulation(kind="cw_sine", frequencies_hz=(120e6,))
    d_amb = mod.ambiguity_distances_m()[0]
    d = np.array([100.0, 100.0 + 1e-5])
    out = decode(ideal_raw(mod, d, signal_e=1e4), mod, DecodeSettings(range_m=(0.0, d_amb)))
    expected = np.mod(d, d_amb)
    np.testing.assert_allclose(out.distance, expected, atol=1e-6)


def test_pulse_delay_exactly_t0_and_2t0():
    t0 = 25e-9
    mod = Modulation(kind="pulsed", pulse_width_s=t0, exposure_s=(1e-3,), duty_cycle=0.1)
    d_t0, d_2t0 = C * t0 / 2, C * t0
    out = decode(ideal_raw(mod, np.array([d_t0, d_2t0]), signal_e=1e4), mod,
                 DecodeSettings(range_m=(0.0, d_t0 * 1.001)))
    np.testing.assert_allclose(out.distance[0], d_t0, rtol=1e-7)   # all light in C2: d = d_max (float32 output)
    assert out.reason[1] == Reason.NO_RETURN                        # the pulse missed both buckets
    assert np.isnan(out.distance[1])


def test_saturation_is_flagged():
    raw = ideal_raw(SINE, np.array([1.0, 1.0]), signal_e=np.array([1e4, 1e6]))
    out = decode(np.minimum(raw, 2e5), SINE, DecodeSettings(saturation_e=2e5))
    assert out.reason.tolist() == [Reason.VALID, Reason.SATURATED]
    assert np.isnan(out.distance[1]) and np.isfinite(out.amplitude).all()
