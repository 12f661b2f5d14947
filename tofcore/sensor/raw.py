"""The raw-image model: mean radiance at the lens → charge in electrons per raw image (SPEC §3).

Scattering (:mod:`~tofcore.sensor.optics`), noise (:mod:`~tofcore.sensor.noise`) and full-well saturation
act on these images afterwards; :mod:`~tofcore.sensor.decode` turns them into distances.
"""

from __future__ import annotations

import numpy as np

from ..backend import namespace


def raw_images(correlation_means: np.ndarray, ambient_mean: np.ndarray, sensor) -> np.ndarray:
    """Noise-free raw images (R, H, W) in electrons, before scattering and saturation.

    Notes
    -----
    .. math:: Q_j = R \\, T_j \\, (\\bar{c}_j + L_{amb} \\, \\delta_j)

    R the responsivity (e⁻ s⁻¹ per W m⁻² sr⁻¹), T_j the raw image's exposure,
    :math:`\\bar c_j` the pixel's mean Σ w g_j (radiance-weighted correlation),
    :math:`L_{amb}` the ambient radiance and δ_j the gate duty: unmodulated
    light adds to every bucket the charge its gate lets through (SPEC §3).
    """
    mod = sensor.modulation
    xp = namespace(correlation_means)
    exposure = xp.asarray(mod.raw_exposure_s())[:, None, None]
    duty = xp.asarray(mod.gate_duty())[:, None, None]
    return sensor.readout.responsivity * exposure * (correlation_means + ambient_mean[None] * duty)
