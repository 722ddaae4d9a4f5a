"""The nearest model sample of each of a fixed set of points that move a little at a time
(the measured points of a refinement, brought into the model frame at each iteration's pose),
within a gate: what a k-d tree query gives, without searching again for the points whose
nearest sample cannot have changed.

A search gives each point its nearest sample (at ``d1``) and the distance ``d2`` to the
second nearest (or to the gate, when no other sample lies within it). A point that has since
moved by less than ``(d2 - d1) / 2`` still has the same nearest sample: every other sample is
still further away than it. A point with no sample within the gate ``g`` has none within
``g - moved`` either: none is within a new gate that small. Only the other points are
searched again; the first kind's distances are measured to their sample. In a Gauss-Newton refinement the pose's steps soon
become small, so after the first iterations most points are not searched again.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from annotator.geometry.lie import norms

#: Kept off the margin (mm): the distances' own rounding must not decide a tie.
_SAFETY_MM = 1e-9


class TrackedNearest:
    """Nearest samples of ``n`` query points in ``tree`` (see the module docstring)."""

    def __init__(self, tree: cKDTree, samples: np.ndarray, n: int) -> None:
        self.tree = tree
        self.samples = samples  # the tree's points
        self.at = np.full((n, 3), np.nan)  # each point where it was last searched
        self.index = np.zeros(n, np.intp)  # its nearest sample then
        self.margin = np.full(n, -np.inf)  # how far it may move and keep that sample
        self.empty = np.zeros(n)  # no sample lies nearer than this to it (when none matched)
        self.searched = 0  # points searched, over all queries (for tests and profiling)

    def query(self, points: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray]:
        """As ``tree.query(points, k=1, distance_upper_bound=gate)``: per point the distance
        to its nearest sample (inf where none lies within ``gate``) and that sample's index
        (``len(samples)`` where none)."""
        moved = norms(points - self.at)
        none = moved + gate + _SAFETY_MM <= self.empty  # NaN (never searched): False
        redo = ~(moved < self.margin) & ~none  # NaN (never searched) is searched too
        dist = np.full(len(points), np.inf)
        index = np.full(len(points), len(self.samples), np.intp)
        if redo.any():
            # Rows by index, not by mask: several times faster for (N, 3) arrays.
            rows = np.flatnonzero(redo)
            q = np.take(points, rows, axis=0)
            d, j = self.tree.query(q, k=2, distance_upper_bound=gate)
            self.searched += len(q)
            self.at[rows] = q
            self.index[redo] = j[:, 0]
            # Another sample is at least d2 away, or at least the gate: none was within it.
            gap = np.minimum(d[:, 1], gate) - d[:, 0]
            with np.errstate(invalid="ignore"):  # inf - inf: no sample within the gate
                self.margin[redo] = np.where(np.isfinite(d[:, 0]), 0.5 * gap - _SAFETY_MM, -np.inf)
            self.empty[redo] = np.where(np.isfinite(d[:, 0]), 0.0, gate)
            dist[redo], index[redo] = d[:, 0], j[:, 0]
        kept = ~redo & ~none
        if kept.any():
            j = self.index[kept]
            moved_to = np.take(points, np.flatnonzero(kept), axis=0)
            d = norms(moved_to - np.take(self.samples, j, axis=0))
            inside = d < gate
            dist[kept] = np.where(inside, d, np.inf)
            index[kept] = np.where(inside, j, len(self.samples))
        return dist, index
