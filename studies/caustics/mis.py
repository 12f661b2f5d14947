r"""Light tracing behind the tracer's MIS: the three strategies' densities and the balance heuristic.

A caustic path lens → x_1 … x_m → LED (x_m glossy) can be sampled three ways; with area densities

.. math::

    p_A &= p_{cam}(x_1) \prod_{i=1}^{m-1} \overrightarrow{p}_i, \qquad
    p_B = p_{cam}(x_1) \prod_{i=1}^{m-2} \overrightarrow{p}_i \; p_L(x_m), \\
    p_C &= p_L(x_m) \prod_{i=2}^{m} \overleftarrow{p}_i,

* A, the path tracer's next event: camera ray (:mod:`camera_importance`, p_cam = W_p), BSDF samples
  :math:`\overrightarrow{p}_i = p_\sigma(x_i;\ \omega_o{=}x_{i-1}, \omega_i{=}x_{i+1})
  |\cos_{x_{i+1}}| / |x_{i+1} - x_i|^2` (x_0 the lens), then the LED;
* B, the tracer's light vertex: the same down to x_{m−1}, x_m from the LED,
  p_L(x) = q_l p_l(ω) |cos_x| / |x − l|² (:mod:`tofcore.tracer.light_paths`);
* C, light tracing: x_m from the LED, then BSDF samples towards the camera,
  :math:`\overleftarrow{p}_i = p_\sigma(x_i;\ \omega_o{=}x_{i+1}, \omega_i{=}x_{i-1})
  |\cos_{x_{i-1}}| / |x_i - x_{i-1}|^2` (x_{m+1} the LED), and x_1 connects to the lens.

The path tracer takes n samples per pixel, light tracing N light paths for the frame; the balance heuristic
with these counts (Veach 1997, eq. 9.12) weighs strategy s by n_s p_s / Σ_t n_t p_t, so with
ρ = N p_C / (n (p_A + p_B)) the tracer's existing two-strategy weights are multiplied by 1/(1 + ρ) and
light tracing's contributions carry ρ/(1 + ρ). Only the caustic part (the specular share at a glossy x_m,
:mod:`classify`) has strategy C; the rest keeps the tracer's weights. Densities of delta lobes do not enter
(the room has none; :func:`check_no_mirrors`).
"""

from __future__ import annotations

import numpy as np

from tofcore.scene.bsdf import SMOOTH_ROUGHNESS_RAD
from tofcore.tracer.surface import dot


def check_no_mirrors(scene) -> None:
    """The densities above have no delta lobes: raise for a material with a mirror lobe."""
    for m in scene.materials:
        if m.roughness < SMOOTH_ROUGHNESS_RAD:
            raise ValueError(f"mis: material {m.name!r} has a mirror lobe (roughness {m.roughness!r}), which the "
                             "three-strategy weights do not handle")


def led_density(setup, position: np.ndarray, geometric_normal: np.ndarray) -> np.ndarray:
    """p_L(x): area density of x as the LED's first hit (one LED), q p_l(ω) |cos_x| / |x − l|²."""
    led = setup.leds[0]
    to_led = setup.led_positions[0] - position
    d2 = (to_led * to_led).sum(axis=1)
    w = to_led / np.sqrt(d2)[:, None]
    cos_axis = -dot(w, setup.led_axis[None, :])
    return float(setup.led_probability[0]) * led.emission_pdf(cos_axis) * np.abs(dot(w, geometric_normal)) / d2


def light_tracing_share(ratio: float, p_c: np.ndarray, p_ab: np.ndarray) -> np.ndarray:
    """ρ/(1 + ρ) = N p_C / (n (p_A + p_B) + N p_C), ratio = N/n: the balance weight of strategy C."""
    c = ratio * p_c
    total = p_ab + c
    return np.where(total > 0, c / np.where(total > 0, total, 1.0), 0.0)
