"""The arrays the compiled tracer reads, packed once per render from the NumPy tracer's context.

Everything here is plain NumPy (no compiler needed), so what the compiled path covers can be decided,
and explained, without numba: :func:`unsupported` names the first feature of a render that the
compiled kernels do not implement, and the tracer then runs the NumPy reference instead.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from ..backend import to_host
from ..sensor.modulation import (CorrelationBank, phasor_component, pulsed_correlation, sine_correlation,
                                square_correlation)
from . import layout


@dataclass(frozen=True, eq=False)
class Packed:
    """The compiled tracer's view of one render (arguments of :func:`tofcore.compiled.kernels.trace_path`)."""

    geo: tuple            # BVH records and scene arrays, see scene_arrays
    cam: np.ndarray       # (13,) camera numbers, see camera_arrays
    cam_table: np.ndarray  # (5, P) undistortion table (1 column when there is no distortion)
    frame: np.ndarray     # (5, 3) rotation, lens centre, LED axis
    leds: tuple           # (positions (L, 3), table (L, 5), cdf (L − 1,))
    corr_kinds: np.ndarray  # (J,) int64 channel kinds
    corr_table: np.ndarray  # (J, 6) float64 channel parameters
    key: np.uint64
    max_depth: int
    independent: bool
    light_paths: bool
    ambient: float        # constant ambient radiance, W/(m² sr) (0 without ambient light)


def unsupported(ctx) -> str:
    """Why the compiled tracer cannot render this trace context exactly as the NumPy one, or ""."""
    if ctx.ambient is not None and ctx.ambient.environment is not None and ctx.ambient.environment_strength > 0:
        return "ambient light from an environment map is not compiled yet (a constant ambient radiance is)"
    if ctx.transient_bins:
        return "transient histograms are not compiled yet"
    if ctx.table.has_textures:
        return "textured materials are not compiled yet"
    try:
        correlation_table(ctx.correlations)
    except TypeError as exc:
        return str(exc)
    return ""


def pack(ctx) -> Packed:
    """The arrays of a trace context that :func:`unsupported` accepts."""
    kinds, table = correlation_table(ctx.correlations)
    return Packed(geo=scene_arrays(ctx.scene, ctx.table), cam=camera_numbers(ctx.camera),
                  cam_table=camera_table(ctx.camera), frame=frame_array(ctx), leds=led_arrays(ctx),
                  corr_kinds=kinds, corr_table=table, key=np.uint64(ctx.sampler.key), max_depth=int(ctx.max_depth),
                  independent=ctx.sampler.kind == "independent", light_paths=bool(ctx.light_paths),
                  ambient=float(ctx.ambient.radiance_w_m2_sr) if ctx.ambient is not None else 0.0)


def scene_arrays(scene, table) -> tuple:
    """(node planes f32, node children i32, leaf vertices f32, leaf triangles i32, triangles, vertices,
    face normals, vertex normals ((0, 3) if none), material ids, material parameters (M, 5))."""
    bvh = scene.bvh
    nodes = np.ascontiguousarray(bvh._nodes)
    leaves = np.ascontiguousarray(bvh._leaves)
    normals = to_host(table.normals) if table.normals is not None else np.zeros((0, 3), np.float32)
    materials = np.stack([to_host(table.values[k]) for k in layout.MATERIAL_COLUMNS], axis=1)
    return (nodes.view(np.float32), nodes, leaves.view(np.float32), leaves,
            np.ascontiguousarray(to_host(table.triangles)), np.ascontiguousarray(to_host(table.vertices)),
            np.ascontiguousarray(to_host(table.face_normals)), np.ascontiguousarray(normals),
            np.ascontiguousarray(to_host(table.material_ids)), np.ascontiguousarray(materials, dtype=np.float64))


def camera_numbers(camera) -> np.ndarray:
    """(width, fx, fy, cx, cy, k1, k2, p1, p2, k3, aperture radius, focus distance, has distortion)."""
    return np.array([camera.width, camera.fx, camera.fy, camera.cx, camera.cy, camera.k1, camera.k2,
                     camera.p1, camera.p2, camera.k3, camera.aperture_radius_m, camera.focus_distance_m,
                     float(camera.has_distortion)], dtype=np.float64)


def camera_table(camera) -> np.ndarray:
    """(5, P) undistorted pixel centres and inverse Jacobians (Camera._centre_table), or (5, 1) zeros."""
    if not camera.has_distortion:
        return np.zeros((5, 1))
    return np.ascontiguousarray(np.stack(camera._centre_table))


def frame_array(ctx) -> np.ndarray:
    """(5, 3): world_from_sensor rotation (rows 0–2), lens centre and LED axis (scene frame). The ray offsets
    come from each point's own coordinates (kernels.point_offset, kernels.spawn_offset)."""
    frame = np.zeros((5, 3))
    frame[0:3] = ctx.world_from_sensor[:3, :3]
    frame[3] = to_host(ctx.lens_center)
    frame[4] = to_host(ctx.led_axis)
    return frame


def led_arrays(ctx) -> tuple:
    """(positions (L, 3) scene frame, table (L, 5): kind, intensity W/sr, power W, emission probability,
    first-hit shadow skipped; cdf (L − 1,) of the emission probabilities)."""
    q = np.asarray(ctx.led_probability, dtype=np.float64)
    table = np.array([[layout.LED_KINDS.index(led.kind), led.intensity_w_sr, led.power_w, q[i],
                       float(ctx.skip_first_shadow[i])] for i, led in enumerate(ctx.leds)], dtype=np.float64)
    return (np.ascontiguousarray(to_host(ctx.led_positions), dtype=np.float64), table,
            np.ascontiguousarray(np.cumsum(q)[:-1]))


def correlation_table(correlations) -> tuple[np.ndarray, np.ndarray]:
    """(kinds (J,), parameters (J, 6)) of a sensor's correlation bank or a list of known g_j.

    Raises TypeError naming a channel the kernels do not know (any callable other than the functions of
    :mod:`tofcore.modulation`).
    """
    if isinstance(correlations, CorrelationBank):
        functions = correlations.functions()
    else:
        functions = list(getattr(correlations, "functions", ()))
    kinds, rows = [], []
    for j, g in enumerate(functions):
        if not isinstance(g, functools.partial) or g.args:
            raise TypeError(f"correlation channel {j} ({g!r}) is not one of tofcore.modulation's functions")
        k = g.keywords
        if g.func is phasor_component:
            kinds.append(layout.PHASOR)
            rows.append([2.0 * np.pi * k["f_hz"], 0.5 * np.pi * k["quarter"], 0, 0, 0, 0])
        elif g.func is sine_correlation:
            kinds.append(layout.SINE)
            rows.append([k["f_hz"], k["offset_fraction"], 0, 0, 0, 0])
        elif g.func is square_correlation:
            duty = k["duty"]
            kinds.append(layout.SQUARE)
            rows.append([k["f_hz"], k["offset_fraction"], duty, max(0.0, duty - 0.5), min(duty, 0.5),
                         0.25 + 0.5 * duty])
        elif g.func is pulsed_correlation:
            kinds.append(layout.PULSED)
            rows.append([k["pulse_width_s"], k["bucket"], 0, 0, 0, 0])
        else:
            raise TypeError(f"correlation channel {j} ({g.func.__name__}) is not compiled")
    return np.array(kinds, dtype=np.int64), np.array(rows, dtype=np.float64).reshape(-1, 6)
