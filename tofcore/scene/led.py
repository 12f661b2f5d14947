"""IR emitters of the sensor: point and Lambertian LEDs at their real offsets from the lens.

==================  ======  =========  ===========================================================
name                unit    default    meaning
==================  ======  =========  ===========================================================
``position_m``      m       (0,0,0)    position in the sensor frame (x right, y down, z forward)
``intensity_w_sr``  W/sr    1.0        radiant intensity I0 (on the axis for a Lambertian LED)
``kind``            –       "point"    ``"point"`` (isotropic) or ``"lambertian"`` (facing +z)
==================  ======  =========  ===========================================================

Both are point emitters as seen from the scene: the irradiance they cause at
a surface point is :math:`E = I(\\theta) \\cos\\theta_x / d^2` (thesis eq. 2.8)
with :math:`I(\\theta) = I_0` for a point LED and :math:`I(\\theta) = I_0
\\cos\\theta` for a Lambertian LED (eq. 2.9), θ measured from the optical axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..backend import namespace
from ..errors import ConfigError
from ..limits import MAX_MAGNITUDE
from .camera import Camera
from .sampling import sample_cosine_hemisphere

KINDS = ("point", "lambertian")


@dataclass(frozen=True, kw_only=True)
class LED:
    """One IR emitter; see the module docstring for the parameter table."""

    position_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    intensity_w_sr: float = 1.0
    kind: str = "point"

    def __post_init__(self) -> None:
        pos = np.asarray(self.position_m, dtype=np.float64)
        if pos.shape != (3,) or not np.isfinite(pos).all():
            raise ConfigError(f"LED: position_m must be three finite numbers (metres, sensor frame), "
                              f"got {self.position_m!r}")
        object.__setattr__(self, "position_m", tuple(float(x) for x in pos))
        if not isinstance(self.intensity_w_sr, (int, float, np.number)) or isinstance(self.intensity_w_sr, bool) \
                or not 0 <= self.intensity_w_sr <= MAX_MAGNITUDE:  # NaN fails too
            raise ConfigError(f"LED: intensity_w_sr must be a finite number >= 0, at most {MAX_MAGNITUDE:g} (W/sr), "
                              f"got {self.intensity_w_sr!r}")
        if self.kind not in KINDS:
            raise ConfigError(f"LED: kind must be one of {list(KINDS)}, got {self.kind!r}")

    def intensity(self, cos_axis: np.ndarray) -> np.ndarray:
        """Radiant intensity I(θ) in W/sr towards directions with cos θ = ``cos_axis`` from the +z axis.

        Notes
        -----
        Point LED: :math:`I = I_0` (eq. 2.8). Lambertian LED:
        :math:`I = I_0 \\max(0, \\cos\\theta)` (eq. 2.9); it emits nothing backwards.
        """
        if self.kind == "point":
            return namespace(cos_axis).full(np.shape(cos_axis), float(self.intensity_w_sr))
        return self.intensity_w_sr * np.maximum(cos_axis, 0.0)

    @property
    def power_w(self) -> float:
        """Radiant power Φ = ∫ I dω in W: 4π I0 (point), π I0 (Lambertian)."""
        return float(self.intensity_w_sr) * (4.0 * np.pi if self.kind == "point" else np.pi)

    def emission_pdf(self, cos_axis: np.ndarray) -> np.ndarray:
        """Solid-angle density (1/sr) of :meth:`sample_emission` towards directions with cos θ = ``cos_axis``.

        Proportional to I(θ): 1/(4π) (point), max(0, cos θ)/π (Lambertian), so I/p = Φ (:attr:`power_w`).
        """
        if self.kind == "point":
            return namespace(cos_axis).full(np.shape(cos_axis), 1.0 / (4.0 * np.pi))
        return np.maximum(cos_axis, 0.0) / np.pi

    def sample_emission(self, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
        """(N, 3) emission directions in the LED frame (+z = optical axis), distributed as I(θ) (pdf above).

        Point: uniform on the sphere, z = 1 − 2u₁, φ = 2πu₂. Lambertian: cosine-weighted about +z
        (:func:`tofcore.scene.sampling.sample_cosine_hemisphere`).
        """
        if self.kind == "lambertian":
            return sample_cosine_hemisphere(u1, u2)
        z = 1.0 - 2.0 * u1
        r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
        phi = 2.0 * np.pi * u2
        return namespace(z).stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def leds_at_pinhole(camera: Camera, leds: tuple[LED, ...] | list[LED]) -> np.ndarray:
    """(L,) bool: LED sits exactly at the centre of a pinhole lens (its first-hit shadow rays are redundant)."""
    return np.array([led.position_m == (0.0, 0.0, 0.0) for led in leds]) & (camera.aperture_radius_m == 0)
