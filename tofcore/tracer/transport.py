"""What a trace hands back: the accumulated :class:`Transport` of a frame, its :class:`FirstHit` ground truth
and its :class:`TraceStats`.

Per pixel and per bounce bucket k the sums hold Σw and Σw·g_j(L/c) for the sensor's correlation functions
(DESIGN.md "path-length bucketing"), the unmodulated ambient radiance apart from them, the per-replicate
channel totals of the error estimate and, optionally, a transient histogram over path length. The means
and the replicates' statistics are its methods; :mod:`tofcore.tracer.accumulate` fills the sums.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..backend import namespace
from ..errors import ConfigError
from . import estimator


@dataclass(frozen=True)
class FirstHit:
    """Noise-free ground truth from one ray through each pixel centre (pinhole at the lens centre).

    Misses: NaN distances/positions/normals, ids −1.
    """

    distance_m: np.ndarray   # (H, W) float64, radial distance lens → surface
    position_m: np.ndarray   # (H, W, 3) float32, world frame
    normal: np.ndarray       # (H, W, 3) float32, world frame, facing the camera
    material_id: np.ndarray  # (H, W) int32
    object_id: np.ndarray    # (H, W) int32
    direction: np.ndarray    # (H, W, 3) float32, world-frame unit ray directions


@dataclass
class TraceStats:
    """Counters of one trace."""

    camera_rays: int = 0
    bounce_rays: int = 0
    shadow_rays: int = 0
    seconds: float = 0.0
    passes: int = 0
    light_rays: int = 0           # rays from the LEDs to their first hit (light vertices)
    skipped_shadow_rays: int = 0  # first-hit shadow rays known to be unoccluded (LED at a pinhole)
    camera_seconds: float = 0.0   # thread-seconds inside the BVH for each kind of ray
    bounce_seconds: float = 0.0
    shadow_seconds: float = 0.0
    chunk_seconds: float = 0.0    # thread-seconds inside chunks (all tracing work, summed over workers)
    setup_seconds: float = 0.0    # wall time before the first pass: first-hit buffers, sharing, worker start
    parallel: str = ""            # how chunks ran: "processes", "threads: <why>" or "one"
    tracer: str = "numpy"         # "compiled" (tofcore.compiled) or "numpy" (this module)
    tracer_reason: str = ""       # why the NumPy tracer ran where numba is installed, or is not
    compile: str = ""             # how a cancellable trace got uncached CPU kernels (tofcore.compiled.child_compile)

    @property
    def rays(self) -> int:
        return self.camera_rays + self.bounce_rays + self.shadow_rays + self.light_rays

    def add(self, other: TraceStats) -> None:
        """Add the ray counters and BVH times of a chunk (not ``seconds`` or ``passes``)."""
        for key in ("camera_rays", "bounce_rays", "shadow_rays", "light_rays", "skipped_shadow_rays",
                    "camera_seconds", "bounce_seconds", "shadow_seconds", "chunk_seconds"):
            setattr(self, key, getattr(self, key) + getattr(other, key))

    def as_dict(self) -> dict:
        return {"camera_rays": self.camera_rays, "bounce_rays": self.bounce_rays, "shadow_rays": self.shadow_rays,
                "light_rays": self.light_rays,
                "rays": self.rays, "seconds": self.seconds, "passes": self.passes,
                "skipped_shadow_rays": self.skipped_shadow_rays,
                "camera_seconds": self.camera_seconds, "bounce_seconds": self.bounce_seconds,
                "shadow_seconds": self.shadow_seconds, "chunk_seconds": self.chunk_seconds,
                "setup_seconds": self.setup_seconds, "parallel": self.parallel,
                "tracer": self.tracer, "tracer_reason": self.tracer_reason, "compile": self.compile,
                "rays_per_second": self.rays / self.seconds if self.seconds > 0 else None}


@dataclass(eq=False)
class Transport:
    """Accumulated light transport of one frame; sums, with means and errors as methods.

    Sums are over samples; divide by ``sample_count`` (done by the accessors).
    Channels of the replicate sums: 0 = signal Σw, 1..J = correlations, J+1 = ambient; replicate r holds
    the samples i ≡ r (mod R) of each pixel (:mod:`tofcore.tracer.qmc`).
    """

    width: int
    height: int
    max_depth: int
    n_correlations: int
    sample_count: np.ndarray      # (P,) int64 samples per pixel, P = H·W
    signal_sum: np.ndarray        # (K, P) float64: Σ w per bounce bucket k = 1..K
    correlation_sum: np.ndarray   # (K, J, P) float64: Σ w·g_j(L/c)
    ambient_sum: np.ndarray       # (P,) float64: Σ ambient radiance (unmodulated)
    replicate_sum: np.ndarray     # (R, J+2, P) float64: Σ of the per-sample channel totals of replicate r
    first_hit: FirstHit
    transient_sum: np.ndarray | None = None  # (P, B) float64: Σ w per path-length bin
    transient_bin_m: float | None = None
    stats: TraceStats = field(default_factory=TraceStats)

    # ------------------------------------------------------------- accessors
    def _per_sample(self, sums: np.ndarray) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = sums / self.sample_count
        return mean.reshape(sums.shape[:-1] + (self.height, self.width))

    def signal(self, max_k: int | None = None) -> np.ndarray:
        """(H, W) mean LED radiance at the lens summed over bounces k ≤ ``max_k`` (all by default)."""
        return self._per_sample(self.signal_sum[: self._k(max_k)].sum(axis=0))

    def correlation(self, max_k: int | None = None) -> np.ndarray:
        """(J, H, W) mean Σ w·g_j summed over bounces k ≤ ``max_k`` (all by default): the partial sums of §6.3.1."""
        return self._per_sample(self.correlation_sum[: self._k(max_k)].sum(axis=0))

    def signal_per_bounce(self) -> np.ndarray:
        """(K, H, W) mean signal of each bounce bucket k = 1..K."""
        return self._per_sample(self.signal_sum)

    def correlation_per_bounce(self) -> np.ndarray:
        """(K, J, H, W) mean correlation sums of each bounce bucket."""
        return self._per_sample(self.correlation_sum)

    def ambient(self) -> np.ndarray:
        """(H, W) mean ambient (unmodulated) radiance at the lens."""
        return self._per_sample(self.ambient_sum)

    def transient(self) -> np.ndarray | None:
        """(H, W, B) mean radiance per path-length bin of width ``transient_bin_m`` (bin b centred at (b+½)·width)."""
        if self.transient_sum is None:
            return None
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = self.transient_sum / self.sample_count[:, None]
        return mean.reshape(self.height, self.width, -1)

    def replicate_means(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-replicate means (R, J+2, H, W) of the channels (signal, correlations…, ambient) and the
        (R, H, W) sample counts behind them; NaN where a replicate has no sample yet."""
        n = self.replicate_counts()
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = self.replicate_sum / n[:, None, :]
        return (mean.reshape(mean.shape[:2] + (self.height, self.width)),
                n.reshape(-1, self.height, self.width))

    def replicate_counts(self) -> np.ndarray:
        """(R, P) samples of each replicate per pixel (:func:`tofcore.tracer.estimator.replicate_counts`)."""
        return estimator.replicate_counts(self.sample_count)

    def variance_of_mean(self) -> np.ndarray:
        """(J+2, H, W) variance of the per-pixel mean of each channel (signal, correlations…, ambient), from
        the spread of the R independent replicates (:func:`tofcore.tracer.estimator.variance_of_mean`)."""
        return estimator.variance_of_mean(*self.replicate_means())

    def _k(self, max_k: int | None) -> int:
        if max_k is None:
            return self.max_depth
        if not 1 <= max_k <= self.max_depth:
            raise ConfigError(f"Transport: max_k must be in [1, {self.max_depth}], got {max_k!r}")
        return max_k
