r"""The path tracer's estimate split by what the LED lights first: which paths are caustics.

The tracer's per-pixel estimate is a sum of contributions, each ending at the LED (DESIGN.md
"path-length bucketing"): next-event estimates at camera vertex x_k (bucket k) and light-vertex
connections through y (bucket k + 1). The vertex next to the LED — x_k, or y — is the one the LED
lights directly. Its BSDF is f = f_d + f_s, Oren–Nayar plus Torrance–Sparrow (tofcore/scene/bsdf.py),
and every contribution w carries exactly one factor f at that vertex, so

.. math:: w = w \, \frac{f_s}{f} + w \, \Big(1 - \frac{f_s}{f}\Big)

splits it into the light the LED's vertex reflected through its **specular lobe** and through its
diffuse lobe, without changing the sum. ``f_s`` is :func:`tofcore.scene.bsdf.eval_bsdf` with the
diffuse albedo set to 0 (the diffuse lobe is linear in ρ, its interreflection term in ρ²).

Classes (``class_names``): 0 = bucket k = 1 (the camera sees the lit vertex: direct light and highlights,
no caustic); for k ≥ 2, ``spec:<material>`` = the specular part at an LED-lit vertex of that material,
and ``diffuse`` = every diffuse part. A **caustic** is a ``spec:`` class of a material whose roughness
is at most :data:`GLOSSY_MAX_RAD` (LED → glossy/specular vertex → … → camera, at least one vertex
between). Each class sum is an unbiased estimate of its component; the classes add up to the
tracer's frame within float rounding (``tests/studies/test_caustics.py``).

This module runs the tracer's own stages (:mod:`tofcore.tracer.stages`) in the order of
:func:`tofcore.tracer.integrator.trace_chunk` and only recomputes the split factor beside them; the
tracer is not changed.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from tofcore.scene.bsdf import eval_bsdf, pdf_bsdf
from tofcore.tracer.integrator import chunk_samples
from tofcore.tracer.light_paths import trace_light_vertices
from tofcore.tracer.stages import camera_rays, intersect, light_vertex, next_event, scatter, shade
from tofcore.tracer.surface import dot, rotate
from tofcore.tracer.transport import TraceStats

from camera_importance import camera_importance
from mis import check_no_mirrors, led_density, light_tracing_share

GLOSSY_MAX_RAD = 0.3
"""Specular lobes with roughness σ ≤ 0.3 rad (Beckmann α ≤ 0.42) count as glossy: in the Kinect room the
metal box (σ = 0.15), the wood (0.2) and the floor (0.3); the walls' σ = 0.6 lobe is broad and does not."""


@dataclass
class ClassSums:
    """Per-class sums of a frame: Σw (C, K, P) and Σw·g_j (C, K, J, P) over ``n`` samples per pixel."""

    signal: np.ndarray
    correlation: np.ndarray
    samples: int

    def __iadd__(self, other: ClassSums) -> ClassSums:
        self.signal += other.signal
        self.correlation += other.correlation
        self.samples += other.samples
        return self


def class_names(materials) -> list[str]:
    """Names of the classes for a scene's materials, in class order (see the module docstring)."""
    return ["k=1"] + [f"spec:{m.name}" for m in materials] + ["diffuse"]


def caustic_classes(materials, glossy_max_rad: float = GLOSSY_MAX_RAD) -> list[int]:
    """Class indices that are caustics: the specular lobes of glossy materials, k ≥ 2."""
    return [1 + i for i, m in enumerate(materials) if m.roughness <= glossy_max_rad]


def specular_share(params, wo: np.ndarray, wi: np.ndarray) -> np.ndarray:
    """f_s / f at points with ``params`` for local directions wo, wi (0 where f = 0)."""
    f = eval_bsdf(params, wo, wi)
    f_s = eval_bsdf(dataclasses.replace(params, reflectance=np.zeros_like(params.reflectance)), wo, wi)
    return np.where(f > 0, f_s / np.where(f > 0, f, 1.0), 0.0)


