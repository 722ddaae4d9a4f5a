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

The solve is Levenberg-Marquardt with Huber weights (iteratively reweighted) so that a
corner off by many pixels pulls with a bounded force. Frames see each other only through the
instances, so the normal equations are built block by block (a frame's 6x6, an instance's,
and each frame-instance pair's) and the frames are eliminated first (the Schur complement):
what is left to solve is the size of the instances alone, whatever the number of frames.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TypeVar

import cv2
import numpy as np

from annotator.geometry.camera import Camera
from annotator.geometry.least_squares import Damping, levenberg_marquardt
from annotator.geometry.lie import perturb
from annotator.geometry.robust import huber_cost, huber_weights, robust_sigma
from annotator.noise import NOISE

__all__ = ["BundleObservations", "BundleResult", "bundle_adjust"]

_I = TypeVar("_I")
_T = TypeVar("_T")

#: Eigenvalues of the normal matrix scaled to a unit diagonal below this are directions the
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
        cross_covariance: (F, I, 6, 6) between each frame's ``(w, v)`` (rows) and each
            instance's (:meth:`joint_covariance`); empty when not asked for.
    """

    scene_T_rig: np.ndarray
    scene_T_model: np.ndarray
    frame_covariance: np.ndarray
    instance_covariance: np.ndarray
    residual_px: np.ndarray
    sigma_px: float
    iterations: int
    cross_covariance: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))

    def joint_covariance(self, instance: int, frame: int) -> np.ndarray:
        """The 12x12 covariance of instance ``instance``'s ``(w, v)`` then frame ``frame``'s,
        cross terms included (zero for the fixed frame's: it defines the scene frame)."""
        out = np.zeros((12, 12))
        out[:6, :6] = self.instance_covariance[instance]
        out[6:, 6:] = self.frame_covariance[frame]
        cross = self.cross_covariance[frame, instance]
        out[6:, :6] = cross
        out[:6, 6:] = cross.T
        return out


#: Levenberg's damping of the adjustment.
_DAMPING = Damping(start=1e-4, floor=1e-9, ceiling=1e6)


def bundle_adjust(
    cameras: Sequence[Camera],
    obs: BundleObservations,
    scene_T_rig: np.ndarray,
    scene_T_model: np.ndarray,
    *,
    fixed_frame: int,
    depth_camera: int | None = None,
    corner_sigma_px: float = NOISE.corner_px,
    depth_sigma_mm: float = NOISE.marker_depth_mm,
    huber_px: float = 1.0,
    max_iterations: int = 30,
    covariance: bool = True,
    obs_sigma_px: np.ndarray | None = None,
) -> BundleResult:
    """Refine ``scene_T_rig`` (F, 4, 4) and ``scene_T_model`` (I, 4, 4) jointly over ``obs``.

    Frame ``fixed_frame`` defines the scene frame and is not moved. Frames and instances
    without observations keep their poses and get infinite covariance. ``depth_camera``: the
    rig camera whose observations' ``depth_mm`` constrain their marker's depth.
    ``covariance``: False leaves the covariances out (zero), for a solve whose outliers are
    still to be sorted out. ``obs_sigma_px``: (N,) each observation's own corner noise (a
    blurred frame's, a noisy frame's), its corners weighed by ``corner_sigma_px`` over it
    (never more than 1); None: every corner ``corner_sigma_px``.
    """
    frames = np.array(scene_T_rig, dtype=np.float64, copy=True)
    models = np.array(scene_T_model, dtype=np.float64, copy=True)
    shape = _Shape(len(frames), len(models), fixed_frame)
    depth_weight = corner_sigma_px / depth_sigma_mm
    camera = -1 if depth_camera is None else depth_camera  # -1: no camera of the rig
    has_depth = np.isfinite(obs.depth_mm) & (obs.camera == camera)
    scale = np.ones(len(obs))
    if obs_sigma_px is not None:
        scale = np.minimum(corner_sigma_px / np.maximum(obs_sigma_px, 1e-9), 1.0)

    def project(frames: np.ndarray, models: np.ndarray) -> _Projection:
        return _project(cameras, obs, frames, models, has_depth, depth_weight, scale, pool)

    # A trial step needs the residuals alone: the Jacobian is made from its projection only
    # for a step taken (half the steps of a long solve are refused).
    State = tuple[np.ndarray, np.ndarray, _Projection]  # frames, instances, projected there
    Step = tuple[np.ndarray, np.ndarray]

    def normal(state: State) -> _Normal:
        lin = _jacobian(obs, state[2], scale, pool)
        return _normal(lin, groups, huber_weights(lin.r, huber_px), shape, pool)

    def trial(state: State, normal: _Normal, damping: float) -> tuple[State, float, Step] | None:
        step = _solve(normal, damping)
        if step is None:
            return None
        f_new, m_new = _apply(state[0], state[1], *step)
        projected = project(f_new, m_new)
        return (f_new, m_new, projected), huber_cost(projected.r, huber_px), step

    # Threads for this solve only: a process that forks workers later should have none.
    with ThreadPoolExecutor(SOLVE_THREADS) as pool:
        groups = _Groups.of(obs, shape, has_depth)
        start = project(frames, models)
        found = levenberg_marquardt(
            (frames, models, start),
            huber_cost(start.r, huber_px),
            normal,
            trial,
            damping=_DAMPING,
            small=_converged,
            max_iterations=max_iterations,
        )
        return _result(
            found.state,
            groups,
            shape,
            scale,
            found.iterations,
            corner_sigma_px=corner_sigma_px,
            huber_px=huber_px,
            covariance=covariance,
            pool=pool,
        )


def _converged(cost: float, new: float, step: tuple[np.ndarray, np.ndarray]) -> bool:
    """The LM step gained too little, or moved nothing."""
    biggest = max(float(np.abs(step[0]).max(initial=0.0)), float(np.abs(step[1]).max()))
    return cost - new < 1e-7 * max(cost, 1e-12) or biggest < 1e-8


def _result(
    state: tuple[np.ndarray, np.ndarray, _Projection],
    groups: _Groups,
    shape: _Shape,
    scale: np.ndarray,
    iterations: int,
    *,
    corner_sigma_px: float,
    huber_px: float,
    covariance: bool,
    pool: Executor | None = None,
) -> BundleResult:
    """The solved poses ``state`` (frames, instances, their projection) with each
    observation's residual, the corner noise the inliers show and (``covariance``) the
    poses' covariances."""
    frames, models, projected = state
    obs = groups.obs
    corners = projected.r[: 8 * len(obs)].reshape(-1, 4, 2)
    per_obs = np.sqrt(np.mean(np.sum(corners**2, axis=-1), axis=-1)) / scale
    # The corner noise as the inliers show it (median absolute deviation, robust to the
    # few observations the Huber weights hold back).
    sigma = robust_sigma(corners)
    sigma = max(sigma, corner_sigma_px / 3)
    n_frames, n_models = shape.frames, shape.models
    if not covariance:
        zero_f, zero_m = np.zeros((n_frames, 6, 6)), np.zeros((n_models, 6, 6))
        return BundleResult(frames, models, zero_f, zero_m, per_obs, sigma, iterations)
    inliers = np.repeat(per_obs * scale < 4 * max(sigma, huber_px / 3), 8).astype(float)
    weights = np.concatenate([inliers, np.ones(projected.r.size - inliers.size)])
    lin = _jacobian(obs, projected, scale, pool)
    cov_f, cov_m, cross = _covariance(_normal(lin, groups, weights, shape, pool), sigma)
    return BundleResult(frames, models, cov_f, cov_m, per_obs, sigma, iterations, cross)


@dataclass(frozen=True)
class _Shape:
    """How many frames and instances, and which frame is fixed (it has no unknowns)."""

    frames: int
    models: int
    fixed: int


@dataclass(frozen=True)
class _Linear:
    """Residuals (8 per observation, then one per depth measurement) and their Jacobian by
    blocks: per observation, with respect to its instance's ``(w, v)`` and its frame's
    (``jf`` zero for the fixed frame); per depth measurement (``depth``: which observation)
    the same."""

    r: np.ndarray
    jm: np.ndarray  # (n, 8, 6)
    jf: np.ndarray  # (n, 8, 6)
    depth: np.ndarray  # (m,) observation indices
    jm_depth: np.ndarray  # (m, 6)
    jf_depth: np.ndarray  # (m, 6)


#: One piece of a projection: its observations (rows of the whole), and per camera those
#: of its observations (indices into the piece), d(pixel)/d(camera point) ``G`` and d(camera
#: point)/d(scene point) ``C``.
_Piece = tuple[slice, list[tuple[np.ndarray, np.ndarray, np.ndarray]]]


@dataclass(frozen=True)
class _Projection:
    """The residuals at some poses (as :class:`_Linear` holds them, each observation's
    corner rows weighed), and what their Jacobian is made of (:func:`_jacobian`): the
    corners turned into the scene frame (``y``) and about the frame's centre (``d``), per
    piece of the observations its cameras' derivatives (:data:`_Piece`), and d(depth)/d(scene
    point) ``Hz`` (its residuals are multiplied by ``depth_weight``)."""

    r: np.ndarray
    y: np.ndarray  # (n, 4, 3)
    d: np.ndarray  # (n, 4, 3)
    pieces: list[_Piece]
    Hz: np.ndarray  # (n, 4, 3)
    depth: np.ndarray  # (m,) the observations with a depth residual
    depth_weight: float


#: Threads of a solve: numpy's loops over many observations and OpenCV's projection let go
#: of the interpreter, and a sequence's solve runs alone in its process, with the batch's
#: workers idle meanwhile.
SOLVE_THREADS = 2
#: Fewer observations than this are worked on in one piece.
_SPLIT_OBSERVATIONS = 1024


def _rows(n: int, pool: Executor | None) -> list[slice]:
    """The observations ``0 .. n`` in one piece per thread of ``pool`` (one piece: no pool,
    or too few). Every number made per observation is the same whatever the pieces."""
    if pool is None or n < _SPLIT_OBSERVATIONS:
        return [slice(0, n)]
    bounds = np.linspace(0, n, SOLVE_THREADS + 1).astype(int)
    return [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


def _each(pool: Executor | None, work: Callable[[_I], _T], items: Sequence[_I]) -> list[_T]:
    """``work`` on every item, on ``pool``'s threads when there are several."""
    if pool is None or len(items) == 1:
        return [work(p) for p in items]
    return list(pool.map(work, items))


def _project(
    cameras: Sequence[Camera],
    obs: BundleObservations,
    frames: np.ndarray,
    models: np.ndarray,
    has_depth: np.ndarray,
    depth_weight: float,
    scale: np.ndarray,
    pool: Executor | None = None,
) -> _Projection:
    """The residuals at these poses, ``scale`` weighing each observation's corner rows (as
    :func:`_jacobian` does), and what their Jacobian is made of (:class:`_Projection`);
    ``pool``: threads that share the observations (:func:`_rows`)."""
    n = len(obs)
    y, d, Hz = np.empty((n, 4, 3)), np.empty((n, 4, 3)), np.empty((n, 4, 3))
    uv = np.empty((n, 4, 2))
    z = np.empty((n, 4))
    zero = np.zeros(3)

    def piece(rows: slice) -> _Piece:
        Rm = models[obs.instance[rows], :3, :3]
        tm = models[obs.instance[rows], :3, 3]
        y[rows] = np.einsum("nij,nkj->nki", Rm, obs.model_corners[rows])  # R_i X, (n, 4, 3)
        P = y[rows] + tm[:, None, :]  # scene frame
        Rf = frames[obs.frame[rows], :3, :3]
        cf = frames[obs.frame[rows], :3, 3]
        d[rows] = P - cf[:, None, :]
        Q = np.einsum("nji,nkj->nki", Rf, d[rows])  # rig frame: R_f^T (P - c_f)
        uv_p, z_p, Hz_p = uv[rows], z[rows], Hz[rows]
        per_camera = []
        camera = obs.camera[rows]
        for j, cam in enumerate(cameras):
            sel = np.flatnonzero(camera == j)
            if sel.size == 0:
                continue
            M = cam.cam_T_rig
            pc = Q[sel] @ M[:3, :3].T + M[:3, 3]
            pts, jac = cv2.projectPoints(pc.reshape(-1, 3), zero, zero, cam.K, cam.dist)
            uv_p[sel] = pts.reshape(-1, 4, 2)
            G = jac[:, 3:6].reshape(-1, 4, 2, 3)  # d(pixel)/d(camera point)
            C = M[:3, :3] @ np.swapaxes(Rf[sel], 1, 2)  # d(camera point)/d(scene point)
            per_camera.append((sel, G, C))
            z_p[sel] = pc[..., 2]
            Hz_p[sel] = np.broadcast_to(C[:, None, 2, :], (sel.size, 4, 3))
        return rows, per_camera

    pieces = _each(pool, piece, _rows(n, pool))
    r = (uv - obs.image_corners).reshape(-1)
    sel = np.flatnonzero(has_depth)
    if sel.size:
        # The marker's centre: the mean of its corners, its depth the mean of theirs.
        r = np.concatenate([r, depth_weight * (z[sel].mean(axis=1) - obs.depth_mm[sel])])
    if not np.all(scale == 1.0):
        r[: 8 * n] *= np.repeat(scale, 8)
    return _Projection(r, y, d, pieces, Hz, sel, depth_weight)


def _jacobian(
    obs: BundleObservations, p: _Projection, scale: np.ndarray, pool: Executor | None = None
) -> _Linear:
    """Residuals and Jacobian blocks (:class:`_Linear`) at a projection, each observation's
    corner rows of the Jacobian multiplied by ``scale`` (its weight's square root, as its
    residuals are, :func:`_project`); the depth rows as they are. By the projection's
    pieces, on ``pool``'s threads."""
    n = len(obs)
    jm, jf = np.empty((n, 8, 6)), np.empty((n, 8, 6))
    weighed = not np.all(scale == 1.0)

    def piece(at: int) -> None:
        rows, per_camera = p.pieces[at]
        y, d = p.y[rows], p.d[rows]
        H = np.empty((len(y), 4, 2, 3))  # d(pixel)/d(scene point), through the frame's rotation
        for sel, G, C in per_camera:
            H[sel] = np.einsum("nkab,nbc->nkac", G, C)
        # Instance (w, v): dP = w x y + v;  frame (w, v): dQ = R_f^T ([d]x w - v).
        m = np.concatenate([np.cross(y[:, :, None, :], H), H], axis=-1).reshape(-1, 8, 6)
        f = np.concatenate([np.cross(H, d[:, :, None, :]), -H], axis=-1).reshape(-1, 8, 6)
        if weighed:
            m, f = m * scale[rows, None, None], f * scale[rows, None, None]
        jm[rows], jf[rows] = m, f

    _each(pool, piece, range(len(p.pieces)))
    sel = p.depth
    jm_d = jf_d = np.zeros((0, 6))
    if sel.size:
        hz = p.depth_weight * p.Hz[sel].mean(axis=1)  # (m, 3)
        yc, dc = p.y[sel].mean(axis=1), p.d[sel].mean(axis=1)
        jm_d = np.concatenate([np.cross(yc, hz), hz], axis=-1)
        jf_d = np.concatenate([np.cross(hz, dc), -hz], axis=-1)
    return _Linear(p.r, jm, jf, sel, jm_d, jf_d)


@dataclass(frozen=True)
class _Normal:
    """The normal equations ``A x = -g`` by blocks (the fixed frame's rows left zero)."""

    amm: np.ndarray  # (I, 6, 6)
    aff: np.ndarray  # (F, 6, 6)
    afm: np.ndarray  # (F, I, 6, 6): frame rows, instance columns
    gm: np.ndarray  # (I, 6)
    gf: np.ndarray  # (F, 6)
    fixed: int


@dataclass(frozen=True)
class _Sum:
    """Sums by an index (:meth:`of`): ``out[k] = sum of values[index == k]``, for
    ``k < size``, by sorted sums (many times faster than ``np.add.at``); the sort made once
    for every solve's iteration."""

    order: np.ndarray
    starts: np.ndarray
    keys: np.ndarray
    size: int

    @classmethod
    def of(cls, index: np.ndarray, size: int) -> _Sum:
        order = np.argsort(index, kind="stable")
        sorted_index = index[order]
        starts = np.flatnonzero(np.r_[True, sorted_index[1:] != sorted_index[:-1]])
        if len(index) == 0:
            starts = starts[:0]
        return cls(order, starts, sorted_index[starts], size)

    def __call__(self, values: np.ndarray) -> np.ndarray:
        out = np.zeros((self.size, *values.shape[1:]))
        if len(self.order) == 0:
            return out
        out[self.keys] = np.add.reduceat(values[self.order], self.starts, axis=0)
        return out


@dataclass(frozen=True)
class _Groups:
    """The observations, and their sums by instance, frame and frame-instance pair (of all
    of them, and of those with a depth residual)."""

    obs: BundleObservations
    instance: _Sum
    frame: _Sum
    pair: _Sum
    depth_instance: _Sum
    depth_frame: _Sum
    depth_pair: _Sum

    @classmethod
    def of(cls, obs: BundleObservations, shape: _Shape, has_depth: np.ndarray) -> _Groups:
        pair = obs.frame * shape.models + obs.instance
        k = np.flatnonzero(has_depth)
        n_pairs = shape.frames * shape.models
        return cls(
            obs,
            _Sum.of(obs.instance, shape.models),
            _Sum.of(obs.frame, shape.frames),
            _Sum.of(pair, n_pairs),
            _Sum.of(obs.instance[k], shape.models),
            _Sum.of(obs.frame[k], shape.frames),
            _Sum.of(pair[k], n_pairs),
        )


def _normal(
    lin: _Linear, groups: _Groups, w: np.ndarray, shape: _Shape, pool: Executor | None = None
) -> _Normal:
    """``J^T W J`` and ``J^T W r`` by blocks, ``w`` the weight of every residual; each
    observation's products by pieces and the sums side by side, on ``pool``'s threads."""
    n = len(groups.obs)
    wc, rc = w[: 8 * n].reshape(n, 8), lin.r[: 8 * n].reshape(n, 8)
    mm, ff, fm = np.empty((n, 6, 6)), np.empty((n, 6, 6)), np.empty((n, 6, 6))
    rm, rf = np.empty((n, 6)), np.empty((n, 6))

    def products(rows: slice) -> None:
        jm, jf = lin.jm[rows], lin.jf[rows]
        wm = np.swapaxes(jm * wc[rows, :, None], 1, 2)  # (n, 6, 8)
        wf = np.swapaxes(jf * wc[rows, :, None], 1, 2)
        mm[rows], ff[rows], fm[rows] = wm @ jm, wf @ jf, wf @ jm
        rm[rows], rf[rows] = (wm @ rc[rows, :, None])[..., 0], (wf @ rc[rows, :, None])[..., 0]

    _each(pool, products, _rows(n, pool))
    sums = [
        (groups.instance, mm),
        (groups.frame, ff),
        (groups.pair, fm),
        (groups.instance, rm),
        (groups.frame, rf),
    ]
    amm, aff, afm, gm, gf = _each(pool, lambda s: s[0](s[1]), sums)
    if lin.depth.size:
        wd, rd = w[8 * n :], lin.r[8 * n :]
        jm, jf = lin.jm_depth, lin.jf_depth
        wjm, wjf = jm * wd[:, None], jf * wd[:, None]
        amm += groups.depth_instance(wjm[:, :, None] * jm[:, None, :])
        aff += groups.depth_frame(wjf[:, :, None] * jf[:, None, :])
        afm += groups.depth_pair(wjf[:, :, None] * jm[:, None, :])
        gm += groups.depth_instance(wjm * rd[:, None])
        gf += groups.depth_frame(wjf * rd[:, None])
    afm = afm.reshape(shape.frames, shape.models, 6, 6)
    f = shape.fixed
    aff[f], afm[f], gf[f] = 0.0, 0.0, 0.0
    return _Normal(amm, aff, afm, gm, gf, f)


def _frame_inverses(aff: np.ndarray, fixed: int) -> tuple[np.ndarray, np.ndarray]:
    """Each frame block's inverse, and which frames the observations leave loose (a block
    not of full rank, the fixed frame apart: their inverse zero)."""
    inv = np.zeros_like(aff)
    loose = np.zeros(len(aff), dtype=bool)
    for f, block in enumerate(aff):
        if f == fixed:
            continue
        scale = np.sqrt(np.maximum(np.diag(block), 1e-300))
        w, V = np.linalg.eigh(block / scale[:, None] / scale[None, :])
        if w[0] <= NULL_EIGENVALUE:
            loose[f] = True
            continue
        inv[f] = ((V / w) @ V.T) / scale[:, None] / scale[None, :]
    return inv, loose


def _coupling(normal: _Normal) -> np.ndarray:
    """Every frame's coupling to the instances as one matrix per frame, (F, 6, 6I)."""
    n_frames, n_models = normal.afm.shape[:2]
    return normal.afm.transpose(0, 2, 1, 3).reshape(n_frames, 6, 6 * n_models)


def _reduced(
    normal: _Normal, amm: np.ndarray, c: np.ndarray, B: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The instances' system with the frames eliminated: ``S = A_mm - sum_f B_f^T C_f B_f``
    (6I, 6I) and its right side, ``B`` the frames' coupling (:func:`_coupling`)."""
    n_frames, n_models = B.shape[0], len(amm)
    CB = c @ B
    S = -(B.reshape(6 * n_frames, -1).T @ CB.reshape(6 * n_frames, -1))
    for i in range(n_models):
        S[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] += amm[i]
    Cg = np.einsum("fab,fb->fa", c, normal.gf)
    rhs = normal.gm.reshape(-1) - B.reshape(6 * n_frames, -1).T @ Cg.reshape(-1)
    return S, rhs


def _solve(normal: _Normal, lam: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The damped step ``(frames (F, 6), instances (I, 6))``; None if it cannot be solved."""
    eye = np.eye(6)

    def damped(blocks: np.ndarray) -> np.ndarray:
        diag = np.einsum("kii->ki", blocks)
        return blocks + (lam * diag + 1e-9)[:, :, None] * eye

    aff = damped(normal.aff)
    aff[normal.fixed] = eye  # no unknowns: its step is 0 (its rows are zero)
    c = np.linalg.inv(aff)
    c[normal.fixed] = 0.0
    B = _coupling(normal)
    S, rhs = _reduced(normal, damped(normal.amm), c, B)
    try:
        dm = np.linalg.solve(S, -rhs)
    except np.linalg.LinAlgError:
        return None
    df = -np.einsum("fab,fb->fa", c, normal.gf + B @ dm)
    return df, dm.reshape(-1, 6)


def _apply(
    frames: np.ndarray, models: np.ndarray, df: np.ndarray, dm: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The poses moved by the step (left perturbations in the scene frame)."""
    return perturb(frames, df), perturb(models, dm)


def _covariance(normal: _Normal, sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``sigma^2 A^-1`` by blocks: each frame's, each instance's and each frame-instance
    pair's. What the residuals do not fix (an unknown no residual touches, or a frame and an
    instance that only see each other: their common motion is free) gets infinite variance,
    not a number: the pseudo-inverse of the rest."""
    n_models = normal.amm.shape[0]
    c, loose_f = _frame_inverses(normal.aff, normal.fixed)
    B = _coupling(normal)
    S, _ = _reduced(normal, normal.amm, c, B)
    d = np.diag(S).copy()
    touched = d > 0
    scale = np.where(touched, 1.0 / np.sqrt(np.where(touched, d, 1.0)), 0.0)
    idx = np.flatnonzero(touched)
    w, V = np.linalg.eigh((S * scale[:, None] * scale[None, :])[np.ix_(idx, idx)])
    null = w <= NULL_EIGENVALUE
    inv_w = np.where(null, 0.0, 1.0 / np.where(null, 1.0, w))
    M = np.zeros_like(S)
    M[np.ix_(idx, idx)] = (V * inv_w) @ V.T * scale[idx, None] * scale[None, idx]
    loose_rows = np.ones(S.shape[0], dtype=bool)
    loose_rows[idx] = np.abs(V[:, null]).max(axis=1, initial=0.0) > 1e-3
    loose_m = np.asarray(loose_rows.reshape(n_models, 6).any(axis=1), dtype=bool)
    M4 = M.reshape(n_models, 6, n_models, 6)
    # Frames: with T = C B, their cross terms are -T M and their blocks C + T M T^T.
    TM = (c @ B) @ M  # (F, 6, 6I)
    cross = -TM.reshape(len(c), 6, n_models, 6).transpose(0, 2, 1, 3)  # (F, I, 6, 6)
    cov_f = c + TM @ np.swapaxes(c @ B, 1, 2)
    cov_m = np.stack([M4[i, :, i, :] for i in range(n_models)])
    # A frame is loose when a free motion moves it: a frame and an instance that only see
    # each other move together. An instance free on its own (a misread marker whose corners
    # the weights hold back) leaves the frames that read it where the others put them.
    free = np.zeros((S.shape[0], int(null.sum())))
    free[idx] = V[:, null] * scale[idx, None]
    frame_scale = np.sqrt(np.maximum(np.einsum("kii->ki", normal.aff), 0.0))
    moved = np.abs(((c @ B) @ free) * frame_scale[:, :, None]).max(axis=(1, 2), initial=0.0)
    bad_f = loose_f | (moved > 1e-3)
    cov_m[loose_m] = np.inf
    cov_f[bad_f] = np.inf
    cross[bad_f] = np.inf
    cross[:, loose_m] = np.inf
    cov_f[normal.fixed] = 0.0
    cross[normal.fixed] = 0.0
    return cov_f * sigma**2, cov_m * sigma**2, cross * sigma**2
