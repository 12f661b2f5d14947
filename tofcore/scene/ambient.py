"""Ambient light: unmodulated radiance arriving from outside the scene.

Ambient light carries no modulation, so it adds the same charge to every
bucket (SPEC §1, thesis §5.1.3, §6.4); the tracer keeps it in sums of its own,
apart from the LED signal.

=============================  ==========  =======  ===================================================
name                           unit        default  meaning
=============================  ==========  =======  ===================================================
``radiance_w_m2_sr``           W/(m² sr)   0.0      constant background radiance in every direction
``environment``                W/(m² sr)   None     equirectangular map (H, W), row 0 = zenith (+Z)
``environment_strength``       1           1.0      scale of the map
=============================  ==========  =======  ===================================================

The map uses Blender's equirectangular mapping (world frame, Z up), so a
Blender world texture exports without conversion:
:math:`u = \\operatorname{atan2}(d_y, -d_x) / 2\\pi + 1/2`,
:math:`v = \\operatorname{atan2}(d_z, \\sqrt{d_x^2 + d_y^2}) / \\pi + 1/2`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..backend import namespace
from ..errors import ConfigError
from ..limits import MAX_MAGNITUDE
from .material import Texture


@dataclass(frozen=True, kw_only=True, eq=False)
class Ambient:
    """Background radiance around the scene; see the module docstring."""

    radiance_w_m2_sr: float = 0.0
    environment: Texture | np.ndarray | None = None
    environment_strength: float = 1.0

    def __post_init__(self) -> None:
        for key in ("radiance_w_m2_sr", "environment_strength"):
            value = getattr(self, key)
            if not isinstance(value, (int, float, np.number)) or not 0 <= value <= MAX_MAGNITUDE:  # NaN fails
                raise ConfigError(f"Ambient: {key} must be a finite number >= 0, at most {MAX_MAGNITUDE:g}, "
                                  f"got {value!r}")
        env = self.environment
        if env is not None:
            if not isinstance(env, Texture):
                env = Texture(np.asarray(env), name="environment")
            if env.channels != 1:
                raise ConfigError(f"Ambient: environment must be a one-channel (H, W) radiance map, "
                                  f"got shape {env.data.shape}")
            if (env.data < 0).any():
                raise ConfigError("Ambient: environment radiance must be >= 0, got a negative value")
            object.__setattr__(self, "environment", env)

    @property
    def is_black(self) -> bool:
        """True when no ambient light reaches the scene (the tracer then skips ambient work)."""
        env_black = self.environment is None or self.environment_strength == 0 or not self.environment.data.any()
        return self.radiance_w_m2_sr == 0 and env_black

    def radiance(self, directions: np.ndarray) -> np.ndarray:
        """Radiance (W m⁻² sr⁻¹) arriving from world directions (N, 3), i.e. seen looking along them."""
        out = namespace(directions).full(len(directions), float(self.radiance_w_m2_sr))
        if self.environment is not None and self.environment_strength > 0:
            d = directions.astype(np.float64)
            u = np.arctan2(d[:, 1], -d[:, 0]) / (2 * np.pi) + 0.5
            v = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])) / np.pi + 0.5
            # Clamp v so the poles do not wrap around to the opposite pole.
            h = self.environment.data.shape[0]
            v = np.clip(v, 0.5 / h, 1.0 - 0.5 / h)
            out += self.environment_strength * self.environment.sample(np.stack([u, v], axis=1))
        return out
