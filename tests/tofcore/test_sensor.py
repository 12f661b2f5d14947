"""Tests of tofcore.sensor and tofcore.sensor.presets: the three presets, round trips and every bad-preset error."""

import json
import math
import re
import tomllib
from pathlib import Path

import pytest

from tofcore.scene.camera import Camera
from tofcore.errors import ConfigError
from tofcore.scene.led import LED
from tofcore.sensor.modulation import Modulation
from tofcore.sensor.presets import PRESETS_DIR, list_presets, load_preset
from tofcore.sensor.config import InvalidRules, Noise, Readout, Scattering, Sensor

# SPEC §5 / thesis Tab. 4.1: resolution, FOV (h, v) in degrees, range, frame rate, IR image.
TABLE_4_1 = {
    "kinect_v2": dict(size=(512, 424), fov=(70.0, 60.0), range_m=(0.5, 4.5), fps=30, ir=True),
    "o3d303": dict(size=(352, 264), fov=(60.0, 45.0), range_m=(0.3, 30.0), fps=25, ir=True),
    "xtion2": dict(size=(640, 480), fov=(74.0, 52.0), range_m=(0.8, 3.5), fps=30, ir=False),
}


def pinhole_fov_deg(cam: Camera) -> tuple[float, float]:
    """Angle between the rays through opposite image edges, from fx, fy and the principal point."""
    h = math.atan((cam.cx + 0.5) / cam.fx) + math.atan((cam.width - 0.5 - cam.cx) / cam.fx)
    v = math.atan((cam.cy + 0.5) / cam.fy) + math.atan((cam.height - 0.5 - cam.cy) / cam.fy)
    return math.degrees(h), math.degrees(v)


# ------------------------------------------------------------------ the presets
def test_list_presets_names_the_three_sensors():
    assert list_presets() == ["kinect_v2", "o3d303", "xtion2"]


@pytest.mark.parametrize("name", sorted(TABLE_4_1))
def test_preset_matches_table_4_1(name):
    sensor = load_preset(name)
    spec = TABLE_4_1[name]
    assert sensor.name == name
    assert (sensor.camera.width, sensor.camera.height) == spec["size"]
    for fov, expected in zip(pinhole_fov_deg(sensor.camera), spec["fov"]):
        assert fov == pytest.approx(expected, abs=2.0)
    assert sensor.range_m[0] == spec["range_m"][0]
    assert sensor.range_m[1] <= spec["range_m"][1]
    assert sensor.frame_rate_hz == spec["fps"]
    assert sensor.ir_image is spec["ir"]


def test_kinect_v2_modulation_and_led():
    s = load_preset("kinect_v2")
    assert s.modulation.kind == "cw_square"
    assert s.modulation.frequencies_hz == (80e6, 16e6, 120e6)
    assert s.modulation.phase_steps == (3, 3, 3)
    assert s.modulation.exposure_s == (8e-3, 4e-3, 8e-3)
    assert s.modulation.unambiguous_range_m() == pytest.approx(18.737, abs=1e-3)  # 8 MHz beat, §2.2.2
    assert [led.position_m for led in s.leds] == [(-0.025, 0.0, 0.0)]  # 2.5 cm to one side, §6.2
    assert s.camera.has_distortion


def test_o3d303_modulation_and_four_leds_around_the_lens():
    s = load_preset("o3d303")
    assert (s.modulation.kind, s.modulation.frequencies_hz) == ("cw_square", (30e6,))
    assert len(s.leds) == 4
    xs = [led.position_m[0] for led in s.leds]
    ys = [led.position_m[1] for led in s.leds]
    assert min(xs) < 0 < max(xs) and min(ys) < 0 < max(ys)
    assert sum(xs) == pytest.approx(0.0) and sum(ys) == pytest.approx(0.0)


def test_xtion2_is_pulsed_with_range_inside_d_max_and_leds_on_one_side():
    s = load_preset("xtion2")
    assert s.modulation.kind == "pulsed"
    assert s.modulation.pulse_width_s == pytest.approx(1 / (2 * 20e6))  # half the 20 MHz period
    assert s.modulation.unambiguous_range_m() >= s.range_m[1] == 3.5
    assert len({math.copysign(1.0, led.position_m[0]) for led in s.leds}) == 1


