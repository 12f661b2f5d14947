"""Light vertices: the LED's first hits, connected to the camera path's vertices, with MIS.

A path lens → x_1 … x_k → y → LED can be sampled two ways:

* **A (BSDF + next event)**: the camera path samples the direction x_k → y from the BSDF at x_k and, at
  y, connects to the LED (:func:`tofcore.tracer.transport._connect_led`). Its area density at y is
  :math:`p_A = p_\\omega(x_k \\to y)\\,|\\cos\\theta_{y}^{x}| / |x_k - y|^2`.
* **B (light vertex)**: one ray per sample leaves an LED l (chosen with probability q_l ∝ its power Φ_l)
  in a direction drawn ∝ its intensity I(θ); its first hit is y, which every camera vertex x_k connects
  to with a shadow ray. Its area density at y is :math:`p_B = q_l\\,p_l(\\omega)\\,|\\cos\\theta_{y}^{l}|
  / |y - l|^2`, and the contribution is

  .. math:: w_B = \\beta_k\\, f(x_k)\\, \\frac{\\cos\\theta_{x_k}\\cos\\theta_y^{x}}{|x_k - y|^2}\\,
            f(y)\\, \\frac{\\cos_s\\theta_y^{l}}{\\cos\\theta_y^{l}}\\, \\frac{\\Phi_l}{q_l}

  (I/p_l = Φ_l; the last cosine ratio is one without shading normals).

Both are weighted by the balance heuristic, w_A ← w_A p_A/(p_A + p_B), w_B ← w_B p_B/(p_A + p_B)
(Veach 1997, ch. 9–10: this is bidirectional path tracing restricted to light sub-paths of one surface
vertex). The sum stays unbiased; what changes is which strategy carries which paths. Where y lies close
to the LED (a wall beside the camera), p_B ∝ 1/|y − l|² is large and the light vertex carries the path:
strategy A alone gives such paths as rare, huge next-event weights — the fireflies of the crosscheck room
(docs/benchmarks.md). Paths through a mirror (delta) lobe at x_k only A can sample: w_A = 1 there.

Bounce count and path length are those of the path: k + 1 surface vertices,
L = |lens … x_k| + |x_k − y| + |y − l|.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..scene.bsdf import eval_bsdf, eval_pdf_bsdf
from . import qmc
from .surface import LEAVE_RELATIVE, Surface, dot, leaving, point_offset, rotate, shadow_ray, spawn_offset, surface_at

DIM_LED_CHOICE = 1_000_000   # 1-D sample dimension: which LED emits the light vertex
DIM_EMISSION = 1_000_001     # 2-D: its emission direction


def led_probabilities(leds) -> np.ndarray:
    """(L,) probability of each LED emitting the light vertex: q_l = Φ_l / Σ Φ (zeros if all are dark)."""
    power = np.array([led.power_w for led in leds], dtype=np.float64)
    return power / power.sum() if power.sum() > 0 else power


@dataclass(frozen=True)
class LightVertices:
    """The light vertex of each path of a chunk (rows of ``surface``; ``row`` maps chunk slots to rows)."""

    row: np.ndarray        # (N,) int64 row per chunk slot, −1 where the light ray missed
    surface: Surface       # (M,) the hit points y, frame facing the LED
    prim: np.ndarray       # (M,) their triangles
    to_led: np.ndarray     # (M, 3) unit direction y → LED
    led_distance: np.ndarray  # (M,) |y − l| in metres
    emitted: np.ndarray    # (M,) Φ_l / q_l · cos_s / cos_g at y (W)
    pdf_area: np.ndarray   # (M,) p_B, area density of y (1/m²)


def trace_light_vertices(ctx, stats, pixel, sample) -> LightVertices:
    """One light vertex per (pixel, sample): choose an LED, emit ∝ I(θ), find the first hit."""
    xp = ctx.device.xp
    n = len(pixel)
    q = led_probabilities(ctx.leds)
    u_led = qmc.sample_1d(ctx.key, pixel, sample, DIM_LED_CHOICE, ctx.sampler)
    led_index = xp.zeros(n, np.int64)
    for cdf in np.cumsum(q)[:-1]:
        led_index += (u_led >= cdf).astype(np.int64)
    u1, u2 = qmc.sample_2d(ctx.key, pixel, sample, DIM_EMISSION, ctx.sampler)
    local = xp.zeros((n, 3))
    pdf_dir = xp.zeros(n)
    for i, led in enumerate(ctx.leds):
        sel = xp.flatnonzero(led_index == i)
        local[sel] = led.sample_emission(u1[sel], u2[sel])
        pdf_dir[sel] = q[i] * led.emission_pdf(local[sel, 2])
    direction = rotate(local, ctx.rotation)
    origin = ctx.led_positions[led_index]
    hits = ctx.scene.bvh.intersect(leaving(origin, direction), direction.astype(np.float32), workers=1)
    stats.light_rays += n
    hit = xp.flatnonzero((hits.prim >= 0) & (pdf_dir > 0))
    row = xp.full(n, -1, np.int64)
    row[hit] = xp.arange(len(hit))
    surf = surface_at(ctx.scene, ctx.table, hits.prim[hit], hits.u[hit], hits.v[hit], origin[hit], direction[hit])
    to_led = -direction[hit]
    led_distance = np.linalg.norm(surf.position - origin[hit], axis=1)
    cos_geo = dot(to_led, surf.geometric_normal)  # > 0: the frame faces the LED
    cos_shading = np.maximum(dot(to_led, surf.shading_normal), 0.0)
    power = xp.asarray(np.array([led.power_w for led in ctx.leds]))[led_index[hit]]
    with np.errstate(divide="ignore", invalid="ignore"):
        emitted = np.where(cos_geo > 0, power / xp.asarray(np.where(q > 0, q, 1.0))[led_index[hit]]
                           * cos_shading / cos_geo, 0.0)
    # An LED on (or behind) the surface it lights has no light vertex there: nothing leaves it that way.
    away = led_distance > point_offset(origin[hit], LEAVE_RELATIVE)
    emitted = np.where(away, emitted, 0.0)
    pdf_area = np.where(away, pdf_dir[hit] * np.abs(cos_geo) / np.where(away, led_distance, 1.0)**2, 0.0)
    return LightVertices(row=row, surface=surf, prim=hits.prim[hit], to_led=to_led, led_distance=led_distance,
                         emitted=emitted, pdf_area=pdf_area)


def connect(ctx, stats, light: LightVertices, slot, surf: Surface, spawn, wo, prim, throughput):
    """Strategy B at the camera vertices ``surf`` of the paths ``slot``: (weight w_B, extra path length).

    The extra length |x − y| + |y − l| is to be added to the camera path's length; w_B is 0 where the
    path has no light vertex, the two points do not see each other or a BSDF is zero.
    """
    xp = ctx.device.xp
    n = len(slot)
    weight = xp.zeros(n)
    extra = xp.zeros(n)
    rows = light.row[slot]
    sel = xp.flatnonzero(rows >= 0)
    if len(sel) == 0:
        return weight, extra
    rows = rows[sel]
    y = light.surface.take(rows)
    x = surf.take(sel)
    to_y = y.position - x.position
    dist = np.linalg.norm(to_y, axis=1)
    dist = np.where(dist > 0, dist, np.inf)
    w_xy = to_y / dist[:, None]
    cos_x = dot(w_xy, x.geometric_normal)
    cos_y = -dot(w_xy, y.geometric_normal)
    wi_x = x.to_local(w_xy)
    f_x, pdf_x = eval_pdf_bsdf(x.params, wo[sel], wi_x)
    f_y = eval_bsdf(y.params, y.to_local(-w_xy), y.to_local(light.to_led[rows]))
    g = np.maximum(dot(w_xy, x.shading_normal), 0.0) * np.maximum(cos_y, 0.0) / dist**2
    w = throughput[sel] * f_x * g * f_y * light.emitted[rows]
    p_bsdf = pdf_x * np.maximum(cos_y, 0.0) / dist**2
    p_light = light.pdf_area[rows]
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where((cos_x > 0) & (cos_y > 0) & (w > 0), w * p_light / (p_bsdf + p_light), 0.0)
    test = xp.flatnonzero(w > 0)
    if len(test):
        clock = time.perf_counter()
        # Stop short of y by a few ray offsets, so y's own surface does not occlude it.
        corners = ctx.table.vertices[ctx.table.triangles[light.prim[rows[test]]]]  # y's triangles
        margin = 4.0 * spawn_offset(y.position[test], y.geometric_normal[test], corners)
        blocked = ctx.scene.bvh.occluded(*shadow_ray(spawn[sel[test]], y.position[test], margin),
                                         ignore_prim=prim[sel[test]], workers=1)
        stats.shadow_rays += len(test)
        stats.shadow_seconds += time.perf_counter() - clock
        w[test[blocked]] = 0.0
    weight[sel] = w
    extra[sel] = dist + light.led_distance[rows]
    return weight, extra


def bsdf_strategy_weight(p_bsdf_area, prev_delta, led, q_led: float, cos_axis, cos_geo, dist):
    """Balance-heuristic weight of strategy A for next-event estimates at y to one LED.

    ``p_bsdf_area`` is p_A (the previous bounce's solid-angle pdf × cos at y / segment²); paths whose
    previous bounce was a mirror (``prev_delta``) only A can sample (weight 1).
    """
    p_light = q_led * led.emission_pdf(cos_axis) * np.maximum(cos_geo, 0.0) / dist**2
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.where(p_bsdf_area + p_light > 0, p_bsdf_area / (p_bsdf_area + p_light), 1.0)
    return np.where(prev_delta, 1.0, share)

