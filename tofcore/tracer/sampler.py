"""The sampler: the one table of sample dimensions, and the uniforms each decision of a path draws.

Every random decision of a path takes its uniforms from the sampler by name — pbrt's ``Sampler::Get1D`` /
``Get2D`` idea: a stage asks for "the lens position" or "the direction at vertex k", never for a
dimension number it chose itself. The numbers live here, once; they never collide:

=========================  =====  ==================================================================
dimension                  kind   decision
=========================  =====  ==================================================================
``PIXEL`` = 0              2-D    position inside the pixel (camera rays)
``LENS`` = 1               2-D    position on the lens (thin lens; unused by a pinhole)
``lobe(k)`` = 2k           1-D    lobe chosen at surface vertex k ≥ 1 (scatter)
``direction(k)`` = 2k + 1  2-D    direction sampled at surface vertex k ≥ 1 (scatter)
``LED_CHOICE`` = 10⁶       1-D    which LED emits the light vertex (light vertices)
``EMISSION`` = 10⁶ + 1     2-D    its emission direction (light vertices)
=========================  =====  ==================================================================

A dimension d of the ``"sobol"`` sampler is one Owen-scrambled Sobol' (0, 2)-sequence per pixel and
replicate (:mod:`tofcore.tracer.qmc`); the ``"independent"`` sampler maps d to the counter-based uniforms
2d and 2d + 1 (:mod:`tofcore.rng`). Either way a sample is a function of (seed, pixel, sample index,
dimension) only, so the frame does not depend on chunks, workers or the device.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import rng
from . import qmc

PIXEL = 0
LENS = 1
LED_CHOICE = 1_000_000
EMISSION = 1_000_001


def lobe(vertex: int) -> int:
    """1-D dimension of the lobe chosen at surface vertex ``vertex`` (1 = first hit)."""
    return 2 * vertex


def direction(vertex: int) -> int:
    """2-D dimension of the direction sampled at surface vertex ``vertex``."""
    return 2 * vertex + 1


@dataclass(frozen=True)
class Sampler:
    """Uniforms for (pixel, sample) pairs of one render: its seed key and kind (:data:`qmc.SAMPLERS`)."""

    key: np.uint64
    kind: str = "sobol"

    @classmethod
    def for_seed(cls, seed: int, kind: str = "sobol") -> Sampler:
        return cls(rng.seed_key(seed), kind)

    def get_1d(self, pixel, sample, dim: int):
        """(N,) uniforms in [0, 1) for dimension ``dim`` of samples ``sample`` of pixels ``pixel``."""
        return qmc.sample_1d(self.key, pixel, sample, dim, self.kind)

    def get_2d(self, pixel, sample, dim: int):
        """Two (N,) uniforms in [0, 1) for dimension ``dim`` (a pair of coordinates)."""
        return qmc.sample_2d(self.key, pixel, sample, dim, self.kind)