@pytest.mark.parametrize("name", list_presets())
def test_every_number_in_a_preset_has_a_source(name):
    data = tomllib.loads((PRESETS_DIR / f"{name}.toml").read_text())
    sources = data["sources"]
    keys = [k for k in data if not isinstance(data[k], (dict, list)) and k not in ("name", "description")]
    for table, value in data.items():
        if table == "sources":
            continue
        if isinstance(value, dict):
            keys += [f"{table}.{k}" for k in value]
        elif isinstance(value, list) and value and isinstance(value[0], dict):
            keys += [f"{table}.{k}" for item in value for k in item]
    missing = sorted({k for k in keys if k not in sources})
    assert not missing, f"{name}: no source for {missing}"


# ------------------------------------------------------------------ round trips and replace
@pytest.mark.parametrize("name", list_presets())
def test_to_dict_round_trips_and_is_strict_json(name):
    sensor = load_preset(name)
    data = sensor.to_dict()
    assert Sensor.from_dict(json.loads(json.dumps(data, allow_nan=False)), where="copy") == sensor


def test_sub_tables_round_trip():
    for obj in (Readout(responsivity=1e7, full_well_e=5e4), Noise(model="li", modulation_contrast=0.5),
                Scattering(model="gaussians", strength=0.1, sigmas_px=(1.0, 3.0), weights=(0.5, 0.5)),
                InvalidRules(min_amplitude_e=10, unwrap_tolerance_m=0.05)):
        assert type(obj).from_dict(obj.to_dict()) == obj


def test_replace_top_level_and_dotted_fields():
    s = load_preset("kinect_v2")
    r = s.replace(**{"modulation.frequencies_hz": [20e6], "modulation.phase_steps": [4],
                     "modulation.exposure_s": [1e-3], "noise.model": "none", "depth_output": "radial",
                     "leds": [LED(position_m=(0.0, 0.0, 0.0))]})
    assert r.modulation.frequencies_hz == (20e6,) and r.modulation.phase_steps == (4,)
    assert (r.noise.model, r.depth_output, len(r.leds)) == ("none", "radial", 1)
    assert r.camera == s.camera and s.noise.model == "raw"  # the original is untouched
    assert s.replace(frame_rate_hz=None).frame_rate_hz is None
    assert s.replace(camera=Camera.from_fov(64, 48, 70.0)).camera.width == 64


def test_replace_validates_like_a_preset():
    s = load_preset("kinect_v2")
    with pytest.raises(ConfigError, match=r"Sensor.replace \[noise\]: model must be one of "
                                          r"\['none', 'raw', 'li'\], got 'gaussian'"):
        s.replace(**{"noise.model": "gaussian"})
    with pytest.raises(ConfigError, match=r"Sensor.replace: 'range_m.max' must name a field of one of the tables"):
        s.replace(**{"range_m.max": 3.0})
    with pytest.raises(ConfigError, match=r"Sensor.replace: unknown top-level key 'colour'"):
        s.replace(colour="red")


def test_sensor_built_directly_is_validated():
    s = load_preset("o3d303")
    kwargs = {f: getattr(s, f) for f in ("name", "camera", "leds", "modulation", "readout", "range_m", "sources")}
    assert Sensor(**kwargs).noise == Noise()
    with pytest.raises(ConfigError, match=r"Sensor: leds must be one or more LEDs .*got \(\)"):
        Sensor(**kwargs | {"leds": ()})
    with pytest.raises(ConfigError, match=r"Sensor: camera must be a Camera, got 'kinect'"):
        Sensor(**kwargs | {"camera": "kinect"})
    pulsed = Modulation(kind="pulsed", pulse_width_s=25e-9)
    with pytest.raises(ConfigError, match=r"Sensor: noise.model must be 'raw' or 'none' for a pulsed sensor"):
        Sensor(**kwargs | {"modulation": pulsed, "range_m": (0.3, 3.0), "noise": Noise(model="li")})


