r"""Light tracing to the camera (the t = 1 strategy): LED → surfaces → a connection to the lens.

A prototype for the study, on tofcore's own scene, BVH, BSDF, LED and camera functions.

Estimator
---------
A light path leaves an LED l (chosen with q_l ∝ Φ_l) in a direction drawn ∝ I(θ) and hits y_1 — exactly
the tracer's light vertex (:func:`tofcore.tracer.light_paths.trace_light_vertices`), with throughput
α_1 = Φ_l/q_l (times cos_s/cos_g, one without shading normals). At each y_j the BSDF is sampled with
ω_o = the direction the light came from (:func:`tofcore.scene.bsdf.sample_bsdf`; the BSDF is
reciprocal), α_{j+1} = α_j f cosθ / p. Every y_j connects to the lens:

.. math:: \hat I_p = \frac1{N} \sum_{i=1}^{N} \sum_j \alpha_{i,j}\, f(y_j;\, \omega_{lens}, \omega_{prev})\,
          W_p(y_j)\, V(y_j, \text{lens})

(W_p: :mod:`camera_importance`)

into bucket k = j with path length |l − y_1| + Σ|y_{i+1} − y_i| + |y_j − lens|. Pinhole cameras only
(a thin lens needs a lens point sampled per connection), no shading normals (the adjoint BSDF of
shading normals is not modelled): both raise.

For the caustic component alone (``caustic_only``) the path keeps only the specular part of y_1's BSDF
at a glossy material (the split of :mod:`classify`), α_2 ← α_2 f_s/f; paths whose y_1 is not glossy
end there, and y_1 itself does not connect (bucket 1 is no caustic).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tofcore.constants import SPEED_OF_LIGHT_M_S
from tofcore.scene.bsdf import eval_bsdf, pdf_bsdf, sample_bsdf
from tofcore.tracer import sampler as dims
from tofcore.tracer.light_paths import trace_light_vertices
from tofcore.tracer.surface import dot, point_offset, rotate, shadow_ray, spawn_offset, surface_at
from tofcore.tracer.transport import TraceStats

from camera_importance import camera_importance
from classify import GLOSSY_MAX_RAD, ClassSums, specular_share
from mis import check_no_mirrors, light_tracing_share

GROUP = 1024
"""Light paths per group of the sampler: path i is sample i mod GROUP of "pixel" i // GROUP, so each group's
emission directions and bounces are one scrambled Sobol' net (or plain uniforms with ``independent``)."""


def check_light_tracing(setup) -> None:
    """Raise where the prototype does not hold: thin lenses, shading normals."""
    if setup.camera.aperture_radius_m > 0:
        raise ValueError("light tracing: pinhole cameras only")
    scene = setup.scene
    if scene.normals is not None or any(m.normal_texture is not None for m in scene.materials):
        raise ValueError(f"light tracing: scene {scene.name!r} has shading normals, which the prototype "
                         "does not model (no adjoint BSDF)")


