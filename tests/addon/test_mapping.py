"""addon/mapping.py: Blender ↔ tofcore conversions, tested without Blender.

The module is loaded by file path, so neither bpy nor the add-on package
(whose ``__init__`` imports bpy) is needed: these tests also run on Python
3.13 / NumPy 2 (``make test-numpy2``).
"""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

import tofcore

_PATH = Path(__file__).resolve().parents[2] / "addon" / "mapping.py"
_spec = importlib.util.spec_from_file_location("tof_addon_mapping", _PATH)
mapping = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(mapping)


# --------------------------------------------------------------------------- colours
def test_luminance_uses_rec709_weights_and_ignores_alpha():
    assert mapping.luminance((1.0, 0.0, 0.0)) == pytest.approx(0.2126)
    assert mapping.luminance((0.0, 1.0, 0.0, 0.3)) == pytest.approx(0.7152)
    assert mapping.luminance((0.0, 0.0, 1.0)) == pytest.approx(0.0722)
    image = np.ones((2, 3, 4), np.float32) * 0.5
    assert mapping.luminance(image).shape == (2, 3)
    np.testing.assert_allclose(mapping.luminance(image), 0.5, rtol=1e-6)
    with pytest.raises(ValueError, match="3 or 4 channels"):
        mapping.luminance((1.0, 2.0))


def test_reflectance_from_base_color_is_clipped_luminance():
    assert mapping.reflectance_from_base_color((0.8, 0.8, 0.8, 1.0)) == pytest.approx(0.8)
    assert mapping.reflectance_from_base_color((3.0, 3.0, 3.0)) == 1.0
    assert mapping.reflectance_from_base_color((-1.0, 0.0, 0.0)) == 0.0


def test_srgb_decoding_matches_the_standard():
    np.testing.assert_allclose(mapping.srgb_to_linear([0.0, 0.04045, 0.5, 1.0]),
                               [0.0, 0.04045 / 12.92, 0.2140411, 1.0], rtol=1e-5, atol=1e-7)


def test_image_rows_are_flipped_to_top_down():
    # Blender's pixels: row 0 is the bottom. 2 × 3 image, one channel: bottom row 0, 1, 2; top row 3, 4, 5.
    flat = np.arange(6, dtype=np.float32)
    out = mapping.image_rows_top_down(flat, width=3, height=2, channels=1)
    np.testing.assert_array_equal(out[..., 0], [[3, 4, 5], [0, 1, 2]])


# --------------------------------------------------------------------------- roughness
@pytest.mark.parametrize("r, sigma", [(0.0, 0.0), (0.5, 0.25 / math.sqrt(2)), (1.0, 1 / math.sqrt(2)),
                                      (2.0, 1 / math.sqrt(2)), (-1.0, 0.0)])
def test_sigma_from_blender_roughness(r, sigma):
    assert mapping.sigma_from_blender_roughness(r) == pytest.approx(sigma)


def test_roughness_conversion_round_trips_and_stays_in_tofcore_range():
    r = np.linspace(0.0, 1.0, 101)
    sigma = mapping.sigma_from_blender_roughness(r)
    assert sigma.dtype == np.float32 and sigma.max() <= mapping.SIGMA_MAX
    np.testing.assert_allclose(mapping.blender_roughness_from_sigma(sigma), r, atol=1e-6)


# --------------------------------------------------------------------------- conductors
@pytest.mark.parametrize("f0, ior", [(0.9, 1.5), (0.6, 0.2), (0.3, 2.5), (0.95, 1.0)])
def test_extinction_reproduces_f0(f0, ior):
    k = mapping.extinction_from_f0(f0, ior)
    assert mapping.f0_from_extinction(ior, k) == pytest.approx(f0, abs=1e-9)


