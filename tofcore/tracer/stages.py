r"""The stages of the path tracer, each a function of the path state and the set-up (pbrt-v4's wavefront).

For a path with throughput :math:`\beta_k = \prod f\cos\theta/p` after k − 1 sampled bounces, surface
vertex :math:`x_k` sends to the lens, per LED (thesis eq. 2.31 with eq. 2.8),

.. math:: w = \beta_k \, f(x_k, \omega_o, \omega_{LED}) \, |\cos\theta_{x_k}| \, I(\theta_{LED}) / d^2

at optical path length L = |LED → x_k| + |x_k → x_{k−1}| + … + |x_1 → lens|. The stages:

=====================  ============================================================================
:func:`camera_rays`    (pixel, sample) → rays through the pixel and the lens: the first state
:func:`intersect`      the next ray of every live path → its hit; misses see the ambient light and end
:func:`shade`          a hit → surface vertex k (position, frames, BSDF), the path length so far
:func:`next_event`     vertex k → every LED, shadow-tested: the contribution of bucket k
:func:`light_vertex`   vertex k → the sample's light vertex → its LED: bucket k + 1 (MIS weighted)
:func:`scatter`        vertex k → the BSDF's next direction, β updated; dead paths leave the state
=====================  ============================================================================

:func:`first_hit` traces the noise-free ground truth (one ray through each pixel centre).
"""

from __future__ import annotations

import time

import numpy as np

from .. import backend
from ..constants import SPEED_OF_LIGHT_M_S
from ..scene.bsdf import eval_bsdf, sample_bsdf
from ..scene.bvh import Hits
from . import sampler
from .estimator import bsdf_strategy_weight
from .light_paths import LightVertices, connect
from .path import Contribution, PathState, Vertex
from .setup import TraceSetup
from .surface import dot, leaving, point_offset, rotate, shadow_ray, spawn_offset, surface_at, surface_geometry
from .transport import FirstHit, TraceStats


def first_hit(setup: TraceSetup, stats: TraceStats) -> FirstHit:
    """Trace the pixel-centre rays on the tracing device; the buffers come back as NumPy arrays."""
    xp = setup.xp
    d = pixel_centre_directions(setup)
    n = len(d)
    origin = xp.broadcast_to(setup.lens_center, (n, 3))
    hits = setup.scene.bvh.intersect(leaving(origin, d), d.astype(np.float32))
    stats.camera_rays += n
    hit = hits.prim >= 0
    # Every pixel's ray through the same arithmetic (a miss's on triangle 0, then masked): no boolean indexing,
    # which on the GPU is a host round trip per mask, and no `hit.any()` (one more, and a CUB reduction that
    # NVRTC compiles for 1.5–2 s per array size in a fresh cache). A hit's numbers are those of its own row.
    prim = xp.where(hit, hits.prim, 0)
    with np.errstate(invalid="ignore"):
        point, facing_normal = surface_geometry(setup.table, prim, hits.u, hits.v, origin, d)
    return first_hit_record(setup, d, hit, prim, point, facing_normal)


def pixel_centre_directions(setup: TraceSetup):
    """(H·W, 3) float64 unit directions of the rays through the pixel centres, in the scene frame."""
    return rotate(setup.xp.asarray(setup.camera.pixel_center_directions().reshape(-1, 3).astype(np.float64)),
                  setup.rotation)


def first_hit_record(setup: TraceSetup, d, hit, prim, point, facing_normal) -> FirstHit:
    """The :class:`FirstHit` of the pixel-centre rays ``d`` from their hits: ``hit`` (R,) bool, ``prim`` the
    triangle (any valid index where ``hit`` is False), the float64 ``point`` (scene frame) and ``facing_normal``
    (R, 3) (anything finite or not where ``hit`` is False: masked here)."""
    xp = setup.xp
    with np.errstate(invalid="ignore"):
        distance = xp.where(hit, xp.linalg.norm(point - setup.lens_center, axis=1), np.nan)
        position = xp.where(hit[:, None], (point + xp.asarray(setup.scene.origin_m)).astype(np.float32),
                            np.float32(np.nan))  # world frame
        normal = xp.where(hit[:, None], facing_normal.astype(np.float32), np.float32(np.nan))
    material = xp.where(hit, setup.table.material_ids[prim], np.int32(-1)).astype(np.int32)
    obj = xp.where(hit, setup.table.object_ids[prim], np.int32(-1)).astype(np.int32)
    shape = (setup.camera.height, setup.camera.width)
    host = backend.to_host
    return FirstHit(distance_m=host(distance).reshape(shape), position_m=host(position).reshape(shape + (3,)),
                    normal=host(normal).reshape(shape + (3,)), material_id=host(material).reshape(shape),
                    object_id=host(obj).reshape(shape), direction=host(d).astype(np.float32).reshape(shape + (3,)))


