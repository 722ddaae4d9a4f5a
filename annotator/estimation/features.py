"""Point pair features and the local frames of Drost et al. (2010), vectorised.

For two oriented points ``(p1, n1)``, ``(p2, n2)`` with ``d = p2 - p1``, the feature is
``F = (||d||, angle(n1, d), angle(n2, d), angle(n1, n2))``, quantised by a distance step and
an angle step into one integer key. The *alignment* of an oriented point moves it to the
origin and turns its normal onto +x; after it, the other point of a pair lies at an angle
``alpha`` about the x axis. A model pair and a scene pair with equal features, aligned, differ
by a rotation about x of ``alpha_scene - alpha_model``: with the two alignments, that fixes
the whole pose (see :mod:`annotator.estimation.voting`).
"""

from __future__ import annotations

import numpy as np

#: Angles in [0, pi] quantised into ``angle_bins // 2 + 1`` cells and the distance into
#: 2^15 cells at most: the key packs them in 15 + 3 x 8 bits.
_ANGLE_BITS = 8


def pair_features(p1: np.ndarray, n1: np.ndarray, p2: np.ndarray, n2: np.ndarray) -> np.ndarray:
    """The features (N, 4) of pairs of oriented points (each (N, 3), unit normals)."""
    d = p2 - p1
    dist = np.linalg.norm(d, axis=1)
    u = d / np.maximum(dist, 1e-12)[:, None]
    return np.stack(
        [
            dist,
            _angle(np.einsum("ij,ij->i", n1, u)),
            _angle(np.einsum("ij,ij->i", n2, u)),
            _angle(np.einsum("ij,ij->i", n1, n2)),
        ],
        axis=1,
    )


def _angle(cos: np.ndarray) -> np.ndarray:
    return np.arccos(np.clip(cos, -1.0, 1.0))


def feature_keys(features: np.ndarray, distance_step: float, angle_step: float) -> np.ndarray:
    """One int64 key per feature (N, 4), equal for features in the same quantisation cell."""
    fd = np.floor(features[:, 0] / distance_step).astype(np.int64)
    fa = np.floor(features[:, 1:] / angle_step).astype(np.int64)
    return (
        (fd << (3 * _ANGLE_BITS))
        | (fa[:, 0] << (2 * _ANGLE_BITS))
        | (fa[:, 1] << _ANGLE_BITS)
        | fa[:, 2]
    )


def alignments(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``R`` (N, 3, 3), ``t`` (N, 3) of the transforms ``x -> R x + t`` that move each point
    to the origin and turn its normal onto +x (the rotation of least angle doing so; a normal
    along -x is turned by a half turn about z)."""
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    ex = np.array([1.0, 0.0, 0.0])
    v = np.cross(n, ex)  # axis * sin
    c = n[:, 0]  # cos
    K = np.zeros((len(n), 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -v[:, 2], v[:, 1]
    K[:, 1, 0], K[:, 1, 2] = v[:, 2], -v[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -v[:, 1], v[:, 0]
    opposite = c < -1.0 + 1e-9
    scale = np.where(opposite, 0.0, 1.0 / np.where(opposite, 1.0, 1.0 + c))
    R = np.eye(3) + K + (K @ K) * scale[:, None, None]
    R[opposite] = np.diag([-1.0, -1.0, 1.0])
    t = -np.einsum("nij,nj->ni", R, points)
    return R, t


def pair_angles(R: np.ndarray, t: np.ndarray, others: np.ndarray) -> np.ndarray:
    """The angle about +x (radians, in (-pi, pi]) of each ``others`` point (N, 3) once moved
    by its reference point's alignment ``R`` (N, 3, 3), ``t`` (N, 3)."""
    q = np.einsum("nij,nj->ni", R, others) + t
    return np.arctan2(q[:, 2], q[:, 1])


def rotations_about_x(angles: np.ndarray) -> np.ndarray:
    """Rotations (N, 3, 3) of ``angles`` (N,) about +x."""
    c, s = np.cos(angles), np.sin(angles)
    R = np.zeros((len(angles), 3, 3))
    R[:, 0, 0] = 1.0
    R[:, 1, 1], R[:, 1, 2] = c, -s
    R[:, 2, 1], R[:, 2, 2] = s, c
    return R
