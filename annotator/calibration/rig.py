"""Calibrating a rig from ChArUco corners: screening, initialisation, joint refinement and
rejection of outliers.

1. **Screening.** A view (one camera, one shot) is usable if it has at least
   ``min_corners`` corners that do not lie on one line; the others are rejected with the
   reason.
2. **Per camera.** OpenCV's ``calibrateCamera`` on the camera's usable views gives its
   intrinsics and the board pose in each view; views it cannot fit (RMS above five times
   the median and 2 px) are rejected and the camera calibrated again.
3. **Extrinsics.** For each pair of cameras that saw the same shots, the relative pose
   ``a_T_board @ inv(b_T_board)`` of every common shot; their robust mean (rotations within
   three times the median angle of the medoid, averaged; translations' median) chains every
   camera to camera 0, the rig frame. Each shot's board pose comes from the camera that saw
   most of its corners.
4. **Joint refinement** (:mod:`annotator.calibration.bundle`): all intrinsics, extrinsics
   and board poses at once, over every corner of every usable view (a corner seen by one
   camera only still constrains that camera and the shot's pose).
5. **Outliers.** Corners whose residual exceeds ``outlier_sigmas`` robust standard
   deviations (at least ``min_outlier_px``) are left out, and whole views whose RMS exceeds
   three times the median view's (at least 1 px) or that lose a quarter of their corners;
   then step 4 again, until nothing changes.

RMS figures are those of OpenCV's ``calibrateCamera``: the root mean square of the
Euclidean distance (px) between detected and projected corners.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from annotator.calibration.board import BoardSpec
from annotator.calibration.bundle import (
    INTRINSICS,
    Corners,
    RefineResult,
    RigState,
    project,
    refine,
)
from annotator.calibration.outliers import Moments, inliers
from annotator.calibration.records import (
    DISTORTION_MODELS,
    Calibration,
    CalibrationSettings,
    CameraReport,
    Rejection,
    ShotReport,
    View,
)
from annotator.calibration.single import calibrate_camera, opencv_flags, require_shots, screen_views
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import invert, make_transform


@dataclass(frozen=True)
class _Setup:
    """What :func:`solve_rig` was given, passed along its steps."""

    views: Sequence[View]
    cameras: Sequence[str]
    sizes: Sequence[tuple[int, int]]
    shots: Sequence[str]
    board: BoardSpec
    opts: CalibrationSettings
    where: Mapping[str, Path]

    @property
    def n_dist(self) -> int:
        """Distortion coefficients kept per camera: OpenCV's five, or eight (rational)."""
        return 8 if self.opts.dist_coeffs == 8 else 5

    def require_shots(self, usable: Sequence[View]) -> None:
        """Every camera still has enough usable shots (else a UserError naming it)."""
        for c, name in enumerate(self.cameras):
            require_shots(usable, c, name, self.views, self.opts, self.where)


@dataclass(frozen=True)
class _Initial:
    """Step 2's outcome: each camera's intrinsics row, board poses ``{(camera, shot):
    cam_T_board}`` and RMS, and the views still usable."""

    intrinsics: np.ndarray
    poses: dict[tuple[int, int], np.ndarray]
    rms: list[float]
    usable: list[View]

    def focal(self, c: int) -> tuple[float, float]:
        return float(self.intrinsics[c, 0]), float(self.intrinsics[c, 1])

    def board_distance(self, c: int, board: BoardSpec) -> float:
        """The farthest camera ``c`` saw the board's centre, mm."""
        centre = np.array([*np.asarray(board.size_mm) / 2, 0.0])
        d = [
            np.linalg.norm(T[:3, :3] @ centre + T[:3, 3])
            for (k, _), T in self.poses.items()
            if k == c
        ]
        return float(max(d)) if d else float("nan")


@dataclass(frozen=True)
class _Observations:
    """The corners of the usable views, flattened, each with its view (an index into
    ``keys``, the sorted ``(camera, shot)`` of the views)."""

    corners: Corners
    view_index: np.ndarray
    keys: list[tuple[int, int]]


