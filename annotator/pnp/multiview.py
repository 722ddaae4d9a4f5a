"""Multi-camera PnP: candidates from each camera (SQPnP, or both IPPE solutions of a lone
marker), then one Levenberg-Marquardt refinement over all cameras at once.

OpenCV solves PnP for one camera only; the joint refinement minimises the stacked
reprojection errors (lens distortion included) of every camera over one pose. The pose is
perturbed as ``R = exp([w]x) R0``, ``t = t0 + v`` (a left perturbation in the reference frame);
the covariance returned is that of ``(w, v)``.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from annotator.geometry.camera import Camera
from annotator.geometry.least_squares import Damping, levenberg_marquardt
from annotator.geometry.lie import cross, perturb
from annotator.geometry.transforms import make_transform
from annotator.noise import NOISE


@dataclass(frozen=True)
class Observation:
    """One marker seen by one camera.

    Attributes:
        camera: Index of the camera in the rig.
        marker_id: The marker's id.
        model_corners: (4, 3) corners in the model frame (mm), ArUco order.
        image_corners: (4, 2) detected corners (px), same order.
        soft: The id was read through the blur model only (it needs other support).
    """

    camera: int
    marker_id: int
    model_corners: np.ndarray
    image_corners: np.ndarray
    soft: bool = False


@dataclass(frozen=True)
class PoseEstimate:
    """A refined pose ``rig_T_model`` with its 6x6 covariance of ``(w, v)`` (rad, mm)."""

    T: np.ndarray
    covariance: np.ndarray
    residual_rms: float
    sigma_px: float


@dataclass(frozen=True)
class _CameraCorners:
    """The observations of one camera: their indices in the list and their model corners
    (4n, 3), stacked."""

    camera: Camera
    index: np.ndarray
    X: np.ndarray


def _by_camera(obs: Sequence[Observation]) -> dict[int, list[int]]:
    groups: dict[int, list[int]] = {}
    for k, o in enumerate(obs):
        groups.setdefault(o.camera, []).append(k)
    return groups


def _grouped(cameras: Sequence[Camera], obs: Sequence[Observation]) -> list[_CameraCorners]:
    """The observations by camera, in order of first appearance: made once for a
    refinement's many projections."""
    return [
        _CameraCorners(
            cameras[j], np.array(idx), np.concatenate([obs[k].model_corners for k in idx])
        )
        for j, idx in _by_camera(obs).items()
    ]


def _per_camera(
    groups: Sequence[_CameraCorners], T: np.ndarray
) -> Iterator[tuple[_CameraCorners, np.ndarray, np.ndarray, np.ndarray]]:
    """For each camera with observations: its group, ``cam_T_model`` M, the projected corners
    (4n, 2) and OpenCV's Jacobian of the projection (8n, 15: rvec, tvec, focal lengths,
    principal point, distortion)."""
    for g in groups:
        M = g.camera.cam_T_rig @ T
        rvec, _ = cv2.Rodrigues(M[:3, :3])
        uv, jac = cv2.projectPoints(g.X, rvec, M[:3, 3], g.camera.K, g.camera.dist)
        yield g, M, uv.reshape(-1, 2), jac


