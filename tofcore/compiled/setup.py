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
from ..scene.camera import shared_centre_rows
from ..sensor.modulation import (CorrelationBank, harmonic_correlation, phasor_component, pulsed_correlation,
                                sine_correlation, square_correlation, tabulated_correlation)
from . import layout


@dataclass(frozen=True, eq=False)
class Packed:
    """The compiled tracer's view of one render (arguments of :func:`tofcore.compiled.kernels.trace_path`)."""

    geo: tuple            # BVH records, scene arrays and textures, see scene_arrays
    cam: np.ndarray       # (13,) camera numbers, see camera_arrays
    cam_table: np.ndarray  # (5, P) undistortion table (1 column when there is no distortion)
    frame: np.ndarray     # (5, 3) rotation, lens centre, LED axis
    leds: tuple           # (positions (L, 3), table (L, 5), cdf (L − 1,))
    corr_kinds: np.ndarray  # (J,) int64 channel kinds
    corr_table: np.ndarray  # (J, 6) float64 channel parameters
    corr_data: np.ndarray   # (≥ 1,) float64 coefficients of the HARMONIC and TABLE channels
    sky: np.ndarray       # (2,): the environment map's strength (float32) and texture index (−1: none)
    key: np.uint64
    max_depth: int
    independent: bool
    light_paths: bool
    ambient: float        # constant ambient radiance, W/(m² sr) (0 without ambient light)
    transient_bin_m: float  # bin width of the transient histogram, metres (0: none)

    def scene(self) -> tuple:
        """The kernels' ``scene`` tuple (kernels.trace_path)."""
        return (self.geo, self.cam, self.cam_table, self.frame, self.leds, self.corr_kinds, self.corr_table,
                self.corr_data, self.sky)

    def settings(self) -> tuple:
        """The kernels' ``settings`` tuple (kernels.trace_path)."""
        return (self.key, int(self.max_depth), bool(self.independent), bool(self.light_paths), float(self.ambient),
                float(self.transient_bin_m))


def unsupported(ctx) -> str:
    """Why the compiled tracer cannot render this trace context exactly as the NumPy one, or "".

    Every scene, material, texture, ambient light, histogram and sensor the add-on and the presets make
    compiles; what remains is a correlation channel given as Python code rather than data."""
    try:
        correlation_table(ctx.correlations)
    except TypeError as exc:
        return str(exc)
    return ""


def pack(ctx) -> Packed:
    """The arrays of a trace context that :func:`unsupported` accepts."""
    kinds, table, data = correlation_table(ctx.correlations)
    environment = ctx.ambient.environment if ctx.ambient is not None and ctx.ambient.environment_strength > 0 \
        else None
    slots, textures, sky_index = texture_store(ctx.scene.materials, environment)
    strength = float(np.float32(ctx.ambient.environment_strength)) if environment is not None else 0.0
    return Packed(geo=scene_arrays(ctx.scene, ctx.table) + (uv_array(ctx.scene), slots) + textures,
                  cam=camera_numbers(ctx.camera), cam_table=camera_table(ctx.camera), frame=frame_array(ctx),
                  leds=led_arrays(ctx), corr_kinds=kinds, corr_table=table, corr_data=data,
                  sky=np.array([strength, float(sky_index)]), key=np.uint64(ctx.sampler.key),
                  max_depth=int(ctx.max_depth), independent=ctx.sampler.kind == "independent",
                  light_paths=bool(ctx.light_paths),
                  ambient=float(ctx.ambient.radiance_w_m2_sr) if ctx.ambient is not None else 0.0,
                  transient_bin_m=float(ctx.transient_bin_m) if ctx.transient_bins else 0.0)