def camera_rays(setup: TraceSetup, pixel, sample) -> PathState:
    """The first state: one path per (pixel, sample), its ray through the pixel and the lens (scene frame)."""
    xp, draw = setup.xp, setup.sampler
    n = len(pixel)
    pixel_u, pixel_v = draw.get_2d(pixel, sample, sampler.PIXEL)
    lens_u, lens_v = draw.get_2d(pixel, sample, sampler.LENS)
    o_s, d_s = setup.camera.generate_rays(pixel, pixel_u, pixel_v, lens_u, lens_v)
    origin = rotate(o_s, setup.rotation) + setup.lens_center
    return PathState(path=xp.arange(n), pixel=pixel, sample=sample, throughput=xp.ones(n), length=xp.zeros(n),
                     origin=origin, direction=rotate(d_s, setup.rotation), prev_point=origin,
                     prev_prim=xp.full(n, -1, np.int32), prev_pdf=xp.zeros(n), prev_delta=xp.zeros(n, dtype=bool))


def intersect(setup: TraceSetup, state: PathState, k: int, stats: TraceStats) -> tuple[PathState, Hits, tuple | None]:
    """Trace the next ray of every path: (paths that hit, their hits, ambient (rows, radiance) of misses or None).

    A missed ray sees the ambient light, β · L_amb(ω), which goes to the path's ambient total.
    """
    clock = time.perf_counter()
    query = leaving(state.origin, state.direction) if k == 1 else state.origin.astype(np.float32)
    hits = setup.scene.bvh.intersect(query, state.direction.astype(np.float32), ignore_prim=state.prev_prim,
                                     workers=1)
    if k == 1:
        stats.camera_rays += len(state)
        stats.camera_seconds += time.perf_counter() - clock
    else:
        stats.bounce_rays += len(state)
        stats.bounce_seconds += time.perf_counter() - clock
    hit = hits.prim >= 0
    ambient = None
    if setup.ambient is not None and not hit.all():
        miss = ~hit
        ambient = (state.path[miss], state.throughput[miss] * setup.ambient.radiance(state.direction[miss]))
    keep = np.flatnonzero(hit)
    return state.take(keep), Hits(t=hits.t[keep], prim=hits.prim[keep], u=hits.u[keep], v=hits.v[keep]), ambient


def shade(setup: TraceSetup, state: PathState, hits: Hits, k: int) -> tuple[PathState, Vertex]:
    """Surface vertex k of the paths: its geometry and BSDF, the path length to it, the ray-leaving point."""
    surf = surface_at(setup.scene, setup.table, hits.prim, hits.u, hits.v, state.origin, state.direction)
    segment = np.linalg.norm(surf.position - state.prev_point, axis=1)
    # Area density at this vertex of having sampled it from the previous one (MIS with light vertices).
    area_pdf = (state.prev_pdf * dot(-state.direction, surf.geometric_normal) / segment**2
                if setup.light_paths and k >= 2 else None)
    corners = setup.table.vertices[setup.table.triangles[hits.prim]]      # (N, 3, 3) the hit triangles, for the offset
    offset = spawn_offset(surf.position, surf.geometric_normal, corners)
    vertex = Vertex(k=k, surface=surf, prim=hits.prim, wo=surf.to_local(-state.direction),
                    spawn=surf.position + surf.geometric_normal * offset[:, None], area_pdf=area_pdf)
    return state.replace(length=state.length + segment), vertex


