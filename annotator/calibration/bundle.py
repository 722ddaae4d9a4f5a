"""The joint refinement of a rig calibration: every camera's intrinsics and extrinsics and
every shot's board pose at once (a bundle adjustment over the board's corners).

Unknowns:

- per camera ``c``: ``fx, fy, cx, cy, k1, k2, p1, p2, k3`` (OpenCV's model; any of them can be
  held fixed, e.g. ``k3`` with a four-coefficient model), and ``k4, k5, k6`` for OpenCV's
  rational model when the state has those columns;
- per camera ``c > 0``: ``cam_T_rig`` (camera 0 *is* the rig frame, which fixes the gauge);
- per shot ``s``: ``rig_T_board``.

Residuals: for every chessboard corner ``X`` (board frame) detected at ``x`` in camera ``c``
in shot ``s``, ``project_c(cam_T_rig_c @ rig_T_board_s @ X) - x`` (pixels, distortion
included). Levenberg-Marquardt minimises their sum of squares with the analytic Jacobian:
OpenCV's derivatives of the projection (``cv2.projectPoints``: with respect to the point in
the camera frame and to the intrinsics) chained with left perturbations of the poses,
``R -> exp([w]x) R``, ``t -> t + v``. The Jacobian is sparse (a corner depends on one camera
and one shot), so the normal equations are assembled and solved sparse, with the columns
scaled to unit norm (Marquardt's scaling), so that an iteration's cost grows with the
corners, not with their square.

The covariance of the camera parameters (marginalised over the board poses) is
``sigma^2 (J^T J)^-1`` at the optimum, ``sigma`` the residual standard deviation per axis.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from annotator.geometry.least_squares import Damping, Stop, levenberg_marquardt
from annotator.geometry.lie import perturb

#: Names of the intrinsic parameters of a camera, in their order in the parameter vector
#: (the last three only with the rational model).
INTRINSICS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


@dataclass(frozen=True)
class Corners:
    """Every corner observation, flattened (one row per detected corner).

    Attributes:
        camera: (N,) camera index of each corner.
        shot: (N,) shot index (into the board poses).
        board: (N, 3) corner position in the board frame, mm.
        pixel: (N, 2) detected pixel position.
    """

    camera: np.ndarray
    shot: np.ndarray
    board: np.ndarray
    pixel: np.ndarray

    def subset(self, keep: np.ndarray) -> Corners:
        """The observations where ``keep`` (bool (N,)) is true."""
        return Corners(self.camera[keep], self.shot[keep], self.board[keep], self.pixel[keep])


@dataclass
class RigState:
    """The unknowns of the refinement.

    Attributes:
        intrinsics: (C, 9) ``fx, fy, cx, cy, k1, k2, p1, p2, k3`` per camera, or (C, 12) with
            ``k4, k5, k6`` (OpenCV's rational model).
        cam_T_rig: (C, 4, 4) rig-to-camera transforms; ``cam_T_rig[0]`` is the identity.
        rig_T_board: (S, 4, 4) board pose of every shot in the rig frame.
        free_intrinsics: (9,) or (12,) bool, which intrinsics are estimated (the others stay
            put).
    """

    intrinsics: np.ndarray
    cam_T_rig: np.ndarray
    rig_T_board: np.ndarray
    free_intrinsics: np.ndarray = field(default_factory=lambda: np.ones(9, bool))

    def copy(self) -> RigState:
        return RigState(
            self.intrinsics.copy(),
            self.cam_T_rig.copy(),
            self.rig_T_board.copy(),
            self.free_intrinsics.copy(),
        )

    def K(self, c: int) -> np.ndarray:
        """3x3 camera matrix of camera ``c``."""
        fx, fy, cx, cy = self.intrinsics[c, :4]
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def dist(self, c: int) -> np.ndarray:
        """Distortion coefficients ``k1, k2, p1, p2, k3[, k4, k5, k6]`` of camera ``c``."""
        return self.intrinsics[c, 4:].copy()


@dataclass(frozen=True)
class _Layout:
    """Where each unknown sits in the vector of free parameters."""

    cameras: int
    shots: int
    free_intrinsics: np.ndarray  # (9,) bool

    @property
    def n_intr(self) -> int:
        return int(self.free_intrinsics.sum())

    @property
    def camera_block(self) -> int:
        """Number of camera parameters (intrinsics of all, extrinsics of cameras 1..C-1)."""
        return self.cameras * self.n_intr + 6 * (self.cameras - 1)

    @property
    def size(self) -> int:
        return self.camera_block + 6 * self.shots

    def intr(self, c: int) -> int:
        return c * self.n_intr

    def extr(self, c: int) -> int:
        """First column of camera ``c``'s (w, v); only for c >= 1."""
        return self.cameras * self.n_intr + 6 * (c - 1)

    def pose(self, s: np.ndarray) -> np.ndarray:
        """First columns of the poses of shots ``s`` (an index array)."""
        return self.camera_block + 6 * s


@dataclass(frozen=True)
class RefineResult:
    """The refined state and what the optimiser saw.

    Attributes:
        state: The refined unknowns.
        residuals: (N, 2) projected minus detected pixel of every corner.
        iterations: Levenberg-Marquardt iterations taken.
        converged: It stopped because a step no longer lowered the cost (by more than the
            tolerance), not at the iteration limit.
        sigma_px: Residual standard deviation per axis (with the degrees of freedom).
        camera_covariance: Per camera, the covariance of its free intrinsics (in
            ``INTRINSICS`` order, fixed ones left out) followed, for cameras 1..C-1, by that of
            the left perturbation ``(w, v)`` of its ``cam_T_rig`` (rad, mm).
    """

    state: RigState
    residuals: np.ndarray
    iterations: int
    sigma_px: float
    camera_covariance: list[np.ndarray]
    converged: bool = True


def project(state: RigState, obs: Corners) -> np.ndarray:
    """(N, 2) projection of every observed corner under ``state``."""
    out = np.empty((len(obs.camera), 2))
    for c in range(state.intrinsics.shape[0]):
        sel = obs.camera == c
        if np.any(sel):
            out[sel] = _project_camera(state, c, obs.shot[sel], obs.board[sel])[0]
    return out


def _project_camera(
    state: RigState, c: int, shot: np.ndarray, board: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (n, 2), OpenCV's Jacobian (n, 2, 15), the points in the rig frame (n, 3) and in
    the camera frame (n, 3) of corners seen by camera ``c``."""
    Rb = state.rig_T_board[shot, :3, :3]
    tb = state.rig_T_board[shot, :3, 3]
    y = np.einsum("nij,nj->ni", Rb, board) + tb
    M = state.cam_T_rig[c]
    xc = y @ M[:3, :3].T + M[:3, 3]
    uv, jac = cv2.projectPoints(
        xc.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), state.K(c), state.dist(c)
    )
    return uv.reshape(-1, 2), jac.reshape(-1, 2, jac.shape[1]), y, xc


def residuals_jacobian(
    state: RigState, obs: Corners, layout: _Layout
) -> tuple[np.ndarray, sp.csr_matrix]:
    """Stacked residuals (2N,) and their sparse Jacobian (2N, layout.size)."""
    n = len(obs.camera)
    r = np.empty((n, 2))
    free = np.flatnonzero(layout.free_intrinsics)
    ni = len(free)
    width = ni + 12  # intrinsics, camera pose (zero for camera 0), shot pose
    vals = np.zeros((n, 2, width))
    cols = np.zeros((n, width), np.int64)
    for c in range(layout.cameras):
        idx = np.flatnonzero(obs.camera == c)
        if len(idx) == 0:
            continue
        shot = obs.shot[idx]
        uv, jac, y, _ = _project_camera(state, c, shot, obs.board[idx])
        r[idx] = uv - obs.pixel[idx]
        G = jac[:, :, 3:6]  # d pixel / d point in the camera frame
        # OpenCV's columns: rotation, translation, focal lengths, principal point, distortion.
        vals[idx, :, :ni] = jac[:, :, 6 : 6 + state.intrinsics.shape[1]][:, :, free]
        cols[idx, :ni] = layout.intr(c) + np.arange(ni)
        Rc = state.cam_T_rig[c, :3, :3]
        if c > 0:
            ry = y @ Rc.T
            vals[idx, :, ni : ni + 3] = np.cross(ry[:, None, :], G)
            vals[idx, :, ni + 3 : ni + 6] = G
            cols[idx, ni : ni + 6] = layout.extr(c) + np.arange(6)
        else:  # no unknowns: point the zero entries at the shot's columns (summed, harmless)
            cols[idx, ni : ni + 6] = layout.pose(shot)[:, None] + np.arange(6)
        GR = G @ Rc  # d pixel / d point in the rig frame
        rx = y - state.rig_T_board[shot, :3, 3]  # R_s X
        vals[idx, :, ni + 6 : ni + 9] = np.cross(rx[:, None, :], GR)
        vals[idx, :, ni + 9 :] = GR
        cols[idx, ni + 6 :] = layout.pose(shot)[:, None] + np.arange(6)
    rows = np.repeat(np.arange(2 * n), width)
    J = sp.csr_matrix(
        (vals.reshape(-1), (rows, np.repeat(cols, 2, axis=0).reshape(-1))),
        shape=(2 * n, layout.size),
    )
    return r.reshape(-1), J


def _apply(state: RigState, step: np.ndarray, layout: _Layout) -> RigState:
    """The state moved by a step of the free parameters."""
    new = state.copy()
    free = np.flatnonzero(layout.free_intrinsics)
    for c in range(layout.cameras):
        new.intrinsics[c, free] += step[layout.intr(c) : layout.intr(c) + len(free)]
        if c > 0:
            new.cam_T_rig[c] = perturb(
                state.cam_T_rig[c], step[layout.extr(c) : layout.extr(c) + 6]
            )
    new.rig_T_board = perturb(state.rig_T_board, step[layout.camera_block :].reshape(-1, 6))
    return new


#: Levenberg's damping of the calibration: it stops once a damping of 1e12 is needed (the
#: ceiling is the float just below it).
_DAMPING = Damping(start=1e-4, floor=1e-12, ceiling=float(np.nextafter(1e12, 0)))


def refine(
    state: RigState,
    obs: Corners,
    *,
    max_iterations: int = 100,
    tolerance: float = 1e-12,
) -> RefineResult:
    """Levenberg-Marquardt over all unknowns from ``state`` (not modified).

    Every shot index in ``obs.shot`` must have a board pose in ``state.rig_T_board``; shots
    without observations keep theirs. Stops when an accepted step lowers the cost by less
    than ``tolerance`` (relative) or after ``max_iterations``.
    """
    C = state.intrinsics.shape[0]
    layout = _Layout(C, state.rig_T_board.shape[0], np.asarray(state.free_intrinsics, bool))
    r0, J0 = residuals_jacobian(state, obs, layout)
    Linear = tuple[RigState, np.ndarray, sp.csr_matrix]  # the state, its residuals, Jacobian
    Normal = tuple[np.ndarray, np.ndarray, np.ndarray, sp.csc_matrix]

    def normal(at: Linear) -> Normal:
        _, r, J = at
        H = (J.T @ J).tocsc()
        d = H.diagonal()
        scale = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
        S = sp.diags(scale)
        return J.T @ r, d, scale, (S @ H @ S).tocsc()

    def trial(at: Linear, normal: Normal, damping: float) -> tuple[Linear, float, np.ndarray]:
        g, d, scale, Hs = normal
        # Unobserved unknowns (a shot without corners) get a unit diagonal.
        A = Hs + sp.diags(np.where(d > 0, damping, 1.0))
        step = -scale * splu(A.tocsc()).solve(scale * g)
        moved = _apply(at[0], step, layout)
        r_new, J_new = residuals_jacobian(moved, obs, layout)
        return (moved, r_new, J_new), float(r_new @ r_new), step

    found = levenberg_marquardt(
        (state, r0, J0),
        float(r0 @ r0),
        normal,
        trial,
        damping=_DAMPING,
        small=lambda cost, new, step: (cost - new) / max(cost, 1e-300) < tolerance,
        max_iterations=max_iterations,
        refused_count=False,
    )
    (state, r, J), cost, iterations = found.state, found.cost, found.iterations
    converged = found.stop in (Stop.SMALL_STEP, Stop.NO_DESCENT)
    dof = max(r.size - layout.size, 1)
    sigma = float(np.sqrt(cost / dof))
    return RefineResult(
        state=state,
        residuals=r.reshape(-1, 2),
        iterations=iterations,
        sigma_px=sigma,
        camera_covariance=_camera_covariance(J, layout, sigma),
        converged=converged,
    )


def _camera_covariance(J: sp.csr_matrix, layout: _Layout, sigma: float) -> list[np.ndarray]:
    """Per camera, the block of ``sigma^2 H^-1`` of its parameters (board poses marginalised)."""
    H = (J.T @ J).tocsc()
    d = H.diagonal()
    # Unobserved shots (no corners left) have empty rows: give them a unit diagonal.
    H = H + sp.diags(np.where(d > 0, 0.0, 1.0))
    d = H.diagonal()
    scale = 1.0 / np.sqrt(d)
    S = sp.diags(scale)
    lu = splu((S @ H @ S).tocsc())
    n = layout.camera_block
    E = np.zeros((layout.size, n))
    E[np.arange(n), np.arange(n)] = scale[:n]
    block = scale[:n, None] * lu.solve(E)[:n] * sigma**2
    out = []
    for c in range(layout.cameras):
        idx = list(range(layout.intr(c), layout.intr(c) + layout.n_intr))
        if c > 0:
            idx += list(range(layout.extr(c), layout.extr(c) + 6))
        out.append(block[np.ix_(idx, idx)])
    return out


def corners_of(
    views: Sequence[tuple[int, int, np.ndarray, np.ndarray]], board_points: np.ndarray
) -> Corners:
    """Flatten views ``(camera, shot, ids, pixels)`` into :class:`Corners`."""
    if not views:
        return Corners(np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 2)))
    cam = np.concatenate([np.full(len(ids), c) for c, _, ids, _ in views])
    shot = np.concatenate([np.full(len(ids), s) for _, s, ids, _ in views])
    board = np.concatenate([board_points[ids] for _, _, ids, _ in views])
    pixel = np.concatenate([np.asarray(px, float).reshape(-1, 2) for _, _, _, px in views])
    return Corners(cam.astype(np.int64), shot.astype(np.int64), board, pixel)
