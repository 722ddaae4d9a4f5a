"""Rigid transforms and rotations (conventions in :mod:`annotator.geometry`)."""

from __future__ import annotations

import numpy as np

from annotator.geometry.lie import rotvec_to_matrix

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


def axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation of ``angle`` radians about ``axis`` (normalised here)."""
    axis = np.asarray(axis, dtype=float)
    return rotvec_to_matrix(axis / np.linalg.norm(axis) * angle)


def random_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` rotations drawn uniformly from SO(3), shape (n, 3, 3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.random(n, random_state=rng).as_matrix()
