"""Blender ↔ tofcore conversions that need no Blender: materials, world light, camera intrinsics.

Pure functions over numbers and NumPy arrays, so that they can be tested (and
reused by the batch tools) without ``bpy``. :mod:`addon.export` reads the
values out of Blender and calls these. The module imports nothing from the
add-on package, so it can also be loaded on its own by file path.

Materials: Principled BSDF → :class:`tofcore.Material`
--------------------------------------------------------

Blender's inputs describe *visible* light; the simulator needs the *near
infrared* (about 850 nm), where paints, fabrics and plants reflect very
differently (green leaves ≈ 0.5, black plastics anywhere from 0.05 to 0.6).
The mapping below therefore only gives defaults; every material has an IR
override (``material.tof``, the add-on's "Near-IR" panel) that wins.

===========================  =========================  ===========================================================
Blender input                tofcore field              mapping (without override)
===========================  =========================  ===========================================================
Base Color (linear RGB)      ``reflectance``            luminance Y = 0.2126 R + 0.7152 G + 0.0722 B, clipped to
                                                        [0, 1]
Base Color image texture     ``reflectance_texture``    the same luminance per texel (8-bit sRGB images decoded
                                                        to linear first)
Roughness r ∈ [0, 1]         ``roughness`` (radians)    σ = r² / √2 (see below)
Roughness image texture      ``roughness_texture``      the same per texel, of its luminance (a colour linked to a
                                                        number input, as Blender's shading converts it)
Metallic                     ``metallic``               unchanged
Metallic image texture       ``metallic_texture``       its luminance per texel
IOR                          ``ior``                    unchanged, clipped to [1, 10]; also the conductor's real
                                                        part η
Base Color (metals only)     ``extinction``             k from F0 = Y with η = IOR:
                                                        k² = (F0 (η+1)² − (η−1)²) / (1 − F0);
                                                        0 when Metallic = 0
Normal → Normal Map →        ``normal_texture``         tangent-space RGB in [0, 1], unchanged (strength 1)
Image Texture
Coat Weight (Clearcoat)      ``coat``                   unchanged, clipped to [0, 1] (the coat's IOR: tofcore's 1.5,
                                                        Blender's default)
Coat Roughness               ``coat_roughness``         σ = r² / √2, as Roughness
===========================  =========================  ===========================================================

IR override (``material.tof.use_override``): ``reflectance`` (0..1) and
``roughness`` (σ in radians) replace the values above *and* drop the
corresponding textures; ``extinction`` replaces k for metals.

Roughness. Blender's Principled BSDF is GGX with α_GGX = r² (Blender
squares the slider value, "perceptual roughness"). tofcore's σ is the RMS
slope deviation of a Beckmann/Oren–Nayar surface, with Beckmann α_B = √2 σ.
Matching the two distributions by their width, α_B ≈ α_GGX (the common
approximation; the GGX tail is longer), gives σ = r² / √2: r = 1 →
σ = 0.707 rad (a very rough surface), r = 0.5 → 0.177 rad.

Extinction. Blender's metals reflect F0 = Base Color at normal incidence
(the Schlick/F82 model); a conductor with index η and extinction k has
F0 = ((η − 1)² + k²) / ((η + 1)² + k²), solved for k with η = IOR. F0 is
clipped to [((η − 1)/(η + 1))², 0.99] so k stays real and finite.

World: Background → :class:`tofcore.Ambient`
-----------------------------------------------

===============================================  ==============================================================
Blender                                          tofcore
===============================================  ==============================================================
Background Color × Strength (or world colour)    ``radiance_w_m2_sr`` = luminance × strength × ``ambient_scale``
Environment Texture → Background Color           ``environment`` = luminance map (row 0 = zenith),
                                                 ``environment_strength`` = strength × ``ambient_scale``
no world, nothing on the World Output, black     None (no ambient light)
===============================================  ==============================================================

A world colour is a visible-light *display* value, not a near-IR radiance in
W m⁻² sr⁻¹: ``ambient_scale`` (default 1.0, i.e. luminance 1 ↦ 1 W m⁻² sr⁻¹)
converts it. Pick it from the background radiance the sensor sees inside its
band-pass filter for the scene you have in mind (dark lab, office, daylight).

Camera: intrinsics ↔ Blender camera
-----------------------------------

OpenCV pixel coordinates put the centre of column 0 at u = 0 (the image spans
[−½, W − ½]); Blender's image plane spans [0, W] with pixel centres at i + ½.
Blender's view plane (``BKE_camera_params_compute_viewplane``) at unit
distance has width W and height ρ H in units of ``sensor / (lens · F)``,
where ρ = aspect_y / aspect_x (pixel aspect) and the fit length F is W for a
horizontal sensor fit and ρ H for a vertical one (``AUTO`` picks horizontal
when aspect_x W ≥ aspect_y H, and always uses the sensor *width*); shifts
move the plane by ``shift · F``. A point (X, Y, Z) of the OpenCV sensor frame
(Z > 0) then lands on

.. math::

    u = \\frac{f F}{s} \\frac{X}{Z} + \\frac{W - 1}{2} - \\mathrm{shift}_x F, \\qquad
    v = \\frac{f F}{s \\rho} \\frac{Y}{Z} + \\frac{H - 1}{2} + \\frac{\\mathrm{shift}_y F}{\\rho}

(f = lens; s = the sensor size Blender uses: ``sensor_height`` for a
VERTICAL fit, else ``sensor_width``; both in mm), so

.. math::

    f_x = \\frac{f F}{s}, \\quad f_y = \\frac{f_x}{\\rho}, \\quad
    c_x = \\frac{W - 1}{2} - \\mathrm{shift}_x F, \\quad
    c_y = \\frac{H - 1}{2} + \\frac{\\mathrm{shift}_y F}{\\rho}.

:func:`blender_camera_from_intrinsics` uses the horizontal fit (F = W) and
puts the pixel aspect on the smaller focal length (Blender's aspects are
≥ 1): ρ = f_x / f_y. Lens distortion has no Blender counterpart.
"""

