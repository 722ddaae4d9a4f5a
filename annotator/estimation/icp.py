"""Point-to-plane ICP of a posed part onto the scene's oriented points.

The part's samples that face the camera at the current pose are matched to their nearest
scene points (within a gate that shrinks from ``start_gate`` to ``end_gate`` mm over the
iterations, and with normals within 60 degrees), and the pose update minimising the sum of
squared point-to-plane distances is solved linearised (small rotation), as in Chen and
Medioni's ICP. It pulls a hypothesis found by voting, quantised to the voting's cells, onto
the measured surface.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from annotator.estimation.cloud import OrientedCloud
from annotator.geometry.lie import skew
from annotator.geometry.transforms import nearest_rotation


def refine_icp(
    cam_T_model: np.ndarray,
    model_points: np.ndarray,
    model_normals: np.ndarray,
    scene: OrientedCloud,
    scene_tree: Any,
    *,
    start_gate: float,
    end_gate: float,
    iterations: int = 12,
) -> np.ndarray:
    """The refined pose (4x4, camera frame); the pose unchanged when fewer than 6 points
    match. ``scene_tree`` is a ``cKDTree`` of ``scene.points``."""
    T = np.array(cam_T_model, float)
    for k in range(iterations):
        gate = start_gate + (end_gate - start_gate) * k / max(iterations - 1, 1)
        R, t = T[:3, :3], T[:3, 3]
        p = model_points @ R.T + t
        n = model_normals @ R.T
        facing = np.einsum("ij,ij->i", n, p) < 0
        p, n = p[facing], n[facing]
        if len(p) < 6:
            break
        d, j = scene_tree.query(p, distance_upper_bound=gate)
        ok = np.isfinite(d)
        ok[ok] &= np.einsum("ij,ij->i", n[ok], scene.normals[j[ok]]) > 0.5
        if ok.sum() < 6:
            break
        p, q, nq = p[ok], scene.points[j[ok]], scene.normals[j[ok]]
        # r + [p x n, n] . [w, dt] = 0 for each match, least squares.
        A = np.concatenate([np.cross(p, nq), nq], axis=1)
        b = -np.einsum("ij,ij->i", p - q, nq)
        x, *_ = np.linalg.lstsq(A, b, rcond=None)
        w, dt = x[:3], x[3:]
        dR = nearest_rotation(np.eye(3) + skew(w))
        T[:3, :3] = dR @ R
        T[:3, 3] = dR @ t + dt
        if np.linalg.norm(w) < 1e-5 and np.linalg.norm(dt) < 1e-3:
            break
    return T