@pytest.mark.parametrize("cls, kwargs, pattern", [
    (Readout, dict(responsivity=0.0, full_well_e=1e4), r"Readout: responsivity must be a finite number > 0 .*got 0.0"),
    (Noise, dict(read_noise_e=-1), r"Noise: read_noise_e must be a finite number >= 0 \(electrons\), got -1"),
    (Noise, dict(modulation_contrast=0.0), r"Noise: modulation_contrast must be a number in \(0, 1\], got 0.0"),
    (Scattering, dict(model="airy", strength=0.1), r"Scattering: radius_px must be > 0 \(pixels\) for model 'airy'"),
    (Scattering, dict(strength=1.0), r"Scattering: strength must be a number in \[0, 1\), got 1.0"),
    (Scattering, dict(model="airy", strength=0.1, radius_px=2, negative_lobe=0.9),
     r"Scattering: negative_lobe must leave the ring pattern a positive total .*got 0.9"),
    (Scattering, dict(model="gaussians", strength=0.1, sigmas_px=(1.0, 2.0), weights=(0.5, 0.6)),
     r"Scattering: weights must be 2 numbers \(one per sigmas_px entry\) summing to 1, got \(0.5, 0.6\)"),
    (InvalidRules, dict(invalidate_saturated=1), r"InvalidRules: invalidate_saturated must be true or false, got 1"),
    (InvalidRules, dict(unwrap_tolerance_m=0.0), r"InvalidRules: unwrap_tolerance_m must be a finite number > 0"),
])
def test_sub_tables_validate_on_construction(cls, kwargs, pattern):
    with pytest.raises(ConfigError, match=pattern):
        cls(**kwargs)


# ------------------------------------------------------------------ bad presets
KINECT_TEXT = (PRESETS_DIR / "kinect_v2.toml").read_text()


def write_variant(tmp_path: Path, old: str, new: str, base: str = KINECT_TEXT) -> Path:
    """A copy of a preset with ``old`` (which must occur once) replaced by ``new``."""
    assert base.count(old) == 1, old
    path = tmp_path / "bad.toml"
    path.write_text(base.replace(old, new))
    return path


FX_SOURCE = ('"camera.fx" = "factory IR intrinsics read by libfreenect2 getIrCameraParams, one device, '
             'OpenKinect/libfreenect2 issue #41 (2014)"')

