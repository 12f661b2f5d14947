"""Accumulate: a chunk's contributions into the frame's sums — bounce buckets, correlation channels,
transient bins, ambient light and the per-replicate totals of the error estimate.

A chunk owns the pixels [p0, p1) and writes only those, so chunks run in parallel (threads, processes)
without locks. Per contribution of bucket k (k surface vertices) and pixel p:

* ``signal_sum[k−1, p] += w``, ``correlation_sum[k−1, j, p] += w·g_j(L/c)`` (DESIGN.md "path-length bucketing");
* ``transient_sum[p, b]``: w split linearly between the two bin centres nearest L (keeps Σw and Σw·L);
* each path's channel totals (signal, correlations…, ambient) go, once the path has ended, to
  ``replicate_sum[r, :, p]`` of its replicate r = sample mod R (:mod:`tofcore.tracer.qmc`), and its ambient
  total to ``ambient_sum[p]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..backend import namespace, scatter_sum
from . import qmc
from .path import Contribution, PathState
from .transport import Transport


@dataclass
class Tally:
    """The sums of chunk [p0, p1) of ``out``, and the channel totals of each of its paths."""

    out: Transport
    p0: int
    p1: int
    transient_bin_m: float | None
    path_total: np.ndarray      # (J + 2, n_paths): signal, correlations…, ambient of each path so far
    path_pixel: np.ndarray      # (n_paths,) pixel of each path, relative to p0
    path_replicate: np.ndarray  # (n_paths,) replicate of each path

    @classmethod
    def for_chunk(cls, out: Transport, p0: int, p1: int, state: PathState) -> Tally:
        """Empty per-path totals for the paths of the first ``state`` (rows = ``state.path``)."""
        xp = namespace(state.pixel)
        return cls(out=out, p0=p0, p1=p1, transient_bin_m=out.transient_bin_m,
                   path_total=xp.zeros((out.n_correlations + 2, len(state))), path_pixel=state.pixel - p0,
                   path_replicate=state.sample % qmc.REPLICATES)

    @property
    def n_pix(self) -> int:
        return self.p1 - self.p0

    def add(self, state: PathState, c: Contribution) -> None:
        """Add contribution ``c`` of the paths ``state`` to bucket c.k of their pixels and to the path totals."""
        local_pixel = state.pixel - self.p0
        for w, length in c.transient:
            if self.out.transient_sum is not None:
                self._add_transient(local_pixel, w, length)
        n_pix, n_corr, k = self.n_pix, self.out.n_correlations, c.k - 1
        self.out.signal_sum[k, self.p0:self.p1] += scatter_sum(local_pixel, c.weight, n_pix)
        self.path_total[0, state.path] += c.weight
        if n_corr:  # all channels in one scatter: channel j of pixel p goes to bin j·n_pix + p
            bins = (namespace(c.weight).arange(n_corr)[:, None] * n_pix + local_pixel).ravel()
            self.out.correlation_sum[k, :, self.p0:self.p1] += scatter_sum(
                bins, c.correlation.ravel(), n_corr * n_pix).reshape(n_corr, n_pix)
            self.path_total[1:n_corr + 1, state.path] += c.correlation

    def add_ambient(self, rows, radiance) -> None:
        """Ambient radiance seen by the paths ``rows`` (their rays left the scene)."""
        self.path_total[-1, rows] += radiance

    def finish(self, ambient: bool) -> None:
        """Every path has ended: add the path totals to the replicate sums (and the ambient sums)."""
        xp = namespace(self.path_total)
        n_pix, n_ch, n_rep = self.n_pix, self.out.n_correlations + 2, qmc.REPLICATES
        bins = ((self.path_replicate * n_ch)[None, :] * n_pix + xp.arange(n_ch)[:, None] * n_pix
                + self.path_pixel).ravel()
        self.out.replicate_sum[:, :, self.p0:self.p1] += scatter_sum(
            bins, self.path_total.ravel(), n_rep * n_ch * n_pix).reshape(n_rep, n_ch, n_pix)
        if ambient:
            self.out.ambient_sum[self.p0:self.p1] += scatter_sum(self.path_pixel, self.path_total[-1], n_pix)

    def _add_transient(self, local_pixel, w, length) -> None:
        """Add weights to the path-length histogram, split linearly between the two nearest bin centres.

        The split keeps Σw and Σw·L of every contribution inside the range (moment-preserving, DESIGN.md).
        """
        nb = self.out.transient_sum.shape[1]
        x = length / self.transient_bin_m - 0.5
        b0 = np.floor(x)
        frac = x - b0
        b0 = b0.astype(np.int64)
        n = self.n_pix * nb
        hist = namespace(w).zeros(n)
        for b, wt in ((b0, w * (1.0 - frac)), (b0 + 1, w * frac)):
            ok = (b >= 0) & (b < nb) & (wt != 0)
            hist += scatter_sum(local_pixel[ok] * nb + b[ok], wt[ok], n)
        self.out.transient_sum[self.p0:self.p1] += hist.reshape(self.n_pix, nb)