def scene_arrays(scene, table) -> tuple:
    """(node planes f32, node children i32, leaf vertices f32, leaf triangles i32, triangles, vertices,
    face normals, vertex normals ((0, 3) if none), material ids, material parameters (M, 5)); :func:`pack`
    appends the UVs, the texture slots and the texture store (geo[10:14])."""
    bvh = scene.bvh
    nodes = np.ascontiguousarray(bvh._nodes)
    leaves = np.ascontiguousarray(bvh._leaves)
    normals = to_host(table.normals) if table.normals is not None else np.zeros((0, 3), np.float32)
    materials = np.stack([to_host(table.values[k]) for k in layout.MATERIAL_COLUMNS], axis=1)
    return (nodes.view(np.float32), nodes, leaves.view(np.float32), leaves,
            np.ascontiguousarray(to_host(table.triangles)), np.ascontiguousarray(to_host(table.vertices)),
            np.ascontiguousarray(to_host(table.face_normals)), np.ascontiguousarray(normals),
            np.ascontiguousarray(to_host(table.material_ids)), np.ascontiguousarray(materials, dtype=np.float64))


def uv_array(scene) -> np.ndarray:
    """(V, 2) float32 texture coordinates ((1, 2) zeros where the scene has none: no texture reads them)."""
    if scene.uvs is None:
        return np.zeros((1, 2), np.float32)
    return np.ascontiguousarray(scene.uvs, dtype=np.float32)


def texture_store(materials, environment) -> tuple[np.ndarray, tuple, int]:
    """(slots (M, 4) int64, (table (T, 4) int64, data float32), environment's index or −1).

    Each image once, in one float32 array (kernels.texture_sample reads it): row t of the table is
    image t's (offset into data, height, width, channels); row m of the slots names material m's
    textures in :data:`layout.TEXTURE_SLOTS` order (−1: none). A texture shared by materials is stored once.
    """
    images: list[np.ndarray] = []
    index: dict[int, int] = {}

    def add(texture) -> int:
        if texture is None:
            return -1
        if id(texture) not in index:
            index[id(texture)] = len(images)
            images.append(np.asarray(texture.data, dtype=np.float32))
        return index[id(texture)]

    slots = np.array([[add(getattr(m, name)) for name in layout.TEXTURE_SLOTS] for m in materials],
                     dtype=np.int64).reshape(-1, len(layout.TEXTURE_SLOTS))
    sky = add(environment)
    table = np.zeros((max(len(images), 1), 4), np.int64)
    offset = 0
    for t, image in enumerate(images):
        table[t] = (offset, image.shape[0], image.shape[1], 1 if image.ndim == 2 else image.shape[2])
        offset += image.size
    data = np.concatenate([image.ravel() for image in images]) if images else np.zeros(1, np.float32)
    return slots, (table, np.ascontiguousarray(data, dtype=np.float32)), sky


def camera_numbers(camera) -> np.ndarray:
    """(width, fx, fy, cx, cy, k1, k2, p1, p2, k3, aperture radius, focus distance, has distortion)."""
    return np.array([camera.width, camera.fx, camera.fy, camera.cx, camera.cy, camera.k1, camera.k2,
                     camera.p1, camera.p2, camera.k3, camera.aperture_radius_m, camera.focus_distance_m,
                     float(camera.has_distortion)], dtype=np.float64)


def camera_table(camera) -> np.ndarray:
    """(5, P) undistorted pixel centres and inverse Jacobians (Camera._centre_table), or (5, 1) zeros; the
    same array (never written) for equal cameras (:func:`tofcore.scene.camera.shared_centre_rows`)."""
    if not camera.has_distortion:
        return np.zeros((5, 1))
    return shared_centre_rows(camera)


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
    rows = []
    for i, led in enumerate(ctx.leds):
        values = {"kind": layout.LED_KINDS.index(led.kind), "intensity_w_sr": led.intensity_w_sr,
                  "power_w": led.power_w, "probability": q[i], "skip_first_shadow": float(ctx.skip_first_shadow[i])}
        rows.append([values[name] for name in layout.LED_COLUMNS])  # the named columns, in the kernels' order
    table = np.array(rows, dtype=np.float64)
    return (np.ascontiguousarray(to_host(ctx.led_positions), dtype=np.float64), table,
            np.ascontiguousarray(np.cumsum(q)[:-1]))


@dataclass(frozen=True)
class CorrelationKind:
    """One row of :data:`CORRELATION_KINDS`: how a reference g_j of :mod:`tofcore.sensor.modulation` becomes a
    row of the kernels' channel table (kernels.correlation reads ``par[i]`` as ``columns[i]``)."""

    code: int           # layout.PHASOR …
    columns: tuple      # the names of its row's values, in order (at most 6)
    row: object         # keywords of the partial → (row values, coefficients for the shared data array)


