"""The largest gap over a model's points between two placements of it, exactly, without
computing every point: BOP's MSSD (3D) and MSPD (pixels) of one symmetry.

The points are grouped once per model into small clusters (:func:`clusters_of`). For a
pair of placements, a bound says how large the gap can be anywhere in a cluster from its
centre and radius; the clusters whose bound is below a gap already found at a real point
cannot hold the largest one and are skipped. The value returned is the largest over the
points computed, which are every point that can hold the maximum: the same number as the
brute force over every point (up to the last bit of float rounding), never an estimate.

- **3D** (:class:`AffineGaps`): ``||A x + b||``, with ``A = R_g S - R_e`` and
  ``b = R_g t_s + t_g - t_e``; over a ball of radius ``r`` about ``c`` it is at most
  ``||A c + b|| + ||A||_F r``.
- **Pixels** (:class:`ProjectedGaps`): ``||pi(M_1 x + m_1) - pi(M_2 x + m_2)||`` with
  ``pi(z) = z_xy / z_z`` and ``M = K R``. Over the ball it is at most the gap at the
  centre, plus the difference of the two projections' derivatives at the centre times
  ``r`` (small when the placements are close, unlike the sum of the two projections'
  spreads), plus each projection's second-order remainder, bounded in closed form
  (:func:`_remainder`).

Bounds carry a relative slack (:data:`_SLACK`) far above float rounding, so a point
skipped is below the maximum by a margin no rounding can cross.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

#: Points per cluster aimed at (fewer points: tighter bounds, more clusters to bound).
CLUSTER_POINTS = 48
#: Bounds are inflated by this share (and :data:`_FLOOR`) before they may skip a cluster.
_SLACK = 1e-7
_FLOOR = 1e-9


@dataclass(frozen=True)
class Clusters:
    """A model's points in spatial clusters.

    Attributes:
        points: (N, 3) the points, ordered cluster by cluster (a maximum does not depend on
            the order).
        starts: (C + 1,) where each cluster's points begin, and N.
        centres: (C, 3) each cluster's centre; ``radii`` (C,): the largest distance from it
            to a point of the cluster.
    """

    points: np.ndarray
    starts: np.ndarray
    centres: np.ndarray
    radii: np.ndarray

    @cached_property
    def firsts(self) -> np.ndarray:
        """(C, 3) one point of each cluster (its first)."""
        return self.points[self.starts[:-1]]

    def members(self, which: np.ndarray) -> np.ndarray:
        """The points of the clusters ``which`` (indices), in one array."""
        lo, hi = self.starts[which], self.starts[which + 1]
        counts = hi - lo
        offsets = np.repeat(lo - np.cumsum(counts) + counts, counts)
        return self.points[np.arange(int(counts.sum())) + offsets]


def clusters_of(points: np.ndarray, size: int = CLUSTER_POINTS) -> Clusters:
    """The points' clusters (cells of a cubic grid sized for about ``size`` points each),
    computed once per process for the same array (one per mesh file,
    :func:`annotator.geometry.mesh.load_mesh`)."""
    got = _CLUSTERS.get((id(points), size))
    if got is not None and got[0] is points:
        return got[1]
    clusters = _make_clusters(np.asarray(points, np.float64), size)
    if len(_CLUSTERS) > 64:
        _CLUSTERS.clear()
    _CLUSTERS[(id(points), size)] = (points, clusters)
    return clusters


_CLUSTERS: dict[tuple[int, int], tuple[np.ndarray, Clusters]] = {}


def _make_clusters(points: np.ndarray, size: int) -> Clusters:
    lo, hi = points.min(axis=0), points.max(axis=0)
    extent = float(np.max(hi - lo)) or 1.0
    wanted = max(1, len(points) // size)
    # A surface's occupied cells grow as the square of their count per side: two tries
    # find a cell size near the wanted number of clusters.
    side = extent / max(1.0, np.sqrt(wanted / 6.0))
    for _ in range(2):
        cells = _cells(points, lo, side)
        occupied = len(np.unique(cells))
        side *= np.sqrt(occupied / wanted)
    cells = _cells(points, lo, side)
    order = np.argsort(cells, kind="stable")
    sorted_points = points[order]
    sorted_cells = cells[order]
    starts = np.flatnonzero(np.r_[True, sorted_cells[1:] != sorted_cells[:-1]])
    counts = np.diff(np.r_[starts, len(points)])
    centres = np.add.reduceat(sorted_points, starts, axis=0) / counts[:, None]
    dist = np.linalg.norm(sorted_points - np.repeat(centres, counts, axis=0), axis=1)
    radii = np.maximum.reduceat(dist, starts)
    return Clusters(sorted_points, np.r_[starts, len(points)], centres, radii)


def _cells(points: np.ndarray, lo: np.ndarray, side: float) -> np.ndarray:
    ijk = np.floor((points - lo) / side).astype(np.int64)
    n = ijk.max(axis=0) + 1
    return (ijk[:, 0] * n[1] + ijk[:, 1]) * n[2] + ijk[:, 2]


class AffineGaps:
    """``||A_s x + b_s||^2`` for rows ``s``: MSSD's squared gaps, one row per symmetry.

    ``A`` (S, 3, 3), ``b`` (S, 3).
    """

    def __init__(self, A: np.ndarray, b: np.ndarray) -> None:
        self.A, self.b = A, b

    def squared(self, rows: np.ndarray | slice, points: np.ndarray) -> np.ndarray:
        """(S', n) squared gaps at ``points`` (n, 3)."""
        d = np.matmul(points, np.swapaxes(self.A[rows], 1, 2)) + self.b[rows][:, None]
        return np.einsum("snk,snk->sn", d, d)

    def bounds(self, row: int, clusters: Clusters) -> np.ndarray:
        """(C,) an upper bound of the gap (not squared) over each cluster."""
        A = self.A[row]
        d = clusters.centres @ A.T + self.b[row]
        return np.sqrt(np.einsum("ck,ck->c", d, d)) + np.linalg.norm(A) * clusters.radii


class ProjectedGaps:
    """``||pi(M_s x + m_s) - pi(M_e x + m_e)||^2`` for rows ``s``, ``pi(z) = z_xy / z_z``:
    MSPD's squared gaps in pixels, one row per symmetry of the true pose against one
    estimate.

    ``M`` (S, 3, 3), ``m`` (S, 3): the true pose's symmetric placements (``K R_g S``,
    ``K (R_g t_s + t_g)``); ``M_e`` (3, 3), ``m_e`` (3,): the estimate's (``K R_e``,
    ``K t_e``).
    """

    def __init__(self, M: np.ndarray, m: np.ndarray, M_e: np.ndarray, m_e: np.ndarray) -> None:
        self.M, self.m, self.M_e, self.m_e = M, m, M_e, m_e

    def squared(self, rows: np.ndarray | slice, points: np.ndarray) -> np.ndarray:
        """(S', n) squared gaps at ``points`` (n, 3)."""
        z = np.matmul(points, np.swapaxes(self.M[rows], 1, 2)) + self.m[rows][:, None]
        ze = points @ self.M_e.T + self.m_e
        d = z[..., :2] / z[..., 2:] - ze[:, :2] / ze[:, 2:]
        return np.einsum("snk,snk->sn", d, d)

    def bounds(self, row: int, clusters: Clusters) -> np.ndarray:
        """(C,) an upper bound of the gap (not squared) over each cluster; infinite where a
        placement may put a point of the cluster at or behind the camera's plane."""
        c, r = clusters.centres, clusters.radii
        terms = []
        for M, m in ((self.M[row], self.m[row]), (self.M_e, self.m_e)):
            q = c @ M.T + m
            qz = q[:, 2]
            # the projection's derivative at the centre, (C, 2, 3): (M_xy - p M_z) / q_z
            p = q[:, :2] / qz[:, None]
            J = (M[None, :2] - p[:, :, None] * M[None, 2:3]) / qz[:, None, None]
            terms.append((p, J, _remainder(q, M, r)))
        (p1, J1, rem1), (p2, J2, rem2) = terms
        gap = np.linalg.norm(p1 - p2, axis=1)
        spread = np.sqrt(np.einsum("cij,cij->c", J1 - J2, J1 - J2)) * r
        return gap + spread + rem1 + rem2


def _remainder(q: np.ndarray, M: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(C,) a bound of ``|pi(q + d) - pi(q) - Dpi(q) d|`` over ``d = M y``, ``|y| <= r``.

    With ``a = d_z / q_z``, the remainder is exactly ``(a / q_z) (a q_xy - d_xy) / (1 + a)``;
    ``|a| <= |M_z| r / q_z`` and ``|d_xy| <= |M_xy|_F r``. Infinite where ``|a|`` may reach
    1 (a point of the ball at or behind the camera's plane) or the centre is behind it."""
    qz = q[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.linalg.norm(M[2]) * r / qz
        dxy = np.linalg.norm(M[:2]) * r
        rem = a / qz * (np.linalg.norm(q[:, :2], axis=1) * a + dxy) / (1.0 - a)
    return np.where((qz > 0) & (a < 1.0), rem, np.inf)


def largest_squared(
    gaps: AffineGaps | ProjectedGaps,
    row: int,
    clusters: Clusters,
    *,
    found: float = 0.0,
    stop: float = np.inf,
) -> float:
    """The largest squared gap of row ``row`` over every point of ``clusters``, exactly;
    or, once a point's gap reaches ``stop`` (squared), that point's (the caller needs only
    to know it is not below ``stop``). ``found``: a squared gap already computed at one of
    the points (a lower bound)."""
    rows = np.array([row])
    best = max(found, float(gaps.squared(rows, clusters.firsts).max()))
    if best >= stop:
        return best
    bound = gaps.bounds(row, clusters) * (1.0 + _SLACK) + _FLOOR
    which = np.flatnonzero(~(bound * bound < best))  # NaN bounds are looked at too
    if len(which):
        best = max(best, float(gaps.squared(rows, clusters.members(which)).max()))
    return best
