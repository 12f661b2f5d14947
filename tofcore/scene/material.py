"""Surface materials in the near infrared, and the textures that vary them.

A :class:`Material` holds the parameters of the reflection model of
:mod:`tofcore.scene.bsdf` (SPEC §2, thesis §2.1.4 and §5.1.2):

==================  ======  ============  =====================================================
name                unit    default       meaning
==================  ======  ============  =====================================================
``reflectance``     1       0.5           near-IR diffuse albedo ρ of the Oren–Nayar lobe, [0, 1]
``roughness``       rad     0.5           σ, slope deviation of the microfacets (Oren–Nayar σ,
                                          Beckmann α = √2 σ); 0 = smooth (mirror specular lobe)
``metallic``        1       0.0           blend between dielectric (0) and conductor (1)
``ior``             1       1.52          η: dielectric index of refraction (≥ 1), conductor real part
                                          (metals may have η < 1, e.g. silver ≈ 0.15 in the near IR)
``extinction``      1       0.0           k: conductor absorption coefficient (metals only)
``coat``            1       0.0           weight of a clear coat (η = 1.5) over the surface; 0 = none
``coat_roughness``  rad     0.05          σ of the coat's microfacets (Beckmann α = √2 σ); 0 = mirror
==================  ======  ============  =====================================================

Visible colour is not near-infrared reflectance: ``reflectance`` is the IR
value. It is the albedo of the body *under* the dielectric interface: the
diffuse lobe is weighted by (1 − F(θ_i))(1 − F(θ_o)) (see :mod:`tofcore.scene.bsdf`),
so with η = 1.52 a surface of ``reflectance`` ρ returns about 0.87 ρ diffusely
at normal incidence, plus the specular lobe. With η = 1 there is no Fresnel
term: roughness 0 is then an exact Lambertian reflector ρ/π, but the
Oren–Nayar approximation alone exceeds an albedo of 1 by up to ~5 % at
grazing angles for ρ = 1 (measured in ``tests/tofcore/test_bsdf.py``). Textures (:class:`Texture`) may replace ``reflectance``, ``roughness``
and ``metallic`` per point and perturb the shading normal (``normal_texture``,
tangent-space RGB in [0, 1] as most normal maps are stored).

Image convention (all of tofcore): ``data[row, col]``, row 0 is the **top** of
the image (v = 1), column 0 its left edge (u = 0); UV (0, 0) is the bottom-left
corner as in Blender. Lookups are bilinear with repeat wrapping.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from ..backend import device_copy, namespace
from ..errors import ConfigError


@dataclass(frozen=True, eq=False)
class Texture:
    """An image sampled through UV coordinates.

    Parameters
    ----------
    data : (H, W) or (H, W, C) array, stored as float32, row 0 at the top.
    name : where the image came from (file or Blender image), for error messages.
    """

    data: np.ndarray
    name: str = "texture"

    def __post_init__(self) -> None:
        data = np.asarray(self.data, dtype=np.float32)
        if data.ndim not in (2, 3) or data.shape[0] < 1 or data.shape[1] < 1:
            raise ConfigError(f"Texture {self.name!r}: data must be (H, W) or (H, W, C), got shape {data.shape}")
        if not np.all(np.isfinite(data)):
            raise ConfigError(f"Texture {self.name!r}: data must be finite, got a NaN or inf value")
        object.__setattr__(self, "data", data)

    @property
    def channels(self) -> int:
        return 1 if self.data.ndim == 2 else self.data.shape[2]

    def sample(self, uv: np.ndarray) -> np.ndarray:
        """Bilinear lookup with repeat wrapping.

        Parameters
        ----------
        uv : (N, 2) texture coordinates; (0, 0) bottom-left, (1, 1) top-right.

        Returns
        -------
        (N,) for a one-channel texture, else (N, C); float32.
        """
        h, w = self.data.shape[:2]
        # Texel centres sit at (i + 0.5) / w; row 0 is v = 1.
        x = uv[:, 0].astype(np.float64) * w - 0.5
        y = (1.0 - uv[:, 1].astype(np.float64)) * h - 0.5
        x0 = np.floor(x)
        y0 = np.floor(y)
        fx = (x - x0).astype(np.float32)
        fy = (y - y0).astype(np.float32)
        x0 = x0.astype(np.int64) % w
        y0 = y0.astype(np.int64) % h
        x1 = (x0 + 1) % w
        y1 = (y0 + 1) % h
        d = device_copy(namespace(uv), self.data)
        if d.ndim == 3:
            fx = fx[:, None]
            fy = fy[:, None]
        top = d[y0, x0] * (1 - fx) + d[y0, x1] * fx
        bottom = d[y1, x0] * (1 - fx) + d[y1, x1] * fx
        return top * (1 - fy) + bottom * fy


@dataclass(frozen=True)
class Parameter:
    """One row of :data:`PARAMETERS`: a material parameter of the reflection model."""

    name: str
    unit: str
    default: float
    low: float
    high: float
    textured: bool  # whether a one-channel ``<name>_texture`` may replace it per point
    meaning: str


PARAMETERS = (
    Parameter("reflectance", "1", 0.5, 0.0, 1.0, True, "near-IR diffuse albedo ρ of the Oren–Nayar lobe"),
    Parameter("roughness", "rad", 0.5, 0.0, np.pi / 2, True,
              "σ, slope deviation of the microfacets (Oren–Nayar σ, Beckmann α = √2 σ); 0 = mirror"),
    Parameter("metallic", "1", 0.0, 0.0, 1.0, True, "blend between dielectric (0) and conductor (1)"),
    Parameter("ior", "1", 1.52, 0.05, 10.0, False, "η: dielectric index (≥ 1), conductor real part"),
    Parameter("extinction", "1", 0.0, 0.0, 100.0, False, "k: conductor absorption coefficient (metals only)"),
    Parameter("coat", "1", 0.0, 0.0, 1.0, False, "weight of a clear coat (η 1.5) over the surface; 0 = none"),
    Parameter("coat_roughness", "rad", 0.05, 0.0, np.pi / 2, False, "σ of the coat's microfacets; 0 = mirror"),
)
"""The material parameters, one row each: the one table the rest derives from — :class:`Material`'s
fields and checks, :data:`PARAMETER_NAMES` (the order of the tracers' per-point records: the NumPy
tracer's :class:`tofcore.scene.bsdf.SurfaceParams`, the compiled kernels' ``params`` tuple and material
columns, :mod:`tofcore.compiled.layout`), the texture slots (:data:`TEXTURE_SLOTS`) and the docs table above.
A new parameter is one row here, one field in :class:`Material` (a test checks they agree) and its use
in each tracer's formula."""

