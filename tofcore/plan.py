"""Leave out what a scene does not need: the render plan.

Before tracing, :func:`make_plan` looks at scene, sensor and settings and
records which pieces of work cannot change the output and are skipped
(DESIGN.md, "Leave out what a scene does not need"). Each skip is exact — a
test per skip shows the output is unchanged (``tests/tofcore/test_plan.py``):

=======================  =====================================================================
skip                     when
=======================  =====================================================================
``ambient``              no ambient light (``None`` or black): no environment lookups, no sums
``conductor_fresnel``    no material is metallic: the conductor Fresnel term is never evaluated
``dielectric_fresnel``   every material is fully metallic
``textures``             no material has a texture: no UV interpolation or texture lookups
``bounces``              max_depth = 1: no bounce rays, no BSDF sampling
``first_hit_shadow``     every LED sits at the centre of a pinhole lens: the camera ray itself
                         proves the first hit is lit, so its shadow rays are not traced
``scattering``           lens scattering off (model "none" or strength 0): no PSF convolution
``raw_noise``            noise model is not "raw"
``distance_noise``       noise model is not "li"
=======================  =====================================================================

The plan is printed by ``python -m tofcore render --verbose`` and stored in
every frame's ``stats["plan"]``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .scene.ambient import Ambient
from .scene.led import leds_at_pinhole
from .scene.scene import Scene


@dataclass(frozen=True)
class Plan:
    """What the render does (True) and skips (False), with the reason for each skip."""

    ambient: bool
    conductor_fresnel: bool
    dielectric_fresnel: bool
    textures: bool
    bounces: bool
    first_hit_shadow: bool
    scattering: bool
    raw_noise: bool
    distance_noise: bool
    reasons: dict[str, str]

    def as_dict(self) -> dict:
        return asdict(self)

    def describe(self) -> str:
        """One line per piece of work: done, or skipped and why."""
        lines = []
        for key, value in self.as_dict().items():
            if key == "reasons":
                continue
            lines.append(f"  {key:<20} {'on' if value else 'skipped: ' + self.reasons[key]}")
        return "plan:\n" + "\n".join(lines)


def make_plan(scene: Scene, sensor, *, max_depth: int, ambient: Ambient | None) -> Plan:
    """Decide what the render of ``scene`` with ``sensor`` can leave out."""
    metallic = np.array([m.metallic for m in scene.materials])
    textured = [m.name for m in scene.materials if m.textures]
    at_pinhole = leds_at_pinhole(sensor.camera, sensor.leds)
    scatter = sensor.scattering.model != "none" and sensor.scattering.strength > 0
    noise = sensor.noise.model
    reasons = {
        "ambient": "no ambient light",
        "conductor_fresnel": "no metallic material",
        "dielectric_fresnel": "every material is fully metallic",
        "textures": "no textured material",
        "bounces": "max_depth = 1",
        "first_hit_shadow": "every LED is at the centre of the pinhole",
        "scattering": f"lens scattering off (model {sensor.scattering.model!r}, "
                      f"strength {sensor.scattering.strength:g})",
        "raw_noise": f"noise model is {noise!r}",
        "distance_noise": f"noise model is {noise!r}",
    }
    return Plan(
        ambient=ambient is not None and not ambient.is_black,
        conductor_fresnel=bool((metallic > 0).any()),
        dielectric_fresnel=bool((metallic < 1).any()),
        textures=bool(textured),
        bounces=max_depth > 1,
        first_hit_shadow=not bool(at_pinhole.all()),
        scattering=scatter,
        raw_noise=noise == "raw",
        distance_noise=noise == "li",
        reasons=reasons,
    )