@dataclass(frozen=True)
class _Fit:
    """The last refinement: the state, the optimiser's result, the observations, the
    residual of each (projected minus detected) and which of them it used."""

    state: RigState
    result: RefineResult
    obs: Corners
    residuals: np.ndarray
    keep: np.ndarray

    @property
    def err2(self) -> np.ndarray:
        """Squared residual norm of each corner."""
        return np.sum(self.residuals**2, axis=1)

    @property
    def used_views(self) -> set[tuple[int, int]]:
        """``(camera, shot)`` of every view with a corner used."""
        obs, keep = self.obs, self.keep
        return {(int(c), int(s)) for c, s in zip(obs.camera[keep], obs.shot[keep])}


def solve_rig(
    views: Sequence[View],
    *,
    cameras: Sequence[str],
    sizes: Sequence[tuple[int, int]],
    shots: Sequence[str],
    board: BoardSpec,
    options: CalibrationSettings | None = None,
    where: Mapping[str, Path] | None = None,
) -> Calibration:
    """Calibrate the rig (see the module docstring).

    Args:
        views: Every camera's detection in every shot (views without corners included:
            they are reported as "board not found").
        cameras: Camera names, in rig order (the first is the rig frame).
        sizes: Image size (width, height) of each camera.
        shots: Shot names, indexed by ``View.shot``.
        board: The board.
        options: Thresholds and the distortion model.
        where: Optional folder of each camera's images, to name it in error messages.

    Raises:
        UserError: too few usable shots for a camera, cameras that never saw the board in
            the same shot, or a calibration that cannot fit the detections.
    """
    setup = _Setup(
        views, cameras, sizes, shots, board, options or CalibrationSettings(), where or {}
    )
    rejections: list[Rejection] = []
    usable = screen_views(views, cameras, shots, board, setup.opts, rejections)
    setup.require_shots(usable)
    initial = _calibrate_cameras(setup, usable, rejections)
    # 3. Extrinsics and board poses.
    cam_T_rig = _initial_extrinsics(initial.poses, cameras, setup.where)
    rig_T_board = _initial_board_poses(initial, cam_T_rig, len(shots))
    state = RigState(initial.intrinsics, cam_T_rig, rig_T_board, _free_intrinsics(setup))
    obs = _observations(initial.usable, board)
    fit, dropped_views = _refine_without_outliers(state, obs, setup.opts, initial.rms)
    if _short_camera(fit, len(cameras), setup.opts.min_shots):
        # Leaving out views of other moments left a camera too few: its views disagree with
        # the rig beyond leaving some out; the rig is solved without that rule, and the
        # checks say what is wrong.
        fit, dropped_views = _refine_without_outliers(state, obs, setup.opts)
    for (c, s), why in sorted(dropped_views.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        rejections.append(Rejection(shots[s], cameras[c], why))
    used_views = {obs.keys[i] for i in np.unique(obs.view_index[fit.keep])}
    setup.require_shots([v for v in initial.usable if (v.camera, v.shot) in used_views])
    return _assemble(fit, setup, initial, rejections)


def _short_camera(fit: _Fit, n_cameras: int, min_shots: int) -> bool:
    """Whether some camera has fewer than ``min_shots`` views in the fit."""
    per_camera = np.bincount([c for c, _ in fit.used_views], minlength=n_cameras)
    return bool(np.any(per_camera < min_shots))


def _calibrate_cameras(setup: _Setup, usable: list[View], rejections: list[Rejection]) -> _Initial:
    """2. Each camera alone: OpenCV's calibrateCamera; the views it cannot fit left out."""
    flags = opencv_flags(setup.opts.dist_coeffs)
    intrinsics = np.zeros((len(setup.cameras), 4 + setup.n_dist))
    poses: dict[tuple[int, int], np.ndarray] = {}
    initial_rms = []
    for c, name in enumerate(setup.cameras):
        K, dist, cam_poses, rms = calibrate_camera(
            [v for v in usable if v.camera == c],
            setup.board,
            setup.sizes[c],
            flags,
            rejections,
            name,
            setup.shots,
            setup.n_dist,
        )
        usable = [v for v in usable if v.camera != c or (c, v.shot) in cam_poses]
        require_shots(usable, c, name, setup.views, setup.opts, setup.where)
        intrinsics[c] = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist]
        poses.update(cam_poses)
        initial_rms.append(rms)
    return _Initial(intrinsics, poses, initial_rms, usable)