from __future__ import annotations

import math

import numpy as np

#: Rec. 709 / sRGB luminance weights of linear R, G, B (Blender's default scene-linear space).
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)

#: Blender's defaults for a face without material (grey 0.8, roughness 0.5, IOR 1.5).
BLENDER_DEFAULT_BASE_COLOR = (0.8, 0.8, 0.8)
BLENDER_DEFAULT_ROUGHNESS = 0.5
BLENDER_DEFAULT_IOR = 1.5
BLENDER_DEFAULT_COAT_ROUGHNESS = 0.03
"""Blender 4's Principled BSDF default Coat Roughness."""

#: Limits of tofcore.Material's fields (see tofcore/scene/material.py).
SIGMA_MAX = math.pi / 2
IOR_RANGE = (1.0, 10.0)
EXTINCTION_MAX = 100.0
#: Largest F0 used to derive a conductor's extinction (k grows without bound as F0 → 1).
F0_MAX = 0.99

SENSOR_FITS = ("AUTO", "HORIZONTAL", "VERTICAL")


# --------------------------------------------------------------------------- colours
def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """Decode sRGB-encoded values in [0, 1] to linear (IEC 61966-2-1), float32."""
    c = np.asarray(values, dtype=np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4).astype(np.float32)


def luminance(rgb) -> np.ndarray | float:
    """Luminance Y of linear RGB(A) values, ``(..., 3|4) → (...)``; alpha is ignored.

    A plain sequence of 3 or 4 numbers gives a float.
    """
    a = np.asarray(rgb, dtype=np.float32)
    if a.shape[-1] not in (3, 4):
        raise ValueError(f"luminance: rgb must have 3 or 4 channels in the last axis, got shape {a.shape}")
    y = a[..., 0] * LUMINANCE_WEIGHTS[0] + a[..., 1] * LUMINANCE_WEIGHTS[1] + a[..., 2] * LUMINANCE_WEIGHTS[2]
    return float(y) if y.ndim == 0 else y.astype(np.float32)


def reflectance_from_base_color(rgb) -> np.ndarray | float:
    """Default near-IR reflectance from a linear Base Color: its luminance, clipped to [0, 1]."""
    y = luminance(rgb)
    return float(min(max(y, 0.0), 1.0)) if isinstance(y, float) else np.clip(y, 0.0, 1.0).astype(np.float32)


# --------------------------------------------------------------------------- roughness
def sigma_from_blender_roughness(roughness) -> np.ndarray | float:
    """tofcore roughness σ (radians) from Blender's Principled roughness r ∈ [0, 1]: σ = r² / √2.

    Values outside [0, 1] are clipped first (Blender clips them too).
    """
    r = np.clip(np.asarray(roughness, dtype=np.float64), 0.0, 1.0)
    sigma = r * r / math.sqrt(2.0)
    return float(sigma) if sigma.ndim == 0 else sigma.astype(np.float32)