def _project(
    cameras: Sequence[Camera], obs: Sequence[Observation], T: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Projected corners (len(obs), 4, 2) of every observation under ``rig_T_model`` T, and
    their depths (len(obs), 4) in their camera (mm)."""
    uv = np.empty((len(obs), 4, 2))
    z = np.empty((len(obs), 4))
    for g, M, p, _ in _per_camera(_grouped(cameras, obs), T):
        uv[g.index] = p.reshape(len(g.index), 4, 2)
        z[g.index] = (g.X @ M[2, :3] + M[2, 3]).reshape(len(g.index), 4)
    return uv, z


def reprojection_errors(
    cameras: Sequence[Camera], obs: Sequence[Observation], T: np.ndarray
) -> np.ndarray:
    """RMS corner reprojection error (px) of each observation under ``rig_T_model`` T.

    Observations behind their camera get infinity.
    """
    if not obs:
        return np.zeros(0)
    uv, z = _project(cameras, obs, T)
    # The mean of the four corners' squares as np.mean takes it (its sum, then / 4), without
    # its wrapper: solvers ask for these errors hundreds of times a scene.
    squares = np.sum((uv - np.stack([o.image_corners for o in obs])) ** 2, axis=-1)
    err = np.sqrt(np.add.reduce(squares, axis=-1) / 4)
    err[(z <= 0).any(axis=1)] = np.inf
    return err


def candidate_poses(cameras: Sequence[Camera], obs: Sequence[Observation]) -> list[np.ndarray]:
    """Pose hypotheses ``rig_T_model`` from each camera alone (see :func:`iter_candidate_poses`)."""
    return list(iter_candidate_poses(cameras, obs))


def iter_candidate_poses(
    cameras: Sequence[Camera], obs: Sequence[Observation]
) -> Iterator[np.ndarray]:
    """Pose hypotheses ``rig_T_model`` from each camera alone, the likeliest first.

    First SQPnP on all the markers of every camera that sees two or more, then both IPPE
    solutions of every single marker (a lone square has two poses that explain it almost
    equally well). Lazy, so that a caller satisfied early does not pay for the rest.
    """
    groups = _by_camera(obs)
    for j in sorted(groups):
        if len(groups[j]) < 2:
            continue
        cam = cameras[j]
        X = np.concatenate([obs[k].model_corners for k in groups[j]])
        x = np.concatenate([obs[k].image_corners for k in groups[j]])
        ok, rvec, tvec = cv2.solvePnP(X, x, cam.K, cam.dist, flags=cv2.SOLVEPNP_SQPNP)
        if ok:
            yield cam.rig_T_cam @ make_transform(cv2.Rodrigues(rvec)[0], tvec.ravel())
    for j in sorted(groups):
        cam = cameras[j]
        for k in groups[j]:
            for T in lone_marker_poses(cam, obs[k]):
                yield cam.rig_T_cam @ T


def lone_marker_poses(cam: Camera, o: Observation) -> list[np.ndarray]:
    """Both IPPE solutions ``cam_T_model`` of one marker, best first.

    OpenCV's IPPE takes the object points to lie in the plane z = 0 (measured: a marker on a
    part's face at z = 35 mm came out 70 mm too near), so the corners are expressed in the
    marker's own frame first (origin at its centre, z along its normal), flattened onto their
    best-fit plane (a marker on a curved surface is off it by a fraction of a millimetre: the
    joint refinement finishes the job), and the poses brought back to the model frame.
    """
    X = o.model_corners.astype(np.float64)
    c = X.mean(axis=0)
    B = np.linalg.svd(X - c)[2].T  # columns: in-plane axes, then the normal
    if np.linalg.det(B) < 0:
        B[:, 2] *= -1
    local = (X - c) @ B
    local[:, 2] = 0.0
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            local,
            o.image_corners.astype(np.float64),
            cam.K,
            cam.dist,
            flags=cv2.SOLVEPNP_IPPE,
        )
    except cv2.error:
        return []
    local_T_model = make_transform(B.T, -B.T @ c)
    return [
        make_transform(cv2.Rodrigues(r)[0], t.ravel()) @ local_T_model
        for r, t in zip(rvecs[:n], tvecs[:n])
    ]


#: A pose, its corner residuals and their Jacobian.
_DAMPING = Damping(start=1e-3, floor=1e-9, ceiling=1e8)


class _Projected:
    """A pose's stacked corner residuals, and its Jacobian made when first asked for: a
    trial step that the iteration refuses needs its residuals alone."""

    def __init__(self, groups: Sequence[_CameraCorners], T: np.ndarray, x: np.ndarray) -> None:
        self.T = T
        self.r, self._jacobians = _residuals(groups, T, x)
        self._J: np.ndarray | None = None

    @property
    def J(self) -> np.ndarray:
        if self._J is None:
            self._J = _jacobian(self._jacobians, self.T, len(self.r) // 8)
        return self._J


def refine_pose(
    cameras: Sequence[Camera],
    obs: Sequence[Observation],
    T0: np.ndarray,
    *,
    sigma_floor: float = NOISE.corner_px,
    max_iterations: int = 50,
) -> PoseEstimate:
    """Jointly refine ``rig_T_model`` over all observations (all cameras), from ``T0``.

    Levenberg-Marquardt on the stacked corner residuals, with the analytic Jacobian (OpenCV's
    projection derivatives, distortion included, chained with the pose perturbation). The
    covariance is ``sigma^2 (J^T J)^-1`` at the optimum, with ``sigma`` the residual standard
    deviation, never below ``sigma_floor`` px: with few corners the residuals underestimate
    the corner noise (the pose absorbs part of it).
    """
    x = np.stack([o.image_corners for o in obs])
    groups = _grouped(cameras, obs)
    start = _Projected(groups, np.array(T0, dtype=float), x)

    def normal(state: _Projected) -> tuple[np.ndarray, np.ndarray]:
        J = state.J
        return J.T @ J, J.T @ state.r

    def trial(
        state: _Projected, lin: tuple[np.ndarray, np.ndarray], damping: float
    ) -> tuple[_Projected, float, np.ndarray]:
        JtJ, g = lin
        step = np.linalg.solve(JtJ + damping * np.diag(np.diag(JtJ) + 1e-12), -g)
        new = _Projected(groups, perturb(state.T, step), x)
        return new, new.r @ new.r, step

    found = levenberg_marquardt(
        start,
        start.r @ start.r,
        normal,
        trial,
        damping=_DAMPING,
        small=lambda cost, new, step: (
            cost - new < 1e-12 * max(cost, 1e-12) or np.abs(step).max() < 1e-10
        ),
        max_iterations=max_iterations,
    )
    T, r, J, cost = found.state.T, found.state.r, found.state.J, found.cost
    dof = max(r.size - 6, 1)
    sigma = max(float(np.sqrt(cost / dof)), sigma_floor)
    try:
        cov = np.linalg.inv(J.T @ J) * sigma**2
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.inf)
    return PoseEstimate(
        T=T, covariance=cov, residual_rms=float(np.sqrt(np.mean(r**2) * 2)), sigma_px=sigma
    )


def residuals_jacobian(
    cameras: Sequence[Camera], obs: Sequence[Observation], T: np.ndarray, x: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Stacked corner residuals (projected - detected, (8 len(obs),)) and their Jacobian
    (8 len(obs), 6) with respect to ``(w, v)`` at T.

    A model point X is at ``y = R X + t`` in the rig and ``c = Rc y + tc`` in the camera;
    ``dc/dw = -Rc [R X]x`` and ``dc/dv = Rc``. OpenCV's derivative of the pixel with respect
    to its ``tvec`` is the derivative with respect to ``c``.
    """
    projected = _Projected(_grouped(cameras, obs), T, x)
    return projected.r, projected.J


def corner_residuals(
    cameras: Sequence[Camera], obs: Sequence[Observation], T: np.ndarray, x: np.ndarray
) -> np.ndarray:
    """:func:`residuals_jacobian`'s residuals alone (the same numbers)."""
    return _residuals(_grouped(cameras, obs), T, x)[0]


def _residuals(
    groups: Sequence[_CameraCorners], T: np.ndarray, x: np.ndarray
) -> tuple[np.ndarray, list[tuple[_CameraCorners, np.ndarray]]]:
    """The stacked residuals of observations grouped by camera, and per camera OpenCV's
    Jacobian of its projection (for :func:`_jacobian`)."""
    r = np.empty((len(x), 4, 2))
    jacobians = []
    for g, _, uv, jac in _per_camera(groups, T):
        r[g.index] = uv.reshape(len(g.index), 4, 2) - x[g.index]
        jacobians.append((g, jac))
    return r.ravel(), jacobians


def _jacobian(
    jacobians: Sequence[tuple[_CameraCorners, np.ndarray]], T: np.ndarray, count: int
) -> np.ndarray:
    """The residuals' Jacobian (8 count, 6) at T from the projections' (see
    :func:`residuals_jacobian`)."""
    J = np.empty((count, 4, 2, 6))
    for g, jac in jacobians:
        n = len(g.index)
        G = jac[:, 3:6].reshape(-1, 2, 3) @ g.camera.cam_T_rig[:3, :3]  # d(pixel)/dy, (N, 2, 3)
        y = g.X @ T[:3, :3].T  # R X, about the rig origin
        Jw = cross(y[:, None, :], G)  # g^T (-[y]x) = (y x g)^T
        J[g.index] = np.concatenate([Jw, G], axis=-1).reshape(n, 4, 2, 6)
    return J.reshape(-1, 6)