def trace_classified(setup, p0: int, p1: int, spp: int, lt_ratio: float | None = None,
                     glossy_max_rad: float = GLOSSY_MAX_RAD) -> ClassSums:
    """Samples 0 … spp − 1 of pixels [p0, p1), every contribution split into its classes.

    The same paths and numbers as :func:`tofcore.tracer.integrator.trace_chunk` with uniform counts.
    One LED only (the Kinect v2 preset's): the next-event split needs the direction to it.
    With ``lt_ratio`` = N/n (light paths of the frame per sample per pixel) the caustic parts carry the
    three-strategy balance weights of :mod:`mis`, for a sum with :func:`light_tracer.trace_light`'s.
    """
    if len(setup.leds) != 1:
        raise ValueError(f"trace_classified: one LED only, got {len(setup.leds)}")
    n_mat = len(setup.scene.materials)
    n_cls, k_max, n_ch, n_pix = n_mat + 2, setup.max_depth, setup.n_channels, p1 - p0
    sums = ClassSums(np.zeros((n_cls, k_max, n_pix)), np.zeros((n_cls, k_max, n_ch, n_pix)), spp)
    stats = TraceStats()
    counts = np.full(n_pix, spp, np.int64)
    state = camera_rays(setup, *chunk_samples(np, p0, np.zeros(n_pix, np.int64), counts))
    light = trace_light_vertices(setup, stats, state.pixel, state.sample) if setup.light_paths else None
    track = None if lt_ratio is None else _Densities.start(setup, len(state), lt_ratio, glossy_max_rad)
    for k in range(1, k_max + 1):
        state, hits, _ = intersect(setup, state, k, stats)
        if len(state) == 0:
            break
        state, vertex = shade(setup, state, hits, k)
        material = setup.table.material_ids[hits.prim]
        contribution = next_event(setup, state, vertex, stats)
        to_led = setup.led_positions[0] - vertex.surface.position
        wi = vertex.surface.to_local(to_led / np.linalg.norm(to_led, axis=1, keepdims=True))
        share = specular_share(vertex.surface.params, vertex.wo, wi)
        weight = None
        if track is not None:
            track.arrive(setup, state, vertex)
            weight = track.next_event_weight(setup, state, vertex, wi, material)
        _add(sums, setup, state.pixel - p0, contribution, share, material, weight)
        if k == k_max:
            break
        if light is not None:
            contribution = light_vertex(setup, state, vertex, light, stats)
            share, y_material = _light_vertex_split(setup, state, vertex, light)
            weight = None if track is None else track.light_vertex_weight(setup, state, vertex, light, y_material)
            _add(sums, setup, state.pixel - p0, contribution, share, y_material, weight)
        before = state
        state = scatter(setup, state, vertex)
        if track is not None:
            track.leave(before, state, vertex)
        if len(state) == 0:
            break
    return sums