def blender_roughness_from_sigma(sigma) -> np.ndarray | float:
    """Inverse of :func:`sigma_from_blender_roughness`: r = √(√2 σ), clipped to [0, 1]."""
    s = np.clip(np.asarray(sigma, dtype=np.float64), 0.0, None)
    r = np.clip(np.sqrt(math.sqrt(2.0) * s), 0.0, 1.0)
    return float(r) if r.ndim == 0 else r.astype(np.float32)


# --------------------------------------------------------------------------- conductors
def extinction_from_f0(f0: float, ior: float) -> float:
    """Conductor extinction k giving normal-incidence reflectance ``f0`` with real index ``ior``.

    Solves F0 = ((η − 1)² + k²) / ((η + 1)² + k²) for k; F0 is clipped to
    [((η − 1)/(η + 1))², :data:`F0_MAX`] so that k is real and finite.
    """
    eta = float(ior)
    f0_min = ((eta - 1.0) / (eta + 1.0)) ** 2
    f0 = min(max(float(f0), f0_min), F0_MAX)
    k2 = (f0 * (eta + 1.0) ** 2 - (eta - 1.0) ** 2) / (1.0 - f0)
    return float(min(math.sqrt(max(k2, 0.0)), EXTINCTION_MAX))


def f0_from_extinction(ior: float, extinction: float) -> float:
    """Normal-incidence reflectance of a conductor, ((η − 1)² + k²) / ((η + 1)² + k²)."""
    eta, k = float(ior), float(extinction)
    return ((eta - 1.0) ** 2 + k * k) / ((eta + 1.0) ** 2 + k * k)


# --------------------------------------------------------------------------- materials
def material_fields(*, base_color=BLENDER_DEFAULT_BASE_COLOR, roughness: float = BLENDER_DEFAULT_ROUGHNESS,
                    metallic: float = 0.0, ior: float = BLENDER_DEFAULT_IOR, coat: float = 0.0,
                    coat_roughness: float = BLENDER_DEFAULT_COAT_ROUGHNESS, override_reflectance: float | None = None, override_roughness: float | None = None,
                    override_extinction: float | None = None) -> dict:
    """Scalar :class:`tofcore.Material` keyword arguments from Principled BSDF inputs (module table).

    Parameters
    ----------
    base_color : linear RGB(A) of the "Base Color" input.
    roughness : Blender roughness r in [0, 1].
    metallic : "Metallic" in [0, 1].
    ior : "IOR" (≥ 1 for dielectrics; the conductor's real part η).
    coat, coat_roughness : "Coat Weight" in [0, 1] and "Coat Roughness" r in [0, 1] (Blender 3: "Clearcoat",
        "Clearcoat Roughness").
    override_reflectance, override_roughness, override_extinction :
        The material's IR override (reflectance in [0, 1], σ in radians,
        extinction k); None keeps the derived value.

    Returns
    -------
    dict with ``reflectance``, ``roughness``, ``metallic``, ``ior``, ``extinction``, ``coat``, ``coat_roughness``.
    """
    metallic = float(min(max(float(metallic), 0.0), 1.0))
    ior = float(min(max(float(ior), IOR_RANGE[0]), IOR_RANGE[1]))
    reflectance = reflectance_from_base_color(base_color)
    sigma = sigma_from_blender_roughness(roughness)
    extinction = extinction_from_f0(reflectance, ior) if metallic > 0.0 else 0.0
    if override_reflectance is not None:
        reflectance = float(override_reflectance)
    if override_roughness is not None:
        sigma = float(override_roughness)
    if override_extinction is not None and metallic > 0.0:
        extinction = float(override_extinction)
    return {"reflectance": reflectance, "roughness": sigma, "metallic": metallic, "ior": ior,
            "extinction": extinction, "coat": float(min(max(float(coat), 0.0), 1.0)),
            "coat_roughness": float(sigma_from_blender_roughness(coat_roughness))}


# --------------------------------------------------------------------------- images
def image_rows_top_down(pixels: np.ndarray, width: int, height: int, channels: int) -> np.ndarray:
    """Blender's flat ``image.pixels`` (rows bottom-up) → (H, W, C) float32 with row 0 at the top."""
    data = np.asarray(pixels, dtype=np.float32).reshape(height, width, channels)
    return np.ascontiguousarray(data[::-1])


