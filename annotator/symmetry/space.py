"""Pose representatives and distances for one part (paper table 2).

Frames: a pose ``(R, t)`` maps model to camera. Internally the part is re-expressed in its
*canonical* frame: origin at the surface centroid ``c`` and, for revolution classes, z along
the symmetry axis (rotation ``B``, columns = canonical axes in model coordinates). The pose
of the canonical frame is ``R' = R B``, ``t' = R c + t``; with ``L`` the square root of the
surface second moments in that frame:

- none / finite: ``{(vec(R' G L), t') : G in group}`` in R^12 (G in canonical coordinates);
- revolution: ``(lambda R' e_z, t')`` in R^6 with ``lambda = sqrt(lambda_r^2 + lambda_z^2)``...

see :meth:`PoseSpace.representatives`; the identities are checked against brute force in
tests/test_symmetry.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from annotator.geometry.mesh import SurfaceMoments
from annotator.symmetry.classes import Symmetry, SymmetryKind, group_of

#: The paper's match threshold, as a fraction of a part's diameter: two poses closer than
#: this are the same pose (evaluation), and two copies posed closer are in the same place.
MATCH_THRESHOLD_FRACTION = 0.1


def _frame_with_z(axis: np.ndarray) -> np.ndarray:
    z = axis / np.linalg.norm(axis)
    if z[2] > 1.0 - 1e-12:
        return np.eye(3)  # the model's own axes when they already fit
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(ref, z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


@dataclass(frozen=True)
class PoseSpace:
    """Representatives and distances for the poses of one part.

    Build with :meth:`from_moments`. All lengths are mm.
    """

    kind: SymmetryKind
    centroid: np.ndarray
    B: np.ndarray  # model -> canonical axes (columns)
    L: np.ndarray  # 3x3 square root of the second moments, canonical frame
    group: np.ndarray  # (G, 3, 3) finite group in canonical coordinates (identity first)
    lam: float  # revolution: sqrt(lambda_r^2 + lambda_z^2)
    diameter: float

    @classmethod
    def from_moments(cls, moments: SurfaceMoments, symmetry: Symmetry) -> PoseSpace:
        """The pose space of a part with these surface moments and this symmetry."""
        kind = symmetry.kind
        B = np.eye(3)
        if kind in ("revolution", "revolution_flip"):
            B = _frame_with_z(
                symmetry.axis if symmetry.axis is not None else np.array([0.0, 0.0, 1.0])
            )
        second = B.T @ moments.second @ B
        w, V = np.linalg.eigh(second)
        L = (V * np.sqrt(np.clip(w, 0, None))) @ V.T
        group = np.eye(3)[None]
        if kind == "finite":
            group = np.einsum("ij,gjk,kl->gil", B.T, group_of(symmetry), B)
        lam = 0.0
        if kind in ("revolution", "revolution_flip"):
            # Radial moments are equal for a true solid of revolution; average the tessellation's.
            lr2 = 0.5 * (second[0, 0] + second[1, 1])
            lam = float(np.sqrt(lr2 + second[2, 2]))
        return cls(kind, moments.centroid.copy(), B, L, group, lam, moments.diameter)

    @property
    def dim(self) -> int:
        return {"none": 12, "finite": 12, "revolution": 6, "revolution_flip": 6, "spherical": 3}[
            self.kind
        ]

    @property
    def count(self) -> int:
        """Representatives per pose."""
        if self.kind in ("none", "finite"):
            return len(self.group)
        return 2 if self.kind == "revolution_flip" else 1

    def representatives(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Representatives of poses ``R`` (N, 3, 3), ``t`` (N, 3): shape (N, count, dim)."""
        R = np.asarray(R, float).reshape(-1, 3, 3)
        t = np.asarray(t, float).reshape(-1, 3)
        Rc = R @ self.B
        tc = t + np.einsum("nij,j->ni", R, self.centroid)
        n = len(R)
        if self.kind in ("none", "finite"):
            M = np.matmul(np.matmul(Rc[:, None], self.group[None]), self.L)
            return np.concatenate(
                [M.reshape(n, self.count, 9), np.repeat(tc[:, None], self.count, 1)], axis=2
            )
        if self.kind == "spherical":
            return tc[:, None, :]
        axis = self.lam * Rc[:, :, 2]
        reps = [np.concatenate([axis, tc], axis=1)]
        if self.kind == "revolution_flip":
            reps.append(np.concatenate([-axis, tc], axis=1))
        return np.stack(reps, axis=1)

    def distance(
        self, R1: np.ndarray, t1: np.ndarray, R2: np.ndarray, t2: np.ndarray
    ) -> np.ndarray:
        """Pairwise-aligned distances between poses 1 and poses 2 (same N), shape (N,)."""
        R1 = np.asarray(R1, float).reshape(-1, 3, 3)
        R2 = np.asarray(R2, float).reshape(-1, 3, 3)
        if self.kind in ("none", "finite"):
            sq = self._rotation_term(np.matmul(np.swapaxes(R1, 1, 2), R2))
            dt = self._origin(R1, t1) - self._origin(R2, t2)
            return np.sqrt(np.clip(sq + np.einsum("ni,ni->n", dt, dt), 0.0, None))
        a = self.representatives(R1, t1)[:, 0]
        b = self.representatives(R2, t2)
        return np.linalg.norm(b - a[:, None], axis=2).min(axis=1)

    def distance_matrix(
        self, R1: np.ndarray, t1: np.ndarray, R2: np.ndarray, t2: np.ndarray
    ) -> np.ndarray:
        """All distances between poses 1 (N) and poses 2 (M), shape (N, M)."""
        R1 = np.asarray(R1, float).reshape(-1, 3, 3)
        R2 = np.asarray(R2, float).reshape(-1, 3, 3)
        n, m = len(R1), len(R2)
        if n == 0 or m == 0:
            return np.zeros((n, m))
        if self.kind in ("none", "finite"):
            # tr(R1^T R2 W) = <R1, R2 W> (Frobenius): one (N, 9) x (9, M G) product.
            R2W = np.matmul(R2[:, None], self._W).reshape(m * len(self._W), 9)
            best = (R1.reshape(n, 9) @ R2W.T).reshape(n, m, -1).max(axis=2)
            sq = self._LL_trace2 - 2 * best
            dt = self._origin(R1, t1)[:, None] - self._origin(R2, t2)[None]
            return np.sqrt(np.clip(sq + np.einsum("abi,abi->ab", dt, dt), 0.0, None))
        a = self.representatives(R1, t1)[:, 0]
        b = self.representatives(R2, t2)
        d = np.linalg.norm(a[:, None, None, :] - b[None], axis=3)
        return d.min(axis=2)

    def _origin(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Where poses put the centroid: the translation part of the representatives."""
        return np.asarray(t, float).reshape(-1, 3) + R @ self.centroid

    def _rotation_term(self, M: np.ndarray) -> np.ndarray:
        """``min_G ||R1' L - R2' G L||_F^2`` from ``M = R1^T R2`` (model axes), shape (N,):
        ``2 tr(L L^T) - 2 max_G tr(M W_G)``, one (N, 9) x (9, G) product instead of N x G
        differences of 12-D points."""
        best = (M.reshape(-1, 9) @ np.swapaxes(self._W, 1, 2).reshape(-1, 9).T).max(axis=1)
        return self._LL_trace2 - 2 * best

    @cached_property
    def _W(self) -> np.ndarray:
        """``W_G = B G L L^T B^T`` for each G of the group, (G, 3, 3)."""
        return np.matmul(np.matmul(self.B, np.matmul(self.group, self.L @ self.L.T)), self.B.T)

    @cached_property
    def _LL_trace2(self) -> float:
        """``2 tr(L L^T)``."""
        return float(2 * np.trace(self.L @ self.L.T))

    def nearest(
        self, R_query: np.ndarray, t_query: np.ndarray, R_set: np.ndarray, t_set: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """For each query pose, the index of the nearest pose of the set and the distance
        (KD-tree over the set's representatives)."""
        from scipy.spatial import cKDTree

        reps = self.representatives(R_set, t_set)
        owner = np.repeat(np.arange(len(reps)), self.count)
        tree = cKDTree(reps.reshape(-1, self.dim))
        d, i = tree.query(self.representatives(R_query, t_query)[:, 0])
        return owner[i], d

    def average(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Average of nearby poses of a (possibly symmetric) part.

        Each pose's representative nearest to the first pose's is taken (this resolves the
        symmetry), those points are averaged in representative space, and the mean is mapped
        back to the nearest valid pose: the rotation part by SVD projection (12-D), or the
        normalised axis (6-D). For revolution classes the returned rotation is one of the
        equivalent ones (any turn about the axis).
        """
        R = np.asarray(R, float).reshape(-1, 3, 3)
        t = np.asarray(t, float).reshape(-1, 3)
        reps = self.representatives(R, t)
        ref = reps[0, 0]
        pick = np.linalg.norm(reps - ref, axis=2).argmin(axis=1)
        mean = reps[np.arange(len(reps)), pick].mean(axis=0)
        if self.kind in ("none", "finite"):
            M = mean[:9].reshape(3, 3) @ np.linalg.inv(self.L)
            U, _, Vt = np.linalg.svd(M)
            Rc = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
            tc = mean[9:]
        elif self.kind == "spherical":
            Rc, tc = R[0] @ self.B, mean
        else:
            z = mean[:3] / np.linalg.norm(mean[:3])
            Rc = _frame_with_z(z)
            tc = mean[3:]
        Rm = Rc @ self.B.T
        return Rm, tc - Rm @ self.centroid
