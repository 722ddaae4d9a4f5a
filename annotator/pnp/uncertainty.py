"""Pose uncertainty in millimetres of RMS surface displacement (the paper's distance, 4.1).

For a small motion of a posed part, ``R -> exp([w]x) R`` and ``t -> t + v``, each surface point
``y = R x`` moves by ``v - [y]x w``. Its mean square over the surface is the quadratic form
``d^T Q d`` in ``d = (w, v)``, with ``Q`` built from the surface centroid and second moments.
For a Gaussian ``d`` of covariance ``S``, the expected squared RMS displacement is
``trace(Q S)``: its square root is the uncertainty reported.
"""

from __future__ import annotations

import numpy as np

from annotator.geometry.mesh import SurfaceMoments


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])


def rms_displacement_matrix(moments: SurfaceMoments, R: np.ndarray) -> np.ndarray:
    """The 6x6 ``Q`` such that ``d^T Q d`` is the mean square surface displacement."""
    ybar = R @ moments.centroid
    S = R @ moments.second @ R.T + np.outer(ybar, ybar)  # E[y y^T] over the surface
    A = np.trace(S) * np.eye(3) - S  # E[[y]x^T [y]x]
    Q = np.zeros((6, 6))
    Q[:3, :3] = A
    Q[3:, 3:] = np.eye(3)
    Q[3:, :3] = -_skew(ybar)
    Q[:3, 3:] = Q[3:, :3].T
    return Q


def rms_uncertainty(moments: SurfaceMoments, R: np.ndarray, covariance: np.ndarray) -> float:
    """Expected RMS surface displacement (mm) of a pose with covariance of ``(w, v)``."""
    value = float(np.trace(rms_displacement_matrix(moments, R) @ covariance))
    return float(np.sqrt(max(value, 0.0))) if np.isfinite(value) else float("inf")