def trace_light(setup, first: int, n_paths: int, *, caustic_only: bool = False,
                glossy_max_rad: float = GLOSSY_MAX_RAD, mis_ratio: float | None = None) -> ClassSums:
    """Light paths ``first`` … ``first + n_paths − 1`` into per-class sums of the frame (classes of
    :func:`classify.class_names`; ``samples`` counts light paths: divide by the frame's total N).

    ``setup`` is a :class:`tofcore.tracer.setup.TraceSetup` (its sampler, seed and max_depth are used).
    With ``mis_ratio`` = N/n (light paths of the frame per path-tracer sample per pixel; ``caustic_only``)
    every contribution carries strategy C's balance weight of :mod:`mis`, for a sum with
    :func:`classify.trace_classified`'s at ``lt_ratio`` = N/n.
    """
    check_light_tracing(setup)
    if mis_ratio is not None and not caustic_only:
        raise ValueError("trace_light: mis_ratio needs caustic_only (only caustics have the light-tracing strategy)")
    cam, k_max, n_ch = setup.camera, setup.max_depth, setup.n_channels
    n_pix, n_mat = cam.width * cam.height, len(setup.scene.materials)
    sums = ClassSums(np.zeros((n_mat + 2, k_max, n_pix)), np.zeros((n_mat + 2, k_max, n_ch, n_pix)), n_paths)
    stats = TraceStats()
    ids = np.arange(first, first + n_paths, dtype=np.int64)
    group, sample = ids // GROUP, ids % GROUP
    light = trace_light_vertices(setup, stats, group, sample)
    keep = np.flatnonzero(light.row >= 0)
    surf, prim = light.surface, light.prim
    group, sample = group[keep], sample[keep]
    throughput = light.emitted.copy()
    length = light.led_distance.copy()
    to_prev = light.to_led.copy()                       # unit direction towards where the light came from
    glossy = np.array([m.roughness <= glossy_max_rad for m in setup.scene.materials])
    first_material = setup.table.material_ids[prim]     # y_1's material: the class of a spec part
    spec_share = np.ones(len(keep))                     # f_s/f at y_1 (set at the first bounce)
    dens = None if mis_ratio is None else _LightDensities.start(setup, light.pdf_area, mis_ratio)
    for j in range(1, k_max + 1):
        corners = setup.table.vertices[setup.table.triangles[prim]]
        spawn = surf.position + surf.geometric_normal * spawn_offset(surf.position, surf.geometric_normal,
                                                                     corners)[:, None]
        if j > 1 or not caustic_only:
            _connect(setup, sums, j, surf, prim, spawn, to_prev, throughput, length, spec_share, first_material,
                     caustic_only, stats, dens)
        if j == k_max:
            break
        wo = surf.to_local(to_prev)
        u1, u2 = setup.sampler.get_2d(group, sample, dims.direction(j))
        u_lobe = setup.sampler.get_1d(group, sample, dims.lobe(j))
        bs = sample_bsdf(surf.params, wo, u_lobe, u1, u2)
        new_dir = surf.to_world(bs.wi)
        weight = bs.weight
        if j == 1:
            share = specular_share(surf.params, bs.wi, wo)
            if caustic_only:
                weight = weight * share * glossy[first_material]
            else:
                spec_share = share
        alive = np.flatnonzero((weight > 0) & (dot(new_dir, surf.geometric_normal) > 0))
        if dens is not None:
            dens.leave(j, surf, wo, bs)
        new_dir = new_dir[alive] / np.linalg.norm(new_dir[alive], axis=1, keepdims=True)
        origin = spawn[alive]
        hits = setup.scene.bvh.intersect(origin.astype(np.float32), new_dir.astype(np.float32),
                                         ignore_prim=prim[alive], workers=1)
        hit = np.flatnonzero(hits.prim >= 0)
        rows = alive[hit]
        new_surf = surface_at(setup.scene, setup.table, hits.prim[hit], hits.u[hit], hits.v[hit], origin[hit],
                              new_dir[hit])
        length_before = length
        length = length[rows] + np.linalg.norm(new_surf.position - surf.position[rows], axis=1)
        throughput = throughput[rows] * weight[rows]
        to_prev = -new_dir[hit]
        surf, prim = new_surf, hits.prim[hit]
        group, sample = group[rows], sample[rows]
        spec_share, first_material = spec_share[rows], first_material[rows]
        if dens is not None:
            dens.arrive(rows, bs.pdf[rows], new_dir[hit], new_surf, length - length_before[rows])
        if len(rows) == 0:
            break
    return sums