# (text in kinect_v2.toml, replacement, the error after the file name)
BAD_PRESETS = [
    # unknown keys: top level, in a table, in [[leds]], in [sources]
    ('name = "kinect_v2"', 'name = "kinect_v2"\ncolour = "red"',
     r": unknown top-level key 'colour'; valid keys are \['camera', 'depth_output', 'description', 'frame_rate_hz', "),
    ("[noise]\n", "[noise]\nshot_noise = true\n",
     r" \[noise\]: unknown key 'shot_noise'; valid keys are \['gain_noise', 'model', 'modulation_contrast', "
     r"'read_noise_e'\]"),
    ("[camera]\n", "[camera]\nhfov_deg = 70.0\n",
     r" \[camera\]: unknown key 'hfov_deg'; valid keys are \['aperture_radius_m', "),
    ('kind = "lambertian"', 'kind = "lambertian"\ncolor = 850',
     r" \[\[leds\]\] #1: unknown key 'color'; valid keys are \['intensity_w_sr', 'kind', 'position_m'\]"),
    ('"camera.k3" =', '"camera.k4" = "x"\n"camera.k3" =',
     r" \[sources\]: unknown key 'camera.k4'; keys must name a field"),
    # missing fields
    ("full_well_e = 2e5", "",
     r" \[readout\]: missing required key 'full_well_e'; required keys are \['responsivity', 'full_well_e'\]"),
    ('name = "kinect_v2"\n', "", r": missing required top-level key 'name'"),
    ("fx = 365.402802\n", "", r" \[camera\]: missing required key 'fx'"),
    # wrong types
    ("read_noise_e = 20.0", 'read_noise_e = "20"',
     r" \[noise\]: read_noise_e must be a finite number >= 0 \(electrons\), got '20'"),
    ("width = 512", "width = 512.0", r" \[camera\]: width must be a positive integer \(pixels\), got 512.0"),
    ("fx = 365.402802", 'fx = "365"', r" \[camera\]: fx must be a number, got '365'"),
    ("phase_steps = [3, 3, 3]", "phase_steps = [3.0, 3, 3]",
     r" \[modulation\]: phase_steps must be a list of integers, got \[3.0, 3, 3\]"),
    ("ir_image = true", 'ir_image = "yes"', r": ir_image must be true or false, got 'yes'"),
    (FX_SOURCE, '"camera.fx" = 365', r" \[sources\]: 'camera.fx' must be a non-empty string, got 365"),
    # out of range
    ("modulation_contrast = 0.8", "modulation_contrast = 1.5",
     r" \[noise\]: modulation_contrast must be a number in \(0, 1\], got 1.5"),
    ("strength = 0.02", "strength = 1.0", r" \[scattering\]: strength must be a number in \[0, 1\), got 1.0"),
    ("frequencies_hz = [80e6, 16e6, 120e6]", "frequencies_hz = [-80e6, 16e6, 120e6]",
     r" \[modulation\]: frequencies_hz must be finite numbers > 0, got \(-80000000.0, 16000000.0, 120000000.0\)"),
    ("k1 = 0.095575", "k1 = -1.5",
     r" \[camera\]: distortion \(k1=-1.5, .*\) must be invertible over the 512x424 image"),
    ("position_m = [-0.025, 0.0, 0.0]", "position_m = [-0.025, 0.0]",
     r" \[\[leds\]\] #1: position_m must be three finite numbers .*got \(-0.025, 0.0\)"),
    ('kind = "lambertian"', 'kind = "laser"',
     r" \[\[leds\]\] #1: kind must be one of \['point', 'lambertian'\], got 'laser'"),
    ("frame_rate_hz = 30", "frame_rate_hz = 0", r": frame_rate_hz must be a finite number > 0 \(Hz\) or absent, got 0"),
    ('depth_output = "z"', 'depth_output = "depth"', r": depth_output must be one of \['radial', 'z'\], got 'depth'"),
    ("range_m = [0.5, 4.5]", "range_m = [4.5, 0.5]",
     r": range_m must be \[min, max\] in metres, 0 <= min < max, got \[4.5, 0.5\]"),
    ("range_m = [0.5, 4.5]", "range_m = [0.5, 0.5]", r": range_m must be \[min, max\] .*got \[0.5, 0.5\]"),
    ("range_m = [0.5, 4.5]", "range_m = [0.5, 20.0]",
     r": range_m must be within the modulation's unambiguous range \(max <= 18.74 m\), got \[0.5, 20.0\]"),
]


@pytest.mark.parametrize("old, new, pattern", BAD_PRESETS, ids=[f"{i:02d}" for i in range(len(BAD_PRESETS))])
def test_bad_preset_names_file_table_key_and_value(tmp_path, old, new, pattern):
    path = write_variant(tmp_path, old, new)
    with pytest.raises(ConfigError, match=re.escape(str(path)) + pattern):
        load_preset(path)


def test_a_table_given_as_a_value_is_rejected():
    data = tomllib.loads(KINECT_TEXT) | {"noise": 3}
    with pytest.raises(ConfigError, match=r"^kinect: noise must be a table \[noise\], got 3$"):
        Sensor.from_dict(data, where="kinect")


def test_toml_ints_are_accepted_for_floats(tmp_path):
    path = write_variant(tmp_path, "read_noise_e = 20.0", "read_noise_e = 20")
    noise = load_preset(path).noise
    assert noise.read_noise_e == 20.0 and isinstance(noise.read_noise_e, float)