def test_extinction_clips_unreachable_f0():
    # F0 below the dielectric's own ((η−1)/(η+1))² needs k = 0; F0 → 1 is capped.
    assert mapping.extinction_from_f0(0.0, 1.5) == pytest.approx(0.0, abs=1e-6)
    assert mapping.extinction_from_f0(1.0, 1.5) == pytest.approx(mapping.extinction_from_f0(mapping.F0_MAX, 1.5))


# --------------------------------------------------------------------------- materials
def test_material_fields_from_principled_inputs():
    fields = mapping.material_fields(base_color=(0.5, 0.2, 0.1, 1.0), roughness=0.6, metallic=0.0, ior=1.45)
    assert fields["reflectance"] == pytest.approx(0.2126 * 0.5 + 0.7152 * 0.2 + 0.0722 * 0.1)
    assert fields["roughness"] == pytest.approx(0.36 / math.sqrt(2))
    assert fields["metallic"] == 0.0 and fields["ior"] == pytest.approx(1.45)
    assert fields["extinction"] == 0.0                       # dielectric
    tofcore.Material(name="check", **fields)                 # valid for tofcore


def test_metal_gets_extinction_from_its_base_color():
    fields = mapping.material_fields(base_color=(0.9, 0.9, 0.9), roughness=0.2, metallic=1.0, ior=1.5)
    assert fields["extinction"] > 0
    assert mapping.f0_from_extinction(fields["ior"], fields["extinction"]) == pytest.approx(0.9, abs=1e-6)
    tofcore.Material(name="metal", **fields)


def test_ir_override_wins():
    fields = mapping.material_fields(base_color=(0.05, 0.05, 0.05), roughness=1.0, metallic=1.0, ior=1.5,
                                     override_reflectance=0.7, override_roughness=0.05, override_extinction=4.2)
    assert fields["reflectance"] == 0.7
    assert fields["roughness"] == 0.05
    assert fields["extinction"] == 4.2


def test_dielectric_ignores_extinction_override_and_ior_is_clipped():
    fields = mapping.material_fields(metallic=0.0, ior=0.5, override_extinction=4.2)
    assert fields["extinction"] == 0.0
    assert fields["ior"] == 1.0


# --------------------------------------------------------------------------- camera
def _project_blender_view_plane(settings, points_cv):
    """Blender's view plane (BKE_camera_params_compute_viewplane), written out independently.

    Returns pixel coordinates in the OpenCV convention for points in the OpenCV sensor frame.
    """
    w, h = settings["resolution_x"], settings["resolution_y"]
    aspx, aspy = settings["pixel_aspect_x"], settings["pixel_aspect_y"]
    ycor = aspy / aspx
    fit = settings["sensor_fit"]
    if fit == "AUTO":
        fit = "HORIZONTAL" if aspx * w >= aspy * h else "VERTICAL"
    sensor = settings["sensor_height_mm"] if settings["sensor_fit"] == "VERTICAL" else settings["sensor_width_mm"]
    viewfac = w if fit == "HORIZONTAL" else ycor * h
    pixsize = sensor / settings["lens_mm"] / viewfac       # view-plane units per pixel at distance 1
    xmin = (-0.5 * w + settings["shift_x"] * viewfac) * pixsize
    xmax = (0.5 * w + settings["shift_x"] * viewfac) * pixsize
    ymin = (-0.5 * ycor * h + settings["shift_y"] * viewfac) * pixsize
    ymax = (0.5 * ycor * h + settings["shift_y"] * viewfac) * pixsize
    x_b = points_cv[:, 0] / points_cv[:, 2]                # Blender camera: x right, y up, looks down -z
    y_b = -points_cv[:, 1] / points_cv[:, 2]
    nx = (x_b - xmin) / (xmax - xmin)
    ny = (y_b - ymin) / (ymax - ymin)
    return np.stack([nx * w - 0.5, (1 - ny) * h - 0.5], axis=1)


