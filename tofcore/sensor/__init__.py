"""From light at the lens to the camera's numbers: the sensor's configuration (:mod:`~tofcore.sensor.config`,
presets), modulation and correlation, lens scattering, noise, the raw-image model and decoding.

It never imports the tracer or the outputs.
"""

from .config import Sensor

__all__ = ["Sensor"]
