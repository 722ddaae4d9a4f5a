"""Bundle adjustment of a sequence: every frame's rig pose and every instance's pose at once,
from every marker corner seen in every frame (and the depth at the markers, where measured).

Conventions (the rest of :mod:`annotator.pnp` and FORMAT.md, sequences):

- Poses live in the *scene frame* (the reference camera of one fixed frame). A frame's pose is
  ``scene_T_rig`` (its rig's reference camera in the scene frame), an instance's is
  ``scene_T_model``; camera ``c`` of frame ``f`` sees model point ``X`` of instance ``i`` at
  ``cam_T_rig[c] @ inverse(scene_T_rig[f]) @ scene_T_model[i] @ X``.
- Both are perturbed on the left in the scene frame: ``R -> exp([w]x) R``, ``t -> t + v``.
  For a frame, ``v`` moves the rig's reference camera centre; for an instance it is the
  perturbation :func:`annotator.pnp.rms_uncertainty` takes, so covariances go straight in.
- Corner residuals are in pixels; a depth residual (measured minus predicted depth of a
  marker's centre in the depth camera) is divided by ``depth_sigma_mm / corner_sigma_px``
  so that both weigh as their noise says.

The solve is Levenberg-Marquardt on the sparse normal equations, with Huber weights
(iteratively reweighted) so that a corner off by many pixels pulls with a bounded force.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.sparse as sp

from annotator.geometry.camera import Camera
from annotator.geometry.transforms import rotvec_to_matrix

__all__ = ["BundleObservations", "BundleResult", "bundle_adjust"]

#: Eigenvalues of ``J^T J`` scaled to a unit diagonal below this are directions the
#: observations do not fix.
NULL_EIGENVALUE = 1e-9


@dataclass(frozen=True)
class BundleObservations:
    """Every marker seen in every frame, as flat arrays (one row per marker observation).

    Attributes:
        frame: (N,) index of the frame.
        instance: (N,) index of the instance.
        camera: (N,) index of the rig camera.
        model_corners: (N, 4, 3) the marker's corners in the instance's model frame (mm).
        image_corners: (N, 4, 2) where they were detected (px), same order.
        depth_mm: (N,) measured depth at the marker's centre in the depth camera (NaN: none,
            or not the depth camera).
    """

    frame: np.ndarray
    instance: np.ndarray
    camera: np.ndarray
    model_corners: np.ndarray
    image_corners: np.ndarray
    depth_mm: np.ndarray

    def __len__(self) -> int:
        return int(self.frame.size)

    def subset(self, keep: np.ndarray) -> BundleObservations:
        """The observations where ``keep`` (a boolean mask or indices) says."""
        return BundleObservations(
            self.frame[keep],
            self.instance[keep],
            self.camera[keep],
            self.model_corners[keep],
            self.image_corners[keep],
            self.depth_mm[keep],
        )


@dataclass(frozen=True)
class BundleResult:
    """The adjusted poses and what they rest on.

    Attributes:
        scene_T_rig: (F, 4, 4) every frame's rig pose (the fixed frame's unchanged).
        scene_T_model: (I, 4, 4) every instance's pose.
        frame_covariance: (F, 6, 6) of each frame's ``(w, v)`` (zero for the fixed frame).
        instance_covariance: (I, 6, 6) of each instance's ``(w, v)``.
        residual_px: (N,) RMS corner reprojection error of each observation.
        sigma_px: Robust standard deviation of the corner residuals (never below the floor).
        iterations: Levenberg-Marquardt steps taken.
        covariance: The whole covariance of every unknown (:meth:`joint_covariance`).
    """

    scene_T_rig: np.ndarray
    scene_T_model: np.ndarray
    frame_covariance: np.ndarray
    instance_covariance: np.ndarray
    residual_px: np.ndarray
    sigma_px: float
    iterations: int
    covariance: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 0)))
    fixed_frame: int = 0

    def joint_covariance(self, instance: int, frame: int) -> np.ndarray:
        """The 12x12 covariance of instance ``instance``'s ``(w, v)`` then frame ``frame``'s,
        cross terms included (zero for the fixed frame's: it defines the scene frame)."""
        layout = _Layout(len(self.scene_T_rig), len(self.scene_T_model), self.fixed_frame)
        m = layout.model_slice(instance)
        f = layout.frame_slice(frame)
        out = np.zeros((12, 12))
        out[:6, :6] = self.covariance[m, m]
        if f is not None:
            out[6:, 6:] = self.covariance[f, f]
            out[:6, 6:] = self.covariance[m, f]
            out[6:, :6] = self.covariance[f, m]
        return out


def bundle_adjust(
    cameras: Sequence[Camera],
    obs: BundleObservations,
    scene_T_rig: np.ndarray,
    scene_T_model: np.ndarray,
    *,
    fixed_frame: int,
    depth_camera: int | None = None,
    corner_sigma_px: float = 0.3,
    depth_sigma_mm: float = 2.0,
    huber_px: float = 1.0,
    max_iterations: int = 30,
) -> BundleResult:
    """Refine ``scene_T_rig`` (F, 4, 4) and ``scene_T_model`` (I, 4, 4) jointly over ``obs``.

    Frame ``fixed_frame`` defines the scene frame and is not moved. Frames and instances
    without observations keep their poses and get infinite covariance. ``depth_camera``: the
    rig camera whose observations' ``depth_mm`` constrain their marker's depth.
    """
    frames = np.array(scene_T_rig, dtype=np.float64, copy=True)
    models = np.array(scene_T_model, dtype=np.float64, copy=True)
    n_frames, n_models = len(frames), len(models)
    layout = _Layout(n_frames, n_models, fixed_frame)
    depth_weight = corner_sigma_px / depth_sigma_mm
    has_depth = (
        np.isfinite(obs.depth_mm) & (obs.camera == depth_camera)
        if depth_camera is not None
        else np.zeros(len(obs), dtype=bool)
    )
    lam = 1e-4
    r, J = _linearise(cameras, obs, frames, models, layout, has_depth, depth_weight)
    w = _huber_weights(r, huber_px)
    cost = _robust_cost(r, huber_px)
    iterations = 0
    while iterations < max_iterations:
        iterations += 1
        A = (J.T @ sp.diags(w) @ J).toarray()
        g = J.T @ (w * r)
        diag = np.diag(A).copy()
        free = diag > 0
        step = np.zeros(layout.size)
        if free.any():
            Af = A[np.ix_(free, free)] + lam * np.diag(diag[free] + 1e-9)
            try:
                step[free] = np.linalg.solve(Af, -g[free])
            except np.linalg.LinAlgError:
                break
        f_new, m_new = _apply(frames, models, step, layout)
        r_new, J_new = _linearise(cameras, obs, f_new, m_new, layout, has_depth, depth_weight)
        cost_new = _robust_cost(r_new, huber_px)
        if cost_new < cost:
            done = cost - cost_new < 1e-10 * max(cost, 1e-12) or np.abs(step).max() < 1e-9
            frames, models, r, J, cost = f_new, m_new, r_new, J_new, cost_new
            w = _huber_weights(r, huber_px)
            lam = max(lam / 10, 1e-9)
            if done:
                break
        else:
            lam *= 10
            if lam > 1e6:
                break
    corners = r[: 8 * len(obs)].reshape(-1, 4, 2)
    per_obs = np.sqrt(np.mean(np.sum(corners**2, axis=-1), axis=-1))
    # The corner noise as the inliers show it (median absolute deviation, robust to the
    # few observations the Huber weights hold back).
    sigma = max(float(1.4826 * np.median(np.abs(corners))) if corners.size else 0.0, 0.0)
    sigma = max(sigma, corner_sigma_px / 3)
    inlier_rows = np.repeat(per_obs < 4 * max(sigma, huber_px / 3), 8)
    rows = np.concatenate([inlier_rows, np.ones(r.size - inlier_rows.size, dtype=bool)])
    Ji = J[np.flatnonzero(rows)]
    cov = _covariance(Ji, layout, sigma)
    frame_cov = np.zeros((n_frames, 6, 6))
    inst_cov = np.zeros((n_models, 6, 6))
    for f in range(n_frames):
        s = layout.frame_slice(f)
        frame_cov[f] = np.zeros((6, 6)) if s is None else cov[s, s]
    for i in range(n_models):
        s = layout.model_slice(i)
        inst_cov[i] = cov[s, s]
    return BundleResult(
        frames, models, frame_cov, inst_cov, per_obs, sigma, iterations, cov, fixed_frame
    )


@dataclass(frozen=True)
class _Layout:
    """Where each pose's six unknowns sit in the parameter vector (the fixed frame has none)."""

    n_frames: int
    n_models: int
    fixed: int

    @property
    def size(self) -> int:
        return 6 * (self.n_frames - 1 + self.n_models)

    def frame_column(self, f: np.ndarray) -> np.ndarray:
        """First column of each frame's block (-1 for the fixed frame)."""
        f = np.asarray(f)
        col = 6 * np.where(f > self.fixed, f - 1, f)
        return np.where(f == self.fixed, -1, col)

    def model_column(self, i: np.ndarray) -> np.ndarray:
        return 6 * (self.n_frames - 1) + 6 * np.asarray(i)

    def frame_slice(self, f: int) -> slice | None:
        c = int(self.frame_column(np.array(f)))
        return None if c < 0 else slice(c, c + 6)

    def model_slice(self, i: int) -> slice:
        c = int(self.model_column(np.array(i)))
        return slice(c, c + 6)


def _linearise(
    cameras: Sequence[Camera],
    obs: BundleObservations,
    frames: np.ndarray,
    models: np.ndarray,
    layout: _Layout,
    has_depth: np.ndarray,
    depth_weight: float,
) -> tuple[np.ndarray, sp.csr_matrix]:
    """Residuals (8 per observation, then one per depth measurement) and their sparse
    Jacobian with respect to every frame's and instance's ``(w, v)``."""
    n = len(obs)
    Rm = models[obs.instance, :3, :3]
    tm = models[obs.instance, :3, 3]
    y = np.einsum("nij,nkj->nki", Rm, obs.model_corners)  # R_i X, (n, 4, 3)
    P = y + tm[:, None, :]  # scene frame
    Rf = frames[obs.frame, :3, :3]
    cf = frames[obs.frame, :3, 3]
    d = P - cf[:, None, :]
    Q = np.einsum("nji,nkj->nki", Rf, d)  # rig frame: R_f^T (P - c_f)
    uv = np.empty((n, 4, 2))
    H = np.empty((n, 4, 2, 3))  # d(pixel)/d(scene point), through the frame's rotation
    z = np.empty((n, 4))
    Hz = np.empty((n, 4, 3))
    for j, cam in enumerate(cameras):
        sel = np.flatnonzero(obs.camera == j)
        if sel.size == 0:
            continue
        M = cam.cam_T_rig
        pc = Q[sel] @ M[:3, :3].T + M[:3, 3]
        pts, jac = cv2.projectPoints(pc.reshape(-1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist)
        uv[sel] = pts.reshape(-1, 4, 2)
        G = jac[:, 3:6].reshape(-1, 4, 2, 3)  # d(pixel)/d(camera point)
        C = M[:3, :3] @ np.swapaxes(Rf[sel], 1, 2)  # d(camera point)/d(scene point)
        H[sel] = np.einsum("nkab,nbc->nkac", G, C)
        z[sel] = pc[..., 2]
        Hz[sel] = np.broadcast_to(C[:, None, 2, :], (sel.size, 4, 3))
    r_px = (uv - obs.image_corners).reshape(-1)
    # Instance (w, v): dP = w x y + v;  frame (w, v): dQ = R_f^T ([d]x w - v).
    Jw_m = np.cross(y[:, :, None, :], H)
    Jv_m = H
    Jw_f = np.cross(H, d[:, :, None, :])
    Jv_f = -H
    rows = np.arange(8 * n).reshape(n, 4, 2)
    data = [np.concatenate([Jw_m, Jv_m], axis=-1), np.concatenate([Jw_f, Jv_f], axis=-1)]
    cols = [layout.model_column(obs.instance), layout.frame_column(obs.frame)]
    parts_r, parts_c, parts_v = [], [], []
    for block, col in zip(data, cols):
        keep = col >= 0
        rr = np.broadcast_to(rows[keep][..., None], (*rows[keep].shape, 6))
        cc = col[keep][:, None, None, None] + np.arange(6)
        cc = np.broadcast_to(cc, rr.shape)
        parts_r.append(rr.reshape(-1))
        parts_c.append(cc.reshape(-1))
        parts_v.append(block[keep].reshape(-1))
    residuals = [r_px]
    sel = np.flatnonzero(has_depth)
    if sel.size:
        # The marker's centre: the mean of its corners, its depth the mean of theirs.
        zc = z[sel].mean(axis=1)
        residuals.append(depth_weight * (zc - obs.depth_mm[sel]))
        base = 8 * n + np.arange(sel.size)
        hz = depth_weight * Hz[sel].mean(axis=1)  # (m, 3)
        yc, dc = y[sel].mean(axis=1), d[sel].mean(axis=1)
        blocks = [
            (
                np.concatenate([np.cross(yc, hz), hz], axis=-1),
                layout.model_column(obs.instance[sel]),
            ),
            (np.concatenate([np.cross(hz, dc), -hz], axis=-1), layout.frame_column(obs.frame[sel])),
        ]
        for block, col in blocks:
            keep = col >= 0
            parts_r.append(np.repeat(base[keep], 6))
            parts_c.append((col[keep][:, None] + np.arange(6)).reshape(-1))
            parts_v.append(block[keep].reshape(-1))
    r = np.concatenate(residuals)
    J = sp.csr_matrix(
        (np.concatenate(parts_v), (np.concatenate(parts_r), np.concatenate(parts_c))),
        shape=(r.size, layout.size),
    )
    return r, J


def _apply(
    frames: np.ndarray, models: np.ndarray, step: np.ndarray, layout: _Layout
) -> tuple[np.ndarray, np.ndarray]:
    """The poses moved by ``step`` (left perturbations in the scene frame)."""
    frames, models = frames.copy(), models.copy()
    for f in range(layout.n_frames):
        s = layout.frame_slice(f)
        if s is not None:
            frames[f] = _perturb(frames[f], step[s])
    for i in range(layout.n_models):
        models[i] = _perturb(models[i], step[layout.model_slice(i)])
    return frames, models


def _perturb(T: np.ndarray, d: np.ndarray) -> np.ndarray:
    out = T.copy()
    out[:3, :3] = rotvec_to_matrix(d[:3]) @ T[:3, :3]
    out[:3, 3] = T[:3, 3] + d[3:]
    return out


def _huber_weights(r: np.ndarray, k: float) -> np.ndarray:
    a = np.abs(r)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))