_RANGES = {p.name: (p.low, p.high) for p in PARAMETERS}


@dataclass(frozen=True, kw_only=True, eq=False)
class Material:
    """Near-IR surface material (see the module docstring for the parameter table).

    Examples
    --------
    >>> wall = Material(name="white wall", reflectance=0.8, roughness=0.5)
    >>> alu = Material(name="aluminium", metallic=1.0, ior=1.35, extinction=9.6, roughness=0.1)
    """

    name: str = "default"
    reflectance: float = PARAMETERS[0].default
    roughness: float = PARAMETERS[1].default
    metallic: float = PARAMETERS[2].default
    ior: float = PARAMETERS[3].default
    extinction: float = PARAMETERS[4].default
    coat: float = PARAMETERS[5].default
    coat_roughness: float = PARAMETERS[6].default
    reflectance_texture: Texture | None = field(default=None)
    roughness_texture: Texture | None = field(default=None)
    metallic_texture: Texture | None = field(default=None)
    normal_texture: Texture | None = field(default=None)

    def __post_init__(self) -> None:
        for key, (lo, hi) in _RANGES.items():
            value = getattr(self, key)
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.floating, np.integer)) \
                    or not np.isfinite(value) \
                    or not lo <= float(value) <= hi:
                raise ConfigError(f"Material {self.name!r}: {key} must be a number in [{lo:g}, {hi:g}], got {value!r}")
            object.__setattr__(self, key, float(value))
        if self.ior < 1.0 and self.metallic < 1.0:
            raise ConfigError(f"Material {self.name!r}: ior must be >= 1 unless metallic = 1 (a dielectric "
                              f"with η < 1 would reflect everything), got ior {self.ior!r} with metallic "
                              f"{self.metallic!r}")
        for key in TEXTURE_SLOTS[:-1]:
            tex = getattr(self, key)
            if tex is not None and (not isinstance(tex, Texture) or tex.channels != 1):
                raise ConfigError(f"Material {self.name!r}: {key} must be a one-channel Texture, got {tex!r}")
        if self.normal_texture is not None and (
                not isinstance(self.normal_texture, Texture) or self.normal_texture.channels < 3):
            raise ConfigError(f"Material {self.name!r}: normal_texture must be an RGB Texture, got {self.normal_texture!r}")

    @property
    def textures(self) -> dict[str, Texture]:
        """The textures this material uses, by field name."""
        return {f.name: getattr(self, f.name) for f in fields(self)
                if f.name.endswith("_texture") and getattr(self, f.name) is not None}

    def to_dict(self) -> dict:
        """The scalar parameters (textures are stored separately by :meth:`Scene.save`)."""
        return {"name": self.name, **{k: getattr(self, k) for k in _RANGES}}

    @classmethod
    def from_dict(cls, data: dict, where: str = "material", textures: dict[str, Texture] | None = None) -> Material:
        """Build from a plain dict, naming ``where`` and the valid keys on an unknown key."""
        valid = {"name", *_RANGES}
        unknown = set(data) - valid
        if unknown:
            raise ConfigError(f"{where}: unknown key {sorted(unknown)[0]!r}; valid keys are {sorted(valid)}")
        return cls(**data, **(textures or {}))


PARAMETER_NAMES = tuple(p.name for p in PARAMETERS)
"""The parameters in the order of the tracers' per-point records (see :data:`PARAMETERS`)."""

TEXTURE_SLOTS = tuple(f"{p.name}_texture" for p in PARAMETERS if p.textured) + ("normal_texture",)
"""A material's texture fields: one per textured parameter, then the normal map (the compiled kernels'
texture slots, in this order)."""
