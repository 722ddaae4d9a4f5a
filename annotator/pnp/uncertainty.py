"""Pose uncertainty in millimetres of RMS surface displacement (the paper's distance, 4.1).

For a small motion of a posed part, ``R -> exp([w]x) R`` and ``t -> t + v``, each surface point
``y = R x`` moves by ``v - [y]x w``. Its mean square over the surface is the quadratic form
``d^T Q d`` in ``d = (w, v)``, with ``Q`` built from the surface centroid and second moments.
For a Gaussian ``d`` of covariance ``S``, the expected squared RMS displacement is
``trace(Q S)``: its square root is the uncertainty reported.
"""

from __future__ import annotations

import numpy as np

from annotator.geometry.lie import skew
from annotator.geometry.mesh import SurfaceMoments


def rms_displacement_matrix(moments: SurfaceMoments, R: np.ndarray) -> np.ndarray:
    """The 6x6 ``Q`` such that ``d^T Q d`` is the mean square surface displacement."""
    ybar = R @ moments.centroid
    S = R @ moments.second @ R.T + np.outer(ybar, ybar)  # E[y y^T] over the surface
    A = np.trace(S) * np.eye(3) - S  # E[[y]x^T [y]x]
    Q = np.zeros((6, 6))
    Q[:3, :3] = A
    Q[3:, 3:] = np.eye(3)
    Q[3:, :3] = -skew(ybar)
    Q[:3, 3:] = Q[3:, :3].T
    return Q


def rms_uncertainty(moments: SurfaceMoments, R: np.ndarray, covariance: np.ndarray) -> float:
    """Expected RMS surface displacement (mm) of a pose with covariance of ``(w, v)``."""
    value = float(np.trace(rms_displacement_matrix(moments, R) @ covariance))
    return float(np.sqrt(max(value, 0.0))) if np.isfinite(value) else float("inf")


def relative_rms_uncertainty(
    moments: SurfaceMoments,
    scene_T_model: np.ndarray,
    scene_T_rig: np.ndarray,
    covariance: np.ndarray,
) -> float:
    """Expected RMS surface displacement (mm) of a part as a moving rig's frame sees it,
    when both the part's pose and the frame's are uncertain: ``covariance`` is the joint
    12x12 covariance of the part's ``(w, v)`` and the frame's (both left perturbations in
    the scene frame; for the frame, ``v`` moves its camera centre, see
    :mod:`annotator.pnp.bundle`), cross terms included (the part is known through the frames).

    In the rig the point ``x`` of the part moves by ``w_m x R x + v_m + d x w_f - v_f`` with
    ``d`` the point's offset from the frame's centre (the rig's rotation is norm-preserving).

    >>> from annotator.geometry.mesh import SurfaceMoments
    >>> m = SurfaceMoments(area=1.0, centroid=np.zeros(3), second=np.eye(3), radius=1.0)
    >>> cov = np.zeros((12, 12)); cov[9:, 9:] = np.eye(3) * 0.01  # the frame's centre alone
    >>> round(relative_rms_uncertainty(m, np.eye(4), np.eye(4), cov), 4)
    0.1732
    """
    R, t = scene_T_model[:3, :3], scene_T_model[:3, 3]
    c = np.asarray(scene_T_rig)[:3, 3]
    ybar = R @ moments.centroid
    S = R @ moments.second @ R.T + np.outer(ybar, ybar)  # E[y y^T], y = R x
    A0 = np.zeros((3, 12))
    A0[:, 3:6] = np.eye(3)
    A0[:, 6:9] = skew(t - c)
    A0[:, 9:12] = -np.eye(3)
    Ak = np.zeros((3, 3, 12))  # the part of A linear in y's components
    for k in range(3):
        e = np.eye(3)[k]
        Ak[k, :, 0:3] = -skew(e)
        Ak[k, :, 6:9] = skew(e)
    Q = A0.T @ A0
    for k in range(3):
        cross = A0.T @ Ak[k] + Ak[k].T @ A0
        Q += cross * ybar[k]
        for j in range(3):
            Q += Ak[k].T @ Ak[j] * S[k, j]
    value = float(np.trace(Q @ covariance))
    return float(np.sqrt(max(value, 0.0))) if np.isfinite(value) else float("inf")


def site_covariance(R: np.ndarray, corners: np.ndarray, sigma: float | np.ndarray) -> np.ndarray:
    """The ``(w, v)`` covariance of a pose fitted to marker corners ``corners`` (model frame,
    (n, 3)) each off by ``sigma`` (mm, isotropic; one for all or (n,) one each) on the part,
    the pose's rotation ``R``: ``(sum B_k^T B_k / sigma_k^2)^-1`` with
    ``B_k = [-[R x_k]x, I]``: what a part's markers' own errors (printing, gluing) do to its
    pose, however often they are seen. Corners on one line leave a turn free: its variance
    infinite.

    >>> square = np.array([[-5.0, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]])
    >>> cov = site_covariance(np.eye(3), square, 0.1)
    >>> bool(np.all(np.isfinite(cov))), round(float(np.sqrt(cov[3, 3])), 4)
    (True, 0.05)
    """
    pts = np.asarray(corners, dtype=float).reshape(-1, 3)
    weights = np.broadcast_to(1.0 / np.asarray(sigma, dtype=float) ** 2, (len(pts),))
    y = pts @ np.asarray(R, dtype=float).T
    # The sum by blocks, all corners at once: B_k^T B_k = [[|y|^2 I - y y^T, [y]x],
    # [-[y]x, I]] with y = R x_k (a sequence's frame rests on hundreds of corners).
    wy = weights @ y
    A = np.zeros((6, 6))
    A[:3, :3] = float(weights @ np.einsum("ki,ki->k", y, y)) * np.eye(3) - (y.T * weights) @ y
    A[:3, 3:] = skew(wy)
    A[3:, :3] = -skew(wy)
    A[3:, 3:] = float(weights.sum()) * np.eye(3)
    w, V = np.linalg.eigh(A)
    if w[0] <= 1e-9 * max(float(w[-1]), 1e-300):
        return np.full((6, 6), np.inf)
    return (V / w) @ V.T
