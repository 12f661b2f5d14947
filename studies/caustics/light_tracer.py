r"""Light tracing to the camera (the t = 1 strategy): LED → surfaces → a connection to the lens.

A prototype for the study, on tofcore's own scene, BVH, BSDF, LED and camera functions.

Camera importance
-----------------
The tracer's pixel value is the mean radiance over the pixel's area in (distorted) pixel coordinates,
:math:`I_p = \int_{\text{pixel } p} L(u)\, du`, pixel area 1 (``Camera.generate_rays``: uniform jitter in
the pixel). With (x, y) = (X/Z, Y/Z) the undistorted normalized coordinates of a sensor-frame point,
u = f_x x_d + c_x, v = f_y y_d + c_y and x_d = distort(x), and dx dy = dω / cos³θ (θ from the optical
axis), the same integral over the surface points y the pinhole sees is

.. math:: I_p = \int L(y \to \text{lens})\, W_p(y)\, dA_y, \qquad
          W_p(y) = [u(y) \in p]\; \frac{f_x f_y\, |\det \partial(x_d, y_d)/\partial(x, y)|}{\cos^3\theta}\;
                   \frac{\cos\theta_y}{r^2}

(:func:`camera_importance`; r = |y − lens|, θ_y at y between its normal and the lens).

Estimator
---------
A light path leaves an LED l (chosen with q_l ∝ Φ_l) in a direction drawn ∝ I(θ) and hits y_1 — exactly
the tracer's light vertex (:func:`tofcore.tracer.light_paths.trace_light_vertices`), with throughput
α_1 = Φ_l/q_l (times cos_s/cos_g, one without shading normals). At each y_j the BSDF is sampled with
ω_o = the direction the light came from (:func:`tofcore.scene.bsdf.sample_bsdf`; the BSDF is
reciprocal), α_{j+1} = α_j f cosθ / p. Every y_j connects to the lens:

.. math:: \hat I_p = \frac1{N} \sum_{i=1}^{N} \sum_j \alpha_{i,j}\, f(y_j;\, \omega_{lens}, \omega_{prev})\,
          W_p(y_j)\, V(y_j, \text{lens})

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
from tofcore.scene.bsdf import eval_bsdf, sample_bsdf
from tofcore.tracer import sampler as dims
from tofcore.tracer.light_paths import trace_light_vertices
from tofcore.tracer.sampler import Sampler
from tofcore.tracer.surface import dot, point_offset, rotate, shadow_ray, spawn_offset, surface_at
from tofcore.tracer.transport import TraceStats

from classify import GLOSSY_MAX_RAD, ClassSums, specular_share

GROUP = 1024
"""Light paths per group of the sampler: path i is sample i mod GROUP of "pixel" i // GROUP, so each group's
emission directions and bounces are one scrambled Sobol' net (or plain uniforms with ``independent``)."""


@dataclass(frozen=True)
class Importance:
    """Where light-vertex connections land: flat pixel index (−1 outside the image) and W_p (1/m²)."""

    pixel: np.ndarray
    weight: np.ndarray


def camera_importance(camera, points_sensor: np.ndarray, cos_y: np.ndarray) -> Importance:
    """W_p(y) of a pinhole camera for points y (sensor frame, metres) whose surface cosine towards the
    lens is ``cos_y`` (see the module docstring); 0 behind the lens, outside the image or for cos_y ≤ 0."""
    if camera.aperture_radius_m > 0:
        raise ValueError("camera_importance: pinhole cameras only (aperture_radius_m = 0), "
                         f"got {camera.aperture_radius_m!r}")
    p = np.asarray(points_sensor, np.float64)
    r2 = (p * p).sum(axis=1)
    front = (p[:, 2] > 0) & (cos_y > 0)
    z = np.where(front, p[:, 2], 1.0)
    x, y = p[:, 0] / z, p[:, 1] / z
    uv = camera.project(np.where(front[:, None], p, [0.0, 0.0, 1.0]))
    u = np.where(np.isfinite(uv[:, 0]), np.clip(uv[:, 0], -1.0, camera.width), -1.0)
    v = np.where(np.isfinite(uv[:, 1]), np.clip(uv[:, 1], -1.0, camera.height), -1.0)
    col, row = np.floor(u + 0.5).astype(np.int64), np.floor(v + 0.5).astype(np.int64)
    inside = front & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    if camera.has_distortion:  # far outside the image the polynomial folds back in: keep true round trips only
        xu, yu = camera.undistort((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy)
        inside &= np.hypot(xu - x, yu - y) <= 1e-6 * np.maximum(1.0, np.hypot(x, y))
    cos_theta = z / np.sqrt(r2)
    det = (np.abs(camera._jacobian_determinant(x, y)) if camera.has_distortion
           else np.ones(len(p)))
    weight = np.where(inside, camera.fx * camera.fy * det / cos_theta**3 * np.maximum(cos_y, 0.0) / r2, 0.0)
    return Importance(pixel=np.where(inside, row * camera.width + col, -1), weight=weight)


def check_light_tracing(setup) -> None:
    """Raise where the prototype does not hold: thin lenses, shading normals."""
    if setup.camera.aperture_radius_m > 0:
        raise ValueError("light tracing: pinhole cameras only")
    scene = setup.scene
    if scene.normals is not None or any(m.normal_texture is not None for m in scene.materials):
        raise ValueError(f"light tracing: scene {scene.name!r} has shading normals, which the prototype "
                         "does not model (no adjoint BSDF)")


def trace_light(setup, first: int, n_paths: int, *, caustic_only: bool = False,
                glossy_max_rad: float = GLOSSY_MAX_RAD) -> ClassSums:
    """Light paths ``first`` … ``first + n_paths − 1`` into per-class sums of the frame (classes of
    :func:`classify.class_names`; ``samples`` counts light paths: divide by the frame's total N).

    ``setup`` is a :class:`tofcore.tracer.setup.TraceSetup` (its sampler, seed and max_depth are used).
    """
    check_light_tracing(setup)
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
    for j in range(1, k_max + 1):
        corners = setup.table.vertices[setup.table.triangles[prim]]
        spawn = surf.position + surf.geometric_normal * spawn_offset(surf.position, surf.geometric_normal,
                                                                     corners)[:, None]
        if j > 1 or not caustic_only:
            _connect(setup, sums, j, surf, prim, spawn, to_prev, throughput, length, spec_share, first_material,
                     caustic_only, stats)
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
        new_dir = new_dir[alive] / np.linalg.norm(new_dir[alive], axis=1, keepdims=True)
        origin = spawn[alive]
        hits = setup.scene.bvh.intersect(origin.astype(np.float32), new_dir.astype(np.float32),
                                         ignore_prim=prim[alive], workers=1)
        hit = np.flatnonzero(hits.prim >= 0)
        rows = alive[hit]
        new_surf = surface_at(setup.scene, setup.table, hits.prim[hit], hits.u[hit], hits.v[hit], origin[hit],
                              new_dir[hit])
        length = length[rows] + np.linalg.norm(new_surf.position - surf.position[rows], axis=1)
        throughput = throughput[rows] * weight[rows]
        to_prev = -new_dir[hit]
        surf, prim = new_surf, hits.prim[hit]
        group, sample = group[rows], sample[rows]
        spec_share, first_material = spec_share[rows], first_material[rows]
        if len(rows) == 0:
            break
    return sums


def _connect(setup, sums: ClassSums, j: int, surf, prim, spawn, to_prev, throughput, length, spec_share,
             first_material, caustic_only: bool, stats: TraceStats) -> None:
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

