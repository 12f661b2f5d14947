"""What a simulated ToF camera delivers for one frame: :class:`Frame`.

Images are (H, W), row 0 at the top, float32 unless noted. Where a pixel has
no valid depth, ``depth`` and ``distance`` are NaN, ``valid`` is False and
``reason`` (:class:`Reason`) says why; the IR measurements (``amplitude``,
``offset``, ``intensity``, ``raw``) stay defined everywhere — a saturated or
out-of-range pixel still has an IR value.

=====================  ==============  ==========================================================
field                  unit            meaning
=====================  ==============  ==========================================================
``depth``              m               the sensor's depth output: radial distance or z-depth
                                       (``depth_output`` of the sensor), NaN where invalid
``distance``           m               decoded radial distance lens → surface, NaN where invalid
``amplitude``          e⁻ (electrons)  modulation amplitude A of the highest frequency (eq. 2.40)
``offset``             e⁻              offset B of the highest frequency (eq. 2.41)
``intensity``          e⁻              IR image: mean charge of all raw images (B for CW)
``valid``              bool            pixel has a depth
``reason``             uint8           0 valid, else a :class:`Reason` code
``confidence``         1               unwrapping/decoding confidence in [0, 1]
``raw``                e⁻              (R, H, W) raw images after scattering and noise, R = frequencies × steps
``raw_labels``         –               R names, e.g. ``"f80MHz_s0"``
``gt_distance``        m               noise-free first-hit radial distance (NaN where no surface)
``gt_depth``           m               the same in the sensor's depth output
``direct_distance``    m               decoded distance from the k = 1 bucket only (no multipath,
                                       no noise, no scattering); None in a preview frame
``distance_per_k``     m               (K, H, W) decoded distance using bounces ≤ k, k = 1..K
                                       (noise-free): the §6.3.1 study from one render; None in a
                                       preview frame (``render_progressive(preview_frames=True)``
                                       before its final pass: K decodes a display does not show)
``ray_directions``     1               (H, W, 3) unit pixel-centre ray directions, sensor frame
``object_id``          –               (H, W) int32 first-hit object, −1 where none
``material_id``        –               (H, W) int32 first-hit material (index into the scene's materials),
                                       −1 where none; None in frames made before it existed
``normal``             1               (H, W, 3) float32 first-hit geometric normal, world frame, facing
                                       the camera; NaN where none; None in frames made before it existed
``render_error``       m               (H, W) estimated Monte Carlo standard error of ``depth`` (the
                                       render's own noise, before sensor noise), NaN where unknown
``samples``            –               (H, W) int samples traced per pixel (adaptive sampling varies it)
``unwrap_flip``        –               (H, W) uint8 1 where the render's replicates unwrap to different
                                       ambiguity intervals (an error of a whole wrap is possible there,
                                       which ``render_error`` does not describe); share and count in
                                       ``stats["convergence"]`` (``unwrap_flip_share``, ``unwrap_flips``)
``transient``          W m⁻² sr⁻¹      (H, W, B) float32 transient histogram: mean radiance at the lens per
                                       optical-path-length bin, bin b centred at (b + ½)·``transient_bin_m``;
                                       None unless asked for (``render(transient_bin_m=…)``)
``transient_bin_m``    m               bin width of ``transient`` (optical path length LED → … → lens)
``stats``              –               dict: time, rays, spp, plan, convergence log, …
=====================  ==============  ==========================================================
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..sensor.decode import Reason


@dataclass(eq=False)
class Frame:
    """One simulated ToF frame; see the module docstring for the fields."""

    depth: np.ndarray
    distance: np.ndarray
    amplitude: np.ndarray
    offset: np.ndarray
    intensity: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    confidence: np.ndarray
    raw: np.ndarray
    raw_labels: tuple[str, ...]
    gt_distance: np.ndarray
    gt_depth: np.ndarray
    direct_distance: np.ndarray | None
    distance_per_k: np.ndarray | None
    ray_directions: np.ndarray
    object_id: np.ndarray
    depth_output: str = "radial"
    world_from_sensor: np.ndarray = field(default_factory=lambda: np.eye(4))
    render_error: np.ndarray | None = None
    samples: np.ndarray | None = None
    unwrap_flip: np.ndarray | None = None
    transient: np.ndarray | None = None
    transient_bin_m: float | None = None
    material_id: np.ndarray | None = None
    normal: np.ndarray | None = None
    stats: dict = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)

    @property
    def height(self) -> int:
        return self.depth.shape[0]

    @property
    def width(self) -> int:
        return self.depth.shape[1]

    def points(self, frame: str = "sensor", valid_only: bool = True) -> np.ndarray:
        """Point cloud (N, 3) float32 in metres from the decoded radial distance.

        Parameters
        ----------
        frame : ``"sensor"`` (OpenCV: x right, y down, z forward) or ``"world"``.
        valid_only : drop invalid pixels (else they are NaN rows, in image order).
        """
        if frame not in ("sensor", "world"):
            raise ValueError(f"Frame.points: frame must be 'sensor' or 'world', got {frame!r}")
        pts = (self.ray_directions * self.distance[..., None]).reshape(-1, 3).astype(np.float64)
        if frame == "world":
            pts = pts @ self.world_from_sensor[:3, :3].T + self.world_from_sensor[:3, 3]
        if valid_only:
            pts = pts[self.valid.reshape(-1)]
        return pts.astype(np.float32)
