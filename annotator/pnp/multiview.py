"""Multi-camera PnP: candidates from each camera (SQPnP, or both IPPE solutions of a lone
marker), then one Levenberg-Marquardt refinement over all cameras at once.

OpenCV solves PnP for one camera only; the joint refinement minimises the stacked
reprojection errors (lens distortion included) of every camera over one pose. The pose is
perturbed as ``R = exp([w]x) R0``, ``t = t0 + v`` (a left perturbation in the reference frame);
the covariance returned is that of ``(w, v)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from annotator.geometry.camera import Camera
from annotator.geometry.transforms import make_transform, rotvec_to_matrix


@dataclass(frozen=True)
class Observation:
    """One marker seen by one camera.

    Attributes:
        camera: Index of the camera in the rig.
        marker_id: The marker's id.
        model_corners: (4, 3) corners in the model frame (mm), ArUco order.
        image_corners: (4, 2) detected corners (px), same order.
    """

    camera: int
    marker_id: int
    model_corners: np.ndarray
    image_corners: np.ndarray


@dataclass(frozen=True)
class PoseEstimate:
    """A refined pose ``rig_T_model`` with its 6x6 covariance of ``(w, v)`` (rad, mm)."""

    T: np.ndarray
    covariance: np.ndarray
    residual_rms: float
    sigma_px: float


def _project(cameras: Sequence[Camera], obs: Sequence[Observation], T: np.ndarray) -> np.ndarray:
    """Projected corners (len(obs), 4, 2) of every observation under ``rig_T_model`` T."""
    out = np.empty((len(obs), 4, 2))
    for j in {o.camera for o in obs}:
        idx = [k for k, o in enumerate(obs) if o.camera == j]
        cam = cameras[j]
        M = cam.cam_T_rig @ T
        X = np.concatenate([obs[k].model_corners for k in idx])
        rvec, _ = cv2.Rodrigues(M[:3, :3])
        uv, _ = cv2.projectPoints(X, rvec, M[:3, 3], cam.K, cam.dist)
        out[idx] = uv.reshape(len(idx), 4, 2)
    return out


def reprojection_errors(
    cameras: Sequence[Camera], obs: Sequence[Observation], T: np.ndarray
) -> np.ndarray:
    """RMS corner reprojection error (px) of each observation under ``rig_T_model`` T.

    Observations behind their camera get infinity.
    """
    if not obs:
        return np.zeros(0)
    proj = _project(cameras, obs, T)
    err = np.sqrt(
        np.mean(np.sum((proj - np.stack([o.image_corners for o in obs])) ** 2, axis=-1), axis=-1)
    )
    for k, o in enumerate(obs):
        M = cameras[o.camera].cam_T_rig @ T
        if np.any(o.model_corners @ M[2, :3] + M[2, 3] <= 0):
            err[k] = np.inf
    return err


def candidate_poses(cameras: Sequence[Camera], obs: Sequence[Observation]) -> list[np.ndarray]:
    """Pose hypotheses ``rig_T_model`` from each camera alone.

    Per camera: SQPnP on all its markers if it sees two or more, and both IPPE solutions of
    every single marker (a lone square has two poses that explain it almost equally well).
    """
    out: list[np.ndarray] = []
    for j in sorted({o.camera for o in obs}):
        cam = cameras[j]
        mine = [o for o in obs if o.camera == j]
        rig_T_cam = cam.rig_T_cam
        if len(mine) >= 2:
            X = np.concatenate([o.model_corners for o in mine])
            x = np.concatenate([o.image_corners for o in mine])
            ok, rvec, tvec = cv2.solvePnP(X, x, cam.K, cam.dist, flags=cv2.SOLVEPNP_SQPNP)
            if ok:
                out.append(rig_T_cam @ make_transform(cv2.Rodrigues(rvec)[0], tvec.ravel()))
        for o in mine:
            for T in lone_marker_poses(cam, o):
                out.append(rig_T_cam @ T)
    return out


def lone_marker_poses(cam: Camera, o: Observation) -> list[np.ndarray]:
    """Both IPPE solutions ``cam_T_model`` of one (planar) marker, best first."""
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            o.model_corners.astype(np.float64),
            o.image_corners.astype(np.float64),
            cam.K,
            cam.dist,
            flags=cv2.SOLVEPNP_IPPE,
        )
    except cv2.error:
        return []
    return [make_transform(cv2.Rodrigues(r)[0], t.ravel()) for r, t in zip(rvecs[:n], tvecs[:n])]


def refine_pose(
    cameras: Sequence[Camera],
    obs: Sequence[Observation],
    T0: np.ndarray,
    *,
    sigma_floor: float = 0.3,
) -> PoseEstimate:
    """Jointly refine ``rig_T_model`` over all observations (all cameras), from ``T0``.

    The covariance is ``sigma^2 (J^T J)^-1`` at the optimum, with ``sigma`` the residual
    standard deviation, never below ``sigma_floor`` px: with few corners the residuals
    underestimate the corner noise (the pose absorbs part of it).
    """
    x = np.concatenate([o.image_corners for o in obs]).ravel()
    R0, t0 = T0[:3, :3], T0[:3, 3]

    def pose(p: np.ndarray) -> np.ndarray:
        return make_transform(rotvec_to_matrix(p[:3]) @ R0, t0 + p[3:])

    def residuals(p: np.ndarray) -> np.ndarray:
        return _project(cameras, obs, pose(p)).ravel() - x

    res = least_squares(
        residuals, np.zeros(6), method="lm", x_scale=np.array([1e-3] * 3 + [1.0] * 3)
    )
    T = pose(res.x)
    # Re-linearise at the optimum so the covariance is that of a perturbation of T itself.
    R0, t0 = T[:3, :3], T[:3, 3]
    r = residuals(np.zeros(6))
    J = _numeric_jacobian(residuals, np.zeros(6))
    m = r.size
    dof = max(m - 6, 1)
    sigma = max(float(np.sqrt(r @ r / dof)), sigma_floor)
    JtJ = J.T @ J
    try:
        cov = np.linalg.inv(JtJ) * sigma**2
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.inf)
    return PoseEstimate(
        T=T, covariance=cov, residual_rms=float(np.sqrt(np.mean(r**2) * 2)), sigma_px=sigma
    )


def _numeric_jacobian(f, p: np.ndarray) -> np.ndarray:
    eps = np.array([1e-6] * 3 + [1e-4] * 3)
    cols = []
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps[k]
        cols.append((f(p + d) - f(p - d)) / (2 * eps[k]))
    return np.column_stack(cols)
