"""Rigid transforms and rotations (conventions in :mod:`annotator.geometry`)."""

from __future__ import annotations

import numpy as np

# scipy.spatial costs more than half a second to import, which commands such as ``check`` and
# ``evaluate`` would pay at start-up: the rotation conversions are written here, and only
# random_rotations imports it.


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build the 4x4 transform ``[R t; 0 1]``."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (or a stack of them, shape (..., 4, 4))."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    Ti[..., 3, 3] = 1.0
    return Ti


def is_rotation(R: np.ndarray, *, tol: float = 1e-4) -> bool:
    """True if ``R`` is a proper rotation (orthonormal, determinant +1) within ``tol``."""
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        return False
    return bool(np.abs(R @ R.T - np.eye(3)).max() < tol and abs(np.linalg.det(R) - 1.0) < tol)


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation closest to ``M`` in the Frobenius norm (SVD projection)."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, shape (..., 3)) to rotation matrices (..., 3, 3), by
    Rodrigues' formula (series near zero)."""
    r = np.asarray(rotvec, dtype=float)
    theta = np.linalg.norm(r, axis=-1)[..., None, None]
    small = theta < 1e-4
    t2 = theta**2
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(small, 1.0 - t2 / 6.0, np.sin(theta) / theta)
        b = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(theta)) / t2)
    K = np.zeros(r.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -r[..., 2], r[..., 1], -r[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = r[..., 2], -r[..., 1], r[..., 0]
    return np.eye(3) + a * K + b * (K @ K)


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) to rotation vectors (..., 3), angles in [0, pi], through
    the quaternion (Shepperd: from its largest component, for accuracy)."""
    q = _quaternion(np.asarray(R, dtype=float))
    v = q[..., :3]
    s = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(s, q[..., 3])
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(s < 1e-12, 2.0, angle / s)
    return v * scale[..., None]


def _quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) ``(x, y, z, w)`` with ``w >= 0`` of rotation matrices
    (..., 3, 3), each from the candidate of its largest component (Shepperd's method)."""
    r = {(i, j): R[..., i, j] for i in range(3) for j in range(3)}
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    big = np.stack(
        [1.0 + 2.0 * r[0, 0] - tr, 1.0 + 2.0 * r[1, 1] - tr, 1.0 + 2.0 * r[2, 2] - tr, 1.0 + tr], -1
    )
    h = np.sqrt(np.maximum(big, 1e-300)) / 2.0  # each candidate's largest component
    d = 4.0 * h
    xy, xz, yz = r[0, 1] + r[1, 0], r[0, 2] + r[2, 0], r[1, 2] + r[2, 1]
    wx, wy, wz = r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]
    rows = (  # (x, y, z, w) from x, from y, from z, from w
        (h[..., 0], xy / d[..., 0], xz / d[..., 0], wx / d[..., 0]),
        (xy / d[..., 1], h[..., 1], yz / d[..., 1], wy / d[..., 1]),
        (xz / d[..., 2], yz / d[..., 2], h[..., 2], wz / d[..., 2]),
        (wx / d[..., 3], wy / d[..., 3], wz / d[..., 3], h[..., 3]),
    )
    candidates = np.stack([np.stack(row, -1) for row in rows], -2)
    pick = np.argmax(big, axis=-1)[..., None, None]
    q = np.take_along_axis(candidates, pick, axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0, -q, q)  # w >= 0: angles up to pi


def axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation of ``angle`` radians about ``axis`` (normalised here)."""
    axis = np.asarray(axis, dtype=float)
    return rotvec_to_matrix(axis / np.linalg.norm(axis) * angle)


def random_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` rotations drawn uniformly from SO(3), shape (n, 3, 3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.random(n, random_state=rng).as_matrix()