def test_li_noise_on_a_pulsed_preset_is_rejected(tmp_path):
    base = (PRESETS_DIR / "xtion2.toml").read_text()
    path = write_variant(tmp_path, 'model = "raw"', 'model = "li"', base=base)
    with pytest.raises(ConfigError, match=re.escape(str(path)) + r": noise.model must be 'raw' or 'none' for a pulsed"):
        load_preset(path)


def test_unknown_preset_name_lists_the_available_ones():
    with pytest.raises(ConfigError, match=r"preset: name must be one of \['kinect_v2', 'o3d303', 'xtion2'\] .*"
                                          r"got 'kinect_v3'"):
        load_preset("kinect_v3")


def test_unreadable_preset_names_the_file(tmp_path):
    path = tmp_path / "missing.toml"
    with pytest.raises(ConfigError, match=re.escape(str(path)) + r": cannot read the preset file \(No such file"):
        load_preset(path)


def test_toml_syntax_error_names_file_and_line(tmp_path):
    path = write_variant(tmp_path, "width = 512", "width = 512 px")
    line = KINECT_TEXT.splitlines().index("width = 512                   # Tab. 4.1") + 1
    with pytest.raises(ConfigError, match=re.escape(str(path)) + rf": invalid TOML: .*line {line}\b"):
        load_preset(str(path))


@pytest.mark.parametrize("factor", [0.0625, 0.25, 0.5, 2.0])
def test_scaled_keeps_the_field_of_view(factor):
    sensor = load_preset("kinect_v2")
    scaled = sensor.scaled(factor)
    cam, new = sensor.camera, scaled.camera
    assert new.width == int(math.floor(cam.width * factor + 0.5))
    assert new.height == int(math.floor(cam.height * factor + 0.5))
    # The image edges (u = -1/2 and u = W - 1/2) see the same angles before and after.
    for (c, f, n), (c2, f2, n2) in (((cam.cx, cam.fx, cam.width), (new.cx, new.fx, new.width)),
                                    ((cam.cy, cam.fy, cam.height), (new.cy, new.fy, new.height))):
        assert math.isclose((-0.5 - c) / f, (-0.5 - c2) / f2, rel_tol=1e-12)
        assert math.isclose((n - 0.5 - c) / f, (n2 - 0.5 - c2) / f2, rel_tol=1e-12)
    assert (new.k1, new.k2, new.k3) == (cam.k1, cam.k2, cam.k3)
    assert scaled.readout == sensor.readout and scaled.leds == sensor.leds
    assert sensor.scaled(1.0) is sensor


def test_resized_to_another_aspect_scales_each_axis():
    """128 x 128 from 512 x 424: s_x = 1/4, s_y = 128/424; a pixel's ray through its centre keeps its angle
    where the centre lands on the same point of the sensor (the image's centre and corners)."""
    sensor = load_preset("kinect_v2")
    cam, new = sensor.camera, sensor.resized(128, 128).camera
    assert (new.width, new.height) == (128, 128)
    assert math.isclose(new.fx, cam.fx / 4) and math.isclose(new.fy, cam.fy * 128 / 424)
    assert math.isclose((new.cy + 0.5) / 128, (cam.cy + 0.5) / 424)
    with pytest.raises(ConfigError, match=r"Sensor\.resized: width must be an integer >= 1, got 0"):
        sensor.resized(0, 10)
    with pytest.raises(ConfigError, match=r"Sensor\.scaled: factor must be a finite number > 0, got -1"):
        sensor.scaled(-1)


@pytest.mark.parametrize("name", ["Kinect_V2", "KINECT-V2", "kinect v2", "O3D303"])
def test_preset_names_ignore_case_and_separators(name):
    assert load_preset(name).name == load_preset(name.lower().replace("-", "_").replace(" ", "_")).name


def test_a_misspelt_preset_gets_a_did_you_mean():
    with pytest.raises(ConfigError, match=r"got 'kinect_v3' \(did you mean 'kinect_v2'\?\)"):
        load_preset("kinect_v3")
    with pytest.raises(ConfigError, match=r"got 'xtoin2' \(did you mean 'xtion2'\?\)"):
        load_preset("xtoin2")
