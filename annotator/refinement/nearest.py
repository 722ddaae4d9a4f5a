"""The nearest model sample of each of a fixed set of points that move a little at a time
(the measured points of a refinement, brought into the model frame at each iteration's pose),
within a gate: what a k-d tree query gives, without searching again for the points whose
nearest sample cannot have changed.

A search gives each point its nearest sample and a bound ``b`` that every other sample is at
least as far as: the distance to the second nearest, or the gate, when no other sample lies
within it. A point that has since moved by ``m`` is at least ``b - m`` from every other
sample; if it is nearer than that to its sample, measured now, that sample is still its
nearest. A point with no sample within the gate ``g`` has none within ``g - m`` either: none
is within a new gate that small. Only the other points are searched again; the first kind's
distances are measured to their sample. In a Gauss-Newton refinement the pose's steps soon
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
        self.others = np.full(n, -np.inf)  # every other sample was at least this far then
        self.empty = np.zeros(n)  # no sample lies nearer than this to it (when none matched)
        self.searched = 0  # points searched, over all queries (for tests and profiling)

    def query(self, points: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray]:
        """As ``tree.query(points, k=1, distance_upper_bound=gate)``: per point the distance
        to its nearest sample (inf where none lies within ``gate``) and that sample's index
        (``len(samples)`` where none)."""
        moved = norms(points - self.at)
        none = moved + gate + _SAFETY_MM <= self.empty  # NaN (never searched): False
        # Where the sample found last is measured now, and still nearer than any other can
        # have come (NaN, never searched, and none found: not; "clip" reads a sample for
        # those that found none, whose bound keeps them out).
        d = norms(points - np.take(self.samples, self.index, axis=0, mode="clip"))
        kept = d + moved + _SAFETY_MM < self.others
        redo = ~kept & ~none
        dist = np.full(len(points), np.inf)
        index = np.full(len(points), len(self.samples), np.intp)
        if redo.any():
            # Rows by index, not by mask: several times faster for (N, 3) arrays.
            rows = np.flatnonzero(redo)
            q = np.take(points, rows, axis=0)
            found, j = self.tree.query(q, k=2, distance_upper_bound=gate)
            self.searched += len(q)
            self.at[rows] = q
            self.index[rows] = j[:, 0]
            # Another sample is at least d2 away, or at least the gate: none was within it.
            matched = np.isfinite(found[:, 0])
            self.others[rows] = np.where(matched, np.minimum(found[:, 1], gate), -np.inf)
            self.empty[rows] = np.where(matched, 0.0, gate)
            dist[rows], index[rows] = found[:, 0], j[:, 0]
        if kept.any():
            inside = kept & (d < gate)
            dist[inside], index[inside] = d[inside], self.index[inside]
        return dist, index