def _initial_board_poses(initial: _Initial, cam_T_rig: np.ndarray, n_shots: int) -> np.ndarray:
    """``rig_T_board`` of every shot, from the camera that saw most of its corners (the
    identity for shots no camera could use)."""
    rig_T_board = np.tile(np.eye(4), (n_shots, 1, 1))
    best: dict[int, tuple[int, int]] = {}
    for v in initial.usable:
        if len(v.ids) > best.get(v.shot, (-1, -1))[0]:
            best[v.shot] = (len(v.ids), v.camera)
    for s, (_, c) in best.items():
        rig_T_board[s] = invert(cam_T_rig[c]) @ initial.poses[(c, s)]
    return rig_T_board


def _free_intrinsics(setup: _Setup) -> np.ndarray:
    """Which intrinsics the refinement estimates: the focal lengths, the principal point and
    the distortion model's coefficients."""
    n_dist = setup.n_dist
    free = np.ones(4 + n_dist, bool)
    model = DISTORTION_MODELS[setup.opts.dist_coeffs]
    free[4:] = [k in model for k in INTRINSICS[4 : 4 + n_dist]]
    return free


def _observations(usable: list[View], board: BoardSpec) -> _Observations:
    """Every corner of the usable views, in ``(camera, shot)`` order of the views."""
    view_of = {(v.camera, v.shot): v for v in usable}
    keys = sorted(view_of)
    obs = Corners(
        camera=np.concatenate([np.full(len(view_of[k].ids), k[0]) for k in keys]),
        shot=np.concatenate([np.full(len(view_of[k].ids), k[1]) for k in keys]),
        board=np.concatenate([board.corners[view_of[k].ids] for k in keys]),
        pixel=np.concatenate([view_of[k].corners for k in keys]),
    )
    view_index = np.concatenate([np.full(len(view_of[k].ids), i) for i, k in enumerate(keys)])
    return _Observations(obs, view_index, keys)


def _refine_without_outliers(
    state: RigState,
    observations: _Observations,
    opts: CalibrationSettings,
    camera_rms: Sequence[float] | None = None,
) -> tuple[_Fit, dict[tuple[int, int], str]]:
    """4-5. Joint refinement, outliers out, again, until the selection settles (at most 8
    rounds): the last fit, and the views dropped as a whole (``(camera, shot)`` -> why)."""
    obs, keys, view_index = observations.corners, observations.keys, observations.view_index
    keep = np.ones(len(obs.camera), bool)
    dropped_views: dict[tuple[int, int], str] = {}
    moments = (
        Moments(np.array([k[1] for k in keys], np.int64), np.asarray(camera_rms, float))
        if camera_rms is not None
        else None
    )
    for _ in range(8):
        result = refine(state, obs.subset(keep))
        state = result.state
        err = np.linalg.norm(project(state, obs) - obs.pixel, axis=1)
        new_keep, new_dropped = inliers(
            err,
            keep,
            view_index,
            len(keys),
            opts,
            np.array([k[0] for k in keys], np.int64),
            moments,
        )
        if np.array_equal(new_keep, keep):
            break
        if not np.any(new_keep):
            raise UserError("no corner fits a calibration: check the board description")
        keep = new_keep
        dropped_views = {keys[i]: why for i, why in new_dropped.items()}
    else:  # still changing after 8 rounds: settle on the last selection
        result = refine(state, obs.subset(keep))
        state = result.state
    residuals = project(state, obs) - obs.pixel
    return _Fit(state, result, obs, residuals, keep), dropped_views