def _connect(setup, sums: ClassSums, j: int, surf, prim, spawn, to_prev, throughput, length, spec_share,
             first_material, caustic_only: bool, stats: TraceStats, dens: _LightDensities | None) -> None:
    """Connect light vertices y_j to the lens (pinhole at the lens centre) and add them to bucket j."""
    lens = setup.lens_center
    to_lens = lens[None, :] - surf.position
    dist = np.linalg.norm(to_lens, axis=1)
    w_lens = to_lens / dist[:, None]
    cos_y = dot(w_lens, surf.geometric_normal)
    points_sensor = rotate(-to_lens, setup.rotation.T)   # sensor frame: world_from_sensor rotation inverted
    imp = camera_importance(setup.camera, points_sensor, cos_y)
    f = eval_bsdf(surf.params, surf.to_local(w_lens), surf.to_local(to_prev))
    w = throughput * f * imp.weight
    if dens is not None:
        w = w * dens.weight(j, surf, surf.to_local(w_lens), surf.to_local(to_prev), imp.weight)
    test = np.flatnonzero(w > 0)
    if len(test):
        margin = point_offset(lens[None])
        blocked = setup.scene.bvh.occluded(*shadow_ray(spawn[test], lens, margin), ignore_prim=prim[test],
                                           workers=1)
        stats.shadow_rays += len(test)
        w[test[blocked]] = 0.0
    ok = np.flatnonzero(w > 0)
    if len(ok) == 0:
        return
    pixel, w = imp.pixel[ok], w[ok]
    n_pix = sums.signal.shape[-1]
    tau = (length[ok] + dist[ok]) / SPEED_OF_LIGHT_M_S
    g = setup.correlations(tau) if setup.n_channels else np.zeros((0, len(ok)))
    if j == 1:
        parts = [(0, np.ones_like(w))]
    elif caustic_only:
        parts = [(1 + m, np.where(first_material[ok] == m, 1.0, 0.0)) for m in range(sums.signal.shape[0] - 2)]
    else:
        s = spec_share[ok]
        parts = [(1 + m, np.where(first_material[ok] == m, s, 0.0)) for m in range(sums.signal.shape[0] - 2)]
        parts.append((sums.signal.shape[0] - 1, 1.0 - s))
    for cls, factor in parts:
        sums.signal[cls, j - 1] += np.bincount(pixel, w * factor, n_pix)
        for c in range(g.shape[0]):
            sums.correlation[cls, j - 1, c] += np.bincount(pixel, w * factor * g[c], n_pix)


@dataclass
class _LightDensities:
    """Per live light path, the products of :mod:`mis` along y_1 … y_j (strategy C's own and A's, reversed)."""

    ratio: float            # N/n
    p_light: np.ndarray     # p_L(y_1)
    fwd: np.ndarray         # p_C of the path ending at y_j: p_L(y_1) Π BSDF area densities towards y_j
    rev: np.ndarray         # Π_{i=2}^{j-1} of the path tracer's densities y_i → y_{i−1} (from y_{i+1})
    first_rev: np.ndarray   # the path tracer's density y_2 → y_1 (set once y_3 is sampled)
    cos_out: np.ndarray     # |cos| at y_{j−1} of the segment to y_j
    seg: np.ndarray         # |y_j − y_{j−1}|

    @classmethod
    def start(cls, setup, p_light: np.ndarray, ratio: float) -> _LightDensities:
        check_no_mirrors(setup.scene)
        n = len(p_light)
        return cls(ratio, p_light.copy(), p_light.copy(), np.ones(n), np.zeros(n), np.zeros(n), np.zeros(n))

    def weight(self, j: int, surf, wo_lens, wi_prev, p_cam) -> np.ndarray:
        """Strategy C's balance weight for connecting y_j (j ≥ 2) to the lens."""
        toward_prev = pdf_bsdf(surf.params, wo_lens, wi_prev) * self.cos_out / self.seg**2   # y_j → y_{j−1}
        p_a = p_cam * toward_prev * self.rev
        toward_first = toward_prev if j == 2 else self.first_rev
        with np.errstate(divide="ignore", invalid="ignore"):
            p_b = np.where(toward_first > 0, p_a / toward_first * self.p_light, 0.0)
        return light_tracing_share(self.ratio, self.fwd, p_a + p_b)

    def leave(self, j: int, surf, wo, bs) -> None:
        """After sampling at y_j: the path tracer's density y_j → y_{j−1} (j ≥ 2) joins rev; cos at y_j."""
        if j >= 2:
            toward_prev = pdf_bsdf(surf.params, bs.wi, wo) * self.cos_out / self.seg**2
            self.rev = self.rev * toward_prev
            if j == 2:
                self.first_rev = toward_prev
        self.cos_out = np.abs(dot(surf.to_world(bs.wi), surf.geometric_normal)) / np.linalg.norm(bs.wi, axis=1)

    def arrive(self, rows, pdf, direction, new_surf, seg) -> None:
        """The paths ``rows`` found y_{j+1}: compact, extend p_C by the BSDF sample's area density."""
        for name in ("p_light", "fwd", "rev", "first_rev", "cos_out"):
            setattr(self, name, getattr(self, name)[rows])
        self.seg = seg
        self.fwd = self.fwd * pdf * np.abs(dot(direction, new_surf.geometric_normal)) / seg**2