@pytest.mark.parametrize("preset", tofcore.list_presets())
def test_blender_camera_reproduces_preset_intrinsics(preset):
    cam = tofcore.load_preset(preset).camera
    settings = mapping.blender_camera_from_intrinsics(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    assert settings["pixel_aspect_x"] >= 1 and settings["pixel_aspect_y"] >= 1
    assert min(settings["pixel_aspect_x"], settings["pixel_aspect_y"]) == 1
    back = mapping.intrinsics_from_blender_camera(**{k: v for k, v in settings.items()})
    for key in ("width", "height", "fx", "fy", "cx", "cy"):
        assert back[key] == pytest.approx(getattr(cam, key), rel=1e-12, abs=1e-9), key
    pinhole = tofcore.Camera(width=cam.width, height=cam.height, fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy)
    rng = np.random.default_rng(1)
    points = np.column_stack([rng.uniform(-1, 1, 200), rng.uniform(-1, 1, 200), rng.uniform(0.5, 5, 200)])
    np.testing.assert_allclose(_project_blender_view_plane(settings, points), pinhole.project(points), atol=1e-9)


@pytest.mark.parametrize("fit, size", [("AUTO", (300, 500)), ("AUTO", (640, 200)), ("VERTICAL", (400, 300)),
                                       ("HORIZONTAL", (123, 456))])
def test_intrinsics_of_any_sensor_fit_match_blenders_view_plane(fit, size):
    settings = {"lens_mm": 27.0, "sensor_width_mm": 30.0, "sensor_height_mm": 21.0, "sensor_fit": fit,
                "shift_x": 0.07, "shift_y": -0.11, "resolution_x": size[0], "resolution_y": size[1],
                "pixel_aspect_x": 1.0, "pixel_aspect_y": 1.7}
    k = mapping.intrinsics_from_blender_camera(**settings)
    pinhole = tofcore.Camera(width=k["width"], height=k["height"], fx=k["fx"], fy=k["fy"], cx=k["cx"], cy=k["cy"])
    rng = np.random.default_rng(2)
    points = np.column_stack([rng.uniform(-1, 1, 100), rng.uniform(-1, 1, 100), rng.uniform(0.5, 5, 100)])
    np.testing.assert_allclose(_project_blender_view_plane(settings, points), pinhole.project(points), atol=1e-9)


def test_resolution_percentage_scales_the_image():
    k = mapping.intrinsics_from_blender_camera(lens_mm=50, sensor_width_mm=36, resolution_x=1000, resolution_y=500,
                                               resolution_percentage=50)
    assert (k["width"], k["height"]) == (500, 250)
    assert k["fx"] == pytest.approx(50 / 36 * 500)
    assert (k["cx"], k["cy"]) == (249.5, 124.5)


def test_camera_errors_name_the_value():
    with pytest.raises(ValueError, match="sensor_fit must be one of"):
        mapping.intrinsics_from_blender_camera(lens_mm=50, sensor_width_mm=36, sensor_fit="DIAGONAL",
                                               resolution_x=10, resolution_y=10)
    with pytest.raises(ValueError, match="fx and fy must be > 0"):
        mapping.blender_camera_from_intrinsics(10, 10, 0.0, 5.0, 5.0, 5.0)


def test_coat_weight_and_roughness_map_to_the_clear_coat():
    """Blender's Coat Weight → coat (clipped to [0, 1]); Coat Roughness r → σ = r² / √2, as Roughness; no coat by
    default."""
    plain = mapping.material_fields()
    assert plain["coat"] == 0.0
    assert plain["coat_roughness"] == pytest.approx(mapping.BLENDER_DEFAULT_COAT_ROUGHNESS ** 2 / math.sqrt(2))
    fields = mapping.material_fields(coat=1.7, coat_roughness=0.4)
    assert fields["coat"] == 1.0 and fields["coat_roughness"] == pytest.approx(0.16 / math.sqrt(2))
    tofcore.Material(name="lacquer", **fields)