def _robust_cost(r: np.ndarray, k: float) -> float:
    a = np.abs(r)
    return float(np.sum(np.where(a <= k, 0.5 * a**2, k * a - 0.5 * k**2)))


def _covariance(J: sp.csr_matrix, layout: _Layout, sigma: float) -> np.ndarray:
    """``sigma^2 (J^T J)^-1``. What the residuals do not fix (an unknown no residual touches,
    or a frame and an instance that only see each other: their common motion is free) gets
    infinite variance, not a number: the pseudo-inverse of the rest."""
    A = (J.T @ J).toarray()
    d = np.diag(A).copy()
    touched = d > 0
    # Scaled to a unit diagonal, radians and millimetres weigh alike: what is left near
    # zero is a direction the observations do not fix, not a unit.
    s = np.where(touched, 1.0 / np.sqrt(np.where(touched, d, 1.0)), 0.0)
    B = A * s[:, None] * s[None, :]
    w, V = np.linalg.eigh(B[np.ix_(touched, touched)])
    null = w <= NULL_EIGENVALUE
    inv_w = np.where(null, 0.0, 1.0 / np.where(null, 1.0, w))
    cov = np.full(A.shape, np.inf)
    sub = (V * inv_w) @ V.T
    idx = np.flatnonzero(touched)
    cov[np.ix_(idx, idx)] = sub * s[idx, None] * s[None, idx] * sigma**2
    loose = idx[np.abs(V[:, null]).max(axis=1, initial=0.0) > 1e-3]
    cov[loose, :] = np.inf
    cov[:, loose] = np.inf
    return cov