def _initial_extrinsics(
    poses: Mapping[tuple[int, int], np.ndarray],
    cameras: Sequence[str],
    where: Mapping[str, Path],
) -> np.ndarray:
    """``cam_T_rig`` of every camera from the per-camera board poses (robust means along the
    pairs that share most shots, starting from camera 0)."""
    C = len(cameras)
    shots_of = [{s for (c, s) in poses if c == k} for k in range(C)]
    cam_T_rig = np.tile(np.eye(4), (C, 1, 1))
    placed = {0}
    while len(placed) < C:
        best = max(
            (
                (len(shots_of[a] & shots_of[b]), a, b)
                for a in placed
                for b in range(C)
                if b not in placed
            ),
            default=(0, 0, 0),
        )
        common, a, b = best
        if common == 0:
            lonely = [cameras[k] for k in range(C) if k not in placed]
            raise UserError(
                f"camera(s) {', '.join(lonely)} never saw the board in the same shot as "
                f"{', '.join(cameras[k] for k in sorted(placed))}: take shots with the board "
                "in view of both",
                path=where.get(lonely[0]),
            )
        common_shots = sorted(shots_of[a] & shots_of[b])
        b_T_a = np.stack([poses[(b, s)] @ invert(poses[(a, s)]) for s in common_shots])
        cam_T_rig[b] = robust_mean_transform(b_T_a) @ cam_T_rig[a]
        placed.add(b)
    return cam_T_rig


def robust_mean_transform(Ts: np.ndarray) -> np.ndarray:
    """Robust mean of rigid transforms (n, 4, 4): the rotations within three times the median
    angle (at least 0.5 degree) of their medoid, averaged; the translations' median of the
    same."""
    rots = Rotation.from_matrix(Ts[:, :3, :3])
    n = len(rots)
    angles = np.stack([(rots[i].inv() * rots).magnitude() for i in range(n)])
    medoid = int(np.argmin(angles.sum(axis=1)))
    to_medoid = angles[medoid]
    keep = to_medoid <= max(3.0 * float(np.median(to_medoid)), np.radians(0.5))
    R = rots[keep].mean().as_matrix()
    t = np.median(Ts[keep, :3, 3], axis=0)
    return make_transform(R, t)


def _assemble(
    fit: _Fit, setup: _Setup, initial: _Initial, rejections: list[Rejection]
) -> Calibration:
    """The calibration's figures from the last fit; ``rejections`` gains the shots no view
    of which was used, and is sorted by shot, then camera."""
    cameras, shots = setup.cameras, setup.shots
    used_views = fit.used_views
    reports = [
        dataclasses.replace(
            _camera_report(fit, c, name, setup.sizes[c], initial.rms[c], used_views),
            initial_focal_px=initial.focal(c),
            board_distance_mm=initial.board_distance(c, setup.board),
        )
        for c, name in enumerate(cameras)
    ]
    shot_reports = _shot_reports(fit, cameras, shots, rejections)
    order = {name: k for k, name in enumerate(shots)}
    rejections.sort(
        key=lambda r: (order[r.shot], -1 if r.camera is None else cameras.index(r.camera))
    )
    return Calibration(
        cameras=tuple(reports),
        shots=tuple(shot_reports),
        rejections=tuple(rejections),
        rms_px=float(np.sqrt(np.mean(fit.err2[fit.keep]))),
        iterations=fit.result.iterations,
        converged=fit.result.converged,
        corners=fit.obs,
        residuals=fit.residuals,
        used=fit.keep,
        sizes=tuple((int(w), int(h)) for w, h in setup.sizes),
        warnings=tuple(_few_shots_together(cameras, len(shots), used_views)),
    )