# --------------------------------------------------------------------------- camera
def blender_camera_from_intrinsics(width: int, height: int, fx: float, fy: float, cx: float, cy: float, *,
                                   sensor_width_mm: float = 36.0) -> dict:
    """Blender camera and render settings that reproduce pinhole intrinsics (OpenCV convention).

    Parameters
    ----------
    width, height : image size, pixels.
    fx, fy : focal lengths, pixels.
    cx, cy : principal point, pixels; the centre of column 0 is u = 0.
    sensor_width_mm : the Blender sensor width to use (any value works; 36 mm is Blender's default).

    Returns
    -------
    dict with ``lens_mm``, ``sensor_width_mm``, ``sensor_height_mm``, ``sensor_fit`` ("HORIZONTAL"),
    ``shift_x``, ``shift_y``, ``resolution_x``, ``resolution_y``, ``pixel_aspect_x``,
    ``pixel_aspect_y`` (render resolution at 100 %). See the module docstring for the formulas.
    """
    width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise ValueError(f"blender_camera_from_intrinsics: width and height must be > 0, got {width} x {height}")
    if not (fx > 0 and fy > 0):
        raise ValueError(f"blender_camera_from_intrinsics: fx and fy must be > 0, got {fx!r}, {fy!r}")
    if fx >= fy:
        aspect_x, aspect_y = 1.0, fx / fy
    else:
        aspect_x, aspect_y = fy / fx, 1.0
    rho = aspect_y / aspect_x                       # = fx / fy
    fit_length = float(width)                       # horizontal fit
    lens_mm = fx * sensor_width_mm / fit_length
    return {
        "lens_mm": lens_mm,
        "sensor_width_mm": float(sensor_width_mm),
        "sensor_height_mm": float(sensor_width_mm) * rho * height / width,
        "sensor_fit": "HORIZONTAL",
        "shift_x": ((width - 1) / 2.0 - cx) / fit_length,
        "shift_y": (cy - (height - 1) / 2.0) * rho / fit_length,
        "resolution_x": width,
        "resolution_y": height,
        "pixel_aspect_x": aspect_x,
        "pixel_aspect_y": aspect_y,
    }


def intrinsics_from_blender_camera(*, lens_mm: float, sensor_width_mm: float, sensor_height_mm: float = 24.0,
                                   sensor_fit: str = "AUTO", shift_x: float = 0.0, shift_y: float = 0.0,
                                   resolution_x: int, resolution_y: int, pixel_aspect_x: float = 1.0,
                                   pixel_aspect_y: float = 1.0, resolution_percentage: float = 100.0) -> dict:
    """Pinhole intrinsics (OpenCV convention) of a Blender perspective camera.

    Accepts every sensor fit; the image size is the render resolution scaled
    by ``resolution_percentage`` (rounded down, as Blender does).

    Returns
    -------
    dict with ``width``, ``height``, ``fx``, ``fy``, ``cx``, ``cy``.
    """
    if sensor_fit not in SENSOR_FITS:
        raise ValueError(f"intrinsics_from_blender_camera: sensor_fit must be one of {list(SENSOR_FITS)}, "
                         f"got {sensor_fit!r}")
    width = int(resolution_x * resolution_percentage / 100.0)
    height = int(resolution_y * resolution_percentage / 100.0)
    if width <= 0 or height <= 0:
        raise ValueError(f"intrinsics_from_blender_camera: the render resolution must be > 0, "
                         f"got {width} x {height}")
    rho = pixel_aspect_y / pixel_aspect_x
    fit = sensor_fit
    if fit == "AUTO":
        fit = "HORIZONTAL" if pixel_aspect_x * width >= pixel_aspect_y * height else "VERTICAL"
    sensor_mm = sensor_height_mm if sensor_fit == "VERTICAL" else sensor_width_mm
    fit_length = float(width) if fit == "HORIZONTAL" else rho * height
    fx = lens_mm * fit_length / sensor_mm
    return {
        "width": width,
        "height": height,
        "fx": fx,
        "fy": fx / rho,
        "cx": (width - 1) / 2.0 - shift_x * fit_length,
        "cy": (height - 1) / 2.0 + shift_y * fit_length / rho,
    }
