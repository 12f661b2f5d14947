"""What the stages of the tracer pass on: the path state, a surface vertex, and a contribution.

The state is a structure of arrays, one row per live path of a chunk (pbrt-v4's wavefront ``SOA`` queues).
Paths that end leave the state through :meth:`PathState.take` (compaction), so every stage works on live
paths only. A path keeps two indices: ``path``, its row in the chunk's per-path tallies (the replicate
sums), and ``pixel``, the frame pixel it belongs to; ``sample`` is its sample index in that pixel.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .surface import Surface


@dataclass(frozen=True)
class PathState:
    """The live paths of a chunk (N rows) between two stages; see the module docstring."""

    path: np.ndarray        # (N,) int64 row of the path in the chunk's tallies
    pixel: np.ndarray       # (N,) int64 flat pixel index in the frame
    sample: np.ndarray      # (N,) int64 sample index within the pixel
    throughput: np.ndarray  # (N,) float64 β = Π f cosθ / pdf of the bounces so far
    length: np.ndarray      # (N,) float64 metres travelled from the lens to the last vertex
    origin: np.ndarray      # (N, 3) float64 next ray's origin, scene frame
    direction: np.ndarray   # (N, 3) float64 next ray's unit direction
    prev_point: np.ndarray  # (N, 3) float64 true position of the last vertex (the lens point first)
    prev_prim: np.ndarray   # (N,) int32 triangle the next ray leaves (never hit again), −1 none
    prev_pdf: np.ndarray    # (N,) float64 solid-angle pdf of the bounce that made the next ray
    prev_delta: np.ndarray  # (N,) bool that bounce was a mirror (delta) lobe

    def __len__(self) -> int:
        return len(self.path)

    def take(self, index, **new) -> PathState:
        """The paths ``index`` (an integer array of rows), every field compacted alike; fields given in ``new``
        are already the new values of those rows (a stage's update, not gathered again)."""
        return PathState(**{f.name: new[f.name] if f.name in new else getattr(self, f.name)[index]
                            for f in dataclasses.fields(self)})

    def replace(self, **fields) -> PathState:
        return dataclasses.replace(self, **fields)


@dataclass(frozen=True)
class Vertex:
    """Surface vertex k of the live paths (one row per row of the state): where the stages shade."""

    k: int                    # surface vertices of the path so far (1 = first hit)
    surface: Surface          # position, frames, BSDF parameters (:func:`~tofcore.tracer.surface.surface_at`)
    prim: np.ndarray          # (N,) int32 triangle hit
    wo: np.ndarray            # (N, 3) direction back along the ray, shading frame
    spawn: np.ndarray         # (N, 3) origin for rays leaving the vertex (off the surface)
    area_pdf: np.ndarray | None  # (N,) p_A: area density of reaching it by the previous bounce (MIS), or None


@dataclass(frozen=True)
class Contribution:
    """Light that reaches the lens along the live paths through ``k`` surface vertices (bucket k).

    ``weight`` is w per path (W m⁻² sr⁻¹); ``correlation`` the J products w·g_j(L/c) or None without
    channels; ``transient`` the (w, L) pairs to histogram, one per light source, in the order summed.
    """

    k: int
    weight: np.ndarray
    correlation: np.ndarray | None
    transient: tuple[tuple[np.ndarray, np.ndarray], ...] = ()