def _camera_report(
    fit: _Fit,
    c: int,
    name: str,
    size: tuple[int, int],
    initial_rms: float,
    used_views: set[tuple[int, int]],
) -> CameraReport:
    """Camera ``c``: its calibrated :class:`Camera`, its RMS, counts and standard deviations."""
    obs, keep, state = fit.obs, fit.keep, fit.state
    sel = keep & (obs.camera == c)
    in_used_views = np.array([(c, int(s)) in used_views for s in obs.shot], bool) & (
        obs.camera == c
    )
    camera = Camera(
        name=name,
        width=int(size[0]),
        height=int(size[1]),
        K=state.K(c),
        dist=state.dist(c),
        rig_T_cam=np.eye(4) if c == 0 else invert(state.cam_T_rig[c]),
    )
    return CameraReport(
        camera=camera,
        rms_px=float(np.sqrt(np.mean(fit.err2[sel]))) if np.any(sel) else float("nan"),
        initial_rms_px=float(initial_rms),
        shots=len({s for (cc, s) in used_views if cc == c}),
        corners=int(sel.sum()),
        outlier_corners=int((in_used_views & ~keep).sum()),
        std=_camera_std(fit, c),
    )


def _camera_std(fit: _Fit, c: int) -> dict[str, float]:
    """One standard deviation of camera ``c``'s free intrinsics, orientation (degrees) and
    position in the rig (mm; both 0 for camera 0, the rig frame)."""
    state = fit.state
    free_names = [n for n, f in zip(INTRINSICS, state.free_intrinsics) if f]
    cov = fit.result.camera_covariance[c]
    std = {n: float(np.sqrt(max(cov[i, i], 0.0))) for i, n in enumerate(free_names)}
    if c == 0:
        std["rotation_deg"] = 0.0
        std["position_mm"] = 0.0
        return std
    R = state.cam_T_rig[c, :3, :3]
    t = state.cam_T_rig[c, :3, 3]
    k = len(free_names)
    cw = cov[k:, k:]
    # The covariance is of cam_T_rig's left perturbation; the position is rig_T_cam's.
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Jc = -R.T @ np.hstack([tx, np.eye(3)])
    std["rotation_deg"] = float(np.degrees(np.sqrt(max(np.trace(cw[:3, :3]), 0.0))))
    std["position_mm"] = float(np.sqrt(max(np.trace(Jc @ cw @ Jc.T), 0.0)))
    return std


def _shot_reports(
    fit: _Fit, cameras: Sequence[str], shots: Sequence[str], rejections: list[Rejection]
) -> list[ShotReport]:
    """Every shot's board pose and per-camera fit; a shot with no view used is rejected
    (unless it already is)."""
    obs, keep, err2 = fit.obs, fit.keep, fit.err2
    out = []
    for s, name in enumerate(shots):
        rms, count = {}, {}
        for c, cam in enumerate(cameras):
            sel = keep & (obs.camera == c) & (obs.shot == s)
            if np.any(sel):
                rms[cam] = float(np.sqrt(np.mean(err2[sel])))
                count[cam] = int(sel.sum())
        pose = fit.state.rig_T_board[s].copy() if rms else None
        out.append(ShotReport(name, pose, rms, count))
        if not rms and not any(r.shot == name for r in rejections):
            rejections.append(Rejection(name, None, "no usable view"))
    return out


def _few_shots_together(
    cameras: Sequence[str], n_shots: int, used_views: set[tuple[int, int]]
) -> list[str]:
    """A warning for each camera that saw the board with another one in under 3 shots."""
    warnings = []
    for c, name in enumerate(cameras):
        together = sum(
            1
            for s in range(n_shots)
            if (c, s) in used_views
            and any((o, s) in used_views for o in range(len(cameras)) if o != c)
        )
        if len(cameras) > 1 and together < 3:
            warnings.append(
                f"camera {name} saw the board together with another camera in only {together} "
                "shot(s): its pose in the rig rests on very few shots"
            )
    return warnings