def next_event(setup: TraceSetup, state: PathState, vertex: Vertex, stats: TraceStats) -> Contribution:
    """Next-event estimation from vertex k to every LED, summed per path in LED order (bucket k)."""
    xp = setup.xp
    w_sum = xp.zeros(len(state))
    wg_sum = xp.zeros((setup.n_channels, len(state)))
    transient = []
    for i in range(len(setup.leds)):
        w, led_distance = _to_led(setup, state, vertex, i, stats)
        total_length = state.length + led_distance
        transient.append((w, total_length))
        w_sum += w
        if setup.n_channels:
            wg = setup.correlations(total_length / SPEED_OF_LIGHT_M_S)
            wg *= w
            wg_sum += wg
    return Contribution(k=vertex.k, weight=w_sum, correlation=wg_sum, transient=tuple(transient))


def _to_led(setup: TraceSetup, state: PathState, vertex: Vertex, i: int, stats: TraceStats):
    """Next-event estimate to LED ``i``: (weight w per path, distance hit point → LED).

    With light vertices on, w carries strategy A's MIS weight (:func:`~tofcore.tracer.estimator.bsdf_strategy_weight`).
    """
    surf, led = vertex.surface, setup.leds[i]
    to_led = setup.led_positions[i] - surf.position
    dist = np.linalg.norm(to_led, axis=1)
    wi_world = to_led / dist[:, None]
    cos_geo = dot(wi_world, surf.geometric_normal)
    cos_shading = dot(wi_world, surf.shading_normal)
    cos_axis = -dot(wi_world, setup.led_axis[None, :])
    intensity = led.intensity(cos_axis)
    f = eval_bsdf(surf.params, vertex.wo, surf.to_local(wi_world))
    w = state.throughput * f * np.maximum(cos_shading, 0.0) * intensity / dist**2
    w = np.where(cos_geo > 0, w, 0.0)
    if vertex.area_pdf is not None:
        w = w * bsdf_strategy_weight(vertex.area_pdf, state.prev_delta, led, float(setup.led_probability[i]),
                                     cos_axis, cos_geo, dist)
    test = np.flatnonzero(w > 0)
    if vertex.k == 1 and setup.skip_first_shadow[i]:
        stats.skipped_shadow_rays += len(test)
    elif len(test):
        clock = time.perf_counter()
        margin = point_offset(setup.led_positions[i][None])  # stop short of the LED (flush with a wall)
        blocked = setup.scene.bvh.occluded(*shadow_ray(vertex.spawn[test], setup.led_positions[i], margin),
                                           ignore_prim=vertex.prim[test], workers=1)
        stats.shadow_rays += len(test)
        stats.shadow_seconds += time.perf_counter() - clock
        w[test[blocked]] = 0.0
    return w, dist


def light_vertex(setup: TraceSetup, state: PathState, vertex: Vertex, light: LightVertices,
                 stats: TraceStats) -> Contribution:
    """Vertex k → the sample's light vertex → its LED: k + 1 surface vertices (:mod:`.light_paths`)."""
    w, extra = connect(setup, state, vertex, light, stats)
    total_length = state.length + extra
    wg = None
    if setup.n_channels:
        wg = setup.correlations(total_length / SPEED_OF_LIGHT_M_S)
        wg *= w
    return Contribution(k=vertex.k + 1, weight=w, correlation=wg, transient=((w, total_length),))


def scatter(setup: TraceSetup, state: PathState, vertex: Vertex) -> PathState:
    """Sample the BSDF at vertex k for the next direction; β ← β f cosθ / p. Paths with zero weight end.

    A direction below the geometric surface would leak through it (shading normals): that path ends too.
    """
    draw, surf = setup.sampler, vertex.surface
    u1, u2 = draw.get_2d(state.pixel, state.sample, sampler.direction(vertex.k))
    u_lobe = draw.get_1d(state.pixel, state.sample, sampler.lobe(vertex.k))
    bs = sample_bsdf(surf.params, vertex.wo, u_lobe, u1, u2)
    new_dir = surf.to_world(bs.wi)
    keep = np.flatnonzero((bs.weight > 0) & (dot(new_dir, surf.geometric_normal) > 0))
    new_dir = new_dir[keep]
    return state.take(keep, throughput=state.throughput[keep] * bs.weight[keep], prev_pdf=bs.pdf[keep],
                      prev_delta=bs.is_delta[keep], prev_prim=vertex.prim[keep], prev_point=surf.position[keep],
                      origin=vertex.spawn[keep], direction=new_dir / np.linalg.norm(new_dir, axis=1, keepdims=True))