@dataclass
class _Densities:
    """Per path (rows = chunk path index) the products of :mod:`mis` up to the current vertex x_k."""

    ratio: float             # N/n
    glossy: np.ndarray       # (M,) bool per material
    fwd: np.ndarray          # p_cam(x_1) Π_{i<k} →p_i: p_A of the path ending at x_k
    rev: np.ndarray          # Π_{i=2}^{k-1} ←p_i (x_{i+1} the path's own next vertex)
    cos_out: np.ndarray      # |cos| at x_{k-1} of the segment to x_k
    seg: np.ndarray          # |x_k − x_{k−1}|

    @classmethod
    def start(cls, setup, n: int, ratio: float, glossy_max_rad: float) -> _Densities:
        check_no_mirrors(setup.scene)
        glossy = np.array([m.roughness <= glossy_max_rad for m in setup.scene.materials])
        return cls(ratio, glossy, np.zeros(n), np.ones(n), np.zeros(n), np.zeros(n))

    def arrive(self, setup, state, vertex) -> None:
        """At x_k: extend p_A by the bounce that found it (p_cam at k = 1); remember |x_k − x_{k−1}|."""
        surf, rows = vertex.surface, state.path
        self.seg[rows] = np.linalg.norm(surf.position - state.prev_point, axis=1)
        if vertex.k == 1:
            cos_x = np.abs(dot(state.direction, surf.geometric_normal))
            self.fwd[rows] = camera_importance(setup.camera, rotate(surf.position - setup.lens_center,
                                                                    setup.rotation.T), cos_x).weight
        else:
            self.fwd[rows] *= vertex.area_pdf

    def leave(self, before, after, vertex) -> None:
        """After the BSDF sample at x_k: ←p_k (towards x_{k−1}, from x_{k+1}) joins rev for k ≥ 2."""
        index = np.full(int(before.path.max()) + 1, -1, np.int64)
        index[before.path] = np.arange(len(before))
        at = index[after.path]                       # the surviving paths' rows in ``vertex``
        surf = vertex.surface.take(at)
        wi_next = surf.to_local(after.direction)
        if vertex.k >= 2:
            p = pdf_bsdf(surf.params, wi_next, vertex.wo[at])
            self.rev[after.path] *= p * self.cos_out[after.path] / self.seg[after.path] ** 2
        self.cos_out[after.path] = np.abs(dot(after.direction, surf.geometric_normal))

    def _rev_to(self, rows, params, wo_next_local, wo_local, k: int) -> np.ndarray:
        """Π_{i=2}^{k} ←p_i for a path whose vertex after x_k is given by ``wo_next_local`` (k ≥ 2), else 1."""
        if k < 2:
            return np.ones(len(rows))
        return self.rev[rows] * pdf_bsdf(params, wo_next_local, wo_local) * self.cos_out[rows] / self.seg[rows] ** 2

    def next_event_weight(self, setup, state, vertex, wi_led, material) -> np.ndarray:
        """1/(1 + ρ) for next-event paths ending at x_k (k ≥ 2, glossy x_k); 1 elsewhere."""
        surf, rows, k = vertex.surface, state.path, vertex.k
        if k < 2:
            return np.ones(len(rows))
        p_l = led_density(setup, surf.position, surf.geometric_normal)
        p_ab = self.fwd[rows] + self.fwd[rows] / np.where(vertex.area_pdf > 0, vertex.area_pdf, np.inf) * p_l
        # C: x_k from the LED, then x_k → x_{k−1} (from the LED's side) and on down to x_1
        p_first = pdf_bsdf(surf.params, wi_led, vertex.wo) * self.cos_out[rows] / self.seg[rows] ** 2
        p_c = p_l * p_first * self.rev[rows]
        return np.where(self.glossy[material], 1.0 - light_tracing_share(self.ratio, p_c, p_ab), 1.0)

    def light_vertex_weight(self, setup, state, vertex, light, y_material) -> np.ndarray:
        """1/(1 + ρ) for paths x_1 … x_k → y (glossy y); 1 elsewhere."""
        rows_all = light.row[state.path]
        sel = np.flatnonzero(rows_all >= 0)
        weight = np.ones(len(state))
        if len(sel) == 0:
            return weight
        rows, x, path = rows_all[sel], vertex.surface.take(sel), state.path[sel]
        y = light.surface.take(rows)
        to_y = y.position - x.position
        dist = np.linalg.norm(to_y, axis=1)
        w_xy = to_y / dist[:, None]
        p_x = pdf_bsdf(x.params, vertex.wo[sel], x.to_local(w_xy)) * np.abs(dot(w_xy, y.geometric_normal)) / dist**2
        p_ab = self.fwd[path] * (p_x + light.pdf_area[rows])
        p_y = pdf_bsdf(y.params, y.to_local(light.to_led[rows]), y.to_local(-w_xy))
        p_c = (light.pdf_area[rows] * p_y * np.abs(dot(w_xy, x.geometric_normal)) / dist**2
               * self._rev_to(path, x.params, x.to_local(w_xy), vertex.wo[sel], vertex.k))
        weight[sel] = np.where(self.glossy[y_material[sel]], 1.0 - light_tracing_share(self.ratio, p_c, p_ab), 1.0)
        return weight


def _light_vertex_split(setup, state, vertex, light):
    """(f_s/f at the light vertex y seen from camera vertex x_k, y's material) per path; 0, 0 without y."""
    rows = light.row[state.path]
    sel = np.flatnonzero(rows >= 0)
    share = np.zeros(len(state))
    material = np.zeros(len(state), np.int64)
    if len(sel):
        y = light.surface.take(rows[sel])
        to_y = y.position - vertex.surface.position[sel]
        w_xy = to_y / np.maximum(np.linalg.norm(to_y, axis=1, keepdims=True), 1e-300)
        share[sel] = specular_share(y.params, y.to_local(-w_xy), y.to_local(light.to_led[rows[sel]]))
        material[sel] = setup.table.material_ids[light.prim[rows[sel]]]
    return share, material


def _add(sums: ClassSums, setup, pixel, contribution, share, material, caustic_weight=None) -> None:
    """Add one contribution (bucket c.k) to its classes: k = 1 → class 0; else spec share → 1 + material
    (times ``caustic_weight``, the MIS weight of :mod:`mis`, where given), the rest → the last class."""
    k, n_pix = contribution.k, sums.signal.shape[-1]
    w = contribution.weight
    g = contribution.correlation if setup.n_channels else np.zeros((0, len(w)))
    if k == 1:
        parts = [(0, np.ones_like(w), None)]
    else:
        spec = share if caustic_weight is None else share * caustic_weight
        parts = [(1 + m, spec, material == m) for m in range(len(setup.scene.materials))]
        parts.append((sums.signal.shape[0] - 1, 1.0 - share, None))
    for cls, factor, mask in parts:
        scale = factor if mask is None else np.where(mask, factor, 0.0)
        sums.signal[cls, k - 1] += np.bincount(pixel, w * scale, n_pix)
        for j in range(g.shape[0]):
            sums.correlation[cls, k - 1, j] += np.bincount(pixel, g[j] * scale, n_pix)