def _quarter_turn(quarter) -> tuple[float, float]:
    """(cos qπ/2, sin qπ/2) of a phasor channel's ``quarter`` q (kernels.channel_value): exact (0, ±1) for a
    whole number of quarter turns (the phasor's cos and sin channels), else from the angle."""
    if float(quarter).is_integer():
        return ((1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0))[int(quarter) % 4]
    return float(np.cos(0.5 * np.pi * quarter)), float(np.sin(0.5 * np.pi * quarter))


def _square_row(k: dict) -> tuple:
    duty = k["duty"]
    return [k["f_hz"], k["offset_fraction"], duty, max(0.0, duty - 0.5), min(duty, 0.5), 0.25 + 0.5 * duty], []


CORRELATION_KINDS = {
    phasor_component: CorrelationKind(layout.PHASOR, ("2πf", "qπ/2", "cos qπ/2", "sin qπ/2"), lambda k: (
        [2.0 * np.pi * k["f_hz"], 0.5 * np.pi * k["quarter"], *_quarter_turn(k["quarter"])], [])),
    sine_correlation: CorrelationKind(layout.SINE, ("f", "k/N"), lambda k: ([k["f_hz"], k["offset_fraction"]], [])),
    square_correlation: CorrelationKind(layout.SQUARE, ("f", "k/N", "D", "lower clip", "upper clip", "¼ + D/2"),
                                        _square_row),
    pulsed_correlation: CorrelationKind(layout.PULSED, ("t0", "bucket"),
                                        lambda k: ([k["pulse_width_s"], k["bucket"]], [])),
    harmonic_correlation: CorrelationKind(layout.HARMONIC, ("2πf", "first coefficient", "N"), lambda k: (
        [2.0 * np.pi * k["f_hz"], None, len(k["sin_terms"])], [*k["cos_terms"], *k["sin_terms"]])),
    tabulated_correlation: CorrelationKind(layout.TABLE, ("T", "first value", "M"), lambda k: (
        [k["period_s"], None, len(k["values"])], list(k["values"]))),
}
"""The correlation functions the kernels compute, by reference function: the one table from which
:func:`correlation_table` (and so :func:`unsupported`) derives. ``None`` in a row is filled with the
index of the row's first coefficient in the shared data array. A new kind is one row here, its code in
:mod:`.layout` and its formula in kernels.correlation."""

_CODE_ONLY = ("is Python code the compiled tracer cannot run; give a custom waveform as data "
              "(tofcore.sensor.modulation.harmonic or .tabulate) to trace it compiled")


def correlation_table(correlations) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(kinds (J,), parameters (J, 6), coefficients (≥ 1,)) of a sensor's correlation bank or a list of g_j
    (:data:`CORRELATION_KINDS`).

    Raises TypeError naming a channel the kernels do not know: a callable other than the functions of
    :mod:`tofcore.sensor.modulation` (custom waveforms compile as data: ``modulation.harmonic`` or
    ``modulation.tabulate``).
    """
    if isinstance(correlations, CorrelationBank):
        functions = correlations.functions()
    else:
        functions = list(getattr(correlations, "functions", ()))
    kinds, rows, data = [], [], []
    for j, g in enumerate(functions):
        kind = CORRELATION_KINDS.get(g.func) if isinstance(g, functools.partial) and not g.args else None
        if kind is None:
            name = getattr(getattr(g, "func", g), "__name__", type(g).__name__)
            raise TypeError(f"correlation channel {j} ({name}) {_CODE_ONLY}")
        values, coefficients = kind.row(g.keywords)
        row = [len(data) if v is None else v for v in values]
        kinds.append(kind.code)
        rows.append(row + [0.0] * (6 - len(row)))
        data.extend(coefficients)
    return (np.array(kinds, dtype=np.int64), np.array(rows, dtype=np.float64).reshape(-1, 6),
            np.array(data or [0.0], dtype=np.float64))
