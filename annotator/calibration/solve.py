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
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
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
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import invert, make_transform

#: The distortion models offered: number of coefficients -> coefficients estimated (8:
#: OpenCV's rational model).
DISTORTION_MODELS = {
    2: ("k1", "k2"),
    4: ("k1", "k2", "p1", "p2"),
    5: ("k1", "k2", "p1", "p2", "k3"),
    8: ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}


#: A view whose RMS in the joint fit is over this many times its camera's RMS alone ...
MOMENT_FACTOR = 2.0
#: ... and this many pixels more is of another moment than its shot (:class:`_Moments`).
MOMENT_MARGIN_PX = 0.25


@dataclass(frozen=True)
class View:
    """The board as detected by one camera in one shot.

    Attributes:
        camera: Index of the camera.
        shot: Index of the shot.
        ids: (n,) chessboard corner ids.
        corners: (n, 2) their pixel positions.
        markers: Markers of the board identified (0: the board was not found at all).
        flipped: The board read only in the image flipped left to right (a mirrored camera,
            or the board seen from behind: :mod:`.readings` decides which).
        rejected: Why the view is left out before the calibration starts (empty: it is not).
    """

    camera: int
    shot: int
    ids: np.ndarray
    corners: np.ndarray
    markers: int = 0
    flipped: bool = False
    rejected: str = ""


@dataclass(frozen=True)
class CalibrationOptions:
    """Settings of :func:`calibrate_rig`.

    Attributes:
        min_shots: Usable shots each camera needs.
        min_corners: Corners a view needs to be used.
        dist_coeffs: Distortion model: 2 (k1 k2), 4 (+ p1 p2), 5 (+ k3, OpenCV's default) or
            8 (+ k4 k5 k6, OpenCV's rational model).
        outlier_sigmas: A corner is an outlier beyond this many robust standard deviations.
        min_outlier_px: ... and never below this residual (px).
    """

    min_shots: int = 6
    min_corners: int = 8
    dist_coeffs: int = 5
    outlier_sigmas: float = 5.0
    min_outlier_px: float = 0.5

    def __post_init__(self) -> None:
        if self.dist_coeffs not in DISTORTION_MODELS:
            raise UserError(
                f"the distortion model must have 2, 4, 5 or 8 coefficients, not {self.dist_coeffs}"
            )
        if self.min_shots < 3:
            raise UserError(f"at least 3 shots are needed per camera, not {self.min_shots}")
        if self.min_corners < 6:
            raise UserError(f"a view needs at least 6 corners, not {self.min_corners}")


@dataclass(frozen=True)
class Rejection:
    """A shot, or one camera's view of it, left out of the calibration, and why."""

    shot: str
    camera: str | None
    reason: str

    def __str__(self) -> str:
        who = f"shot {self.shot}" + (f", camera {self.camera}" if self.camera else "")
        return f"{who}: {self.reason}"


@dataclass(frozen=True)
class CameraReport:
    """How well one camera is calibrated.

    Attributes:
        camera: The calibrated camera (K, dist, rig_T_cam).
        rms_px: RMS reprojection error of its corners after the joint refinement.
        initial_rms_px: RMS of OpenCV's ``calibrateCamera`` for this camera alone.
        shots: Shots whose view of this camera was used.
        corners: Corners used.
        outlier_corners: Corners left out as outliers (in views that were used).
        std: One standard deviation of each estimated intrinsic (``fx`` ... ``k3``), of the
            camera's orientation (``rotation_deg``) and of its position in the rig
            (``position_mm``), from the refinement's covariance.
        initial_focal_px: Focal lengths ``(fx, fy)`` of OpenCV's ``calibrateCamera`` for this
            camera alone.
        board_distance_mm: The farthest the board's centre was from this camera, by
            ``calibrateCamera`` for this camera alone.
    """

    camera: Camera
    rms_px: float
    initial_rms_px: float
    shots: int
    corners: int
    outlier_corners: int
    std: dict[str, float]
    initial_focal_px: tuple[float, float] = (float("nan"), float("nan"))
    board_distance_mm: float = float("nan")


@dataclass(frozen=True)
class ShotReport:
    """One shot: its board pose and each camera's fit (cameras whose view was used)."""

    name: str
    rig_T_board: np.ndarray | None
    rms_px: dict[str, float]
    corners: dict[str, int]

    @property
    def used(self) -> bool:
        return self.rig_T_board is not None


@dataclass(frozen=True)
class Calibration:
    """The result of :func:`calibrate_rig`.

    Attributes:
        cameras: Per camera, the calibrated :class:`Camera` and its figures (rig order).
        shots: Per shot, in input order.
        rejections: Shots and views left out, and why.
        rms_px: RMS reprojection error over every corner used.
        iterations: Levenberg-Marquardt iterations of the last refinement.
        converged: Whether that refinement converged (rather than stopping at its limit).
        corners: Every corner of the usable views (including the outliers).
        residuals: (N, 2) projected minus detected position of each of ``corners``.
        used: (N,) bool, which of ``corners`` the refinement used.
        sizes: Image size (width, height) per camera.
        warnings: Things worth knowing that did not stop the calibration.
        held_out: The held-out error (:mod:`.heldout`), when measured.
        model_choice: How the distortion model was chosen (:mod:`.model_choice`), if it was.
        extrapolation: Per camera, where its distortion is extrapolated (:mod:`.extrapolation`).
        readings: Per camera, mirrored or not and where it saw the board from behind
            (:mod:`.readings`), when decided.
        camera_held_out: Per camera, the held-out error of that camera alone (:mod:`.checks`).
        problems: Why the rig does not hold together (:mod:`.checks`); empty: it does.
    """

    cameras: tuple[CameraReport, ...]
    shots: tuple[ShotReport, ...]
    rejections: tuple[Rejection, ...]
    rms_px: float
    iterations: int
    corners: Corners
    residuals: np.ndarray
    used: np.ndarray
    sizes: tuple[tuple[int, int], ...]
    warnings: tuple[str, ...] = field(default=())
    held_out: Any = None
    model_choice: Any = None
    extrapolation: tuple[Any, ...] = ()
    converged: bool = True
    readings: Any = None
    camera_held_out: tuple[float, ...] = ()
    problems: tuple[Any, ...] = ()

    @property
    def rig_cameras(self) -> tuple[Camera, ...]:
        """The calibrated cameras, the first being the rig frame."""
        return tuple(c.camera for c in self.cameras)


@dataclass(frozen=True)
class _Setup:
    """What :func:`calibrate_rig` was given, passed along its steps."""

    views: Sequence[View]
    cameras: Sequence[str]
    sizes: Sequence[tuple[int, int]]
    shots: Sequence[str]
    board: BoardSpec
    opts: CalibrationOptions
    where: Mapping[str, Path]

    @property
    def n_dist(self) -> int:
        """Distortion coefficients kept per camera: OpenCV's five, or eight (rational)."""
        return 8 if self.opts.dist_coeffs == 8 else 5

    def require_shots(self, usable: Sequence[View]) -> None:
        """Every camera still has enough usable shots (else a UserError naming it)."""
        for c, name in enumerate(self.cameras):
            _require_shots(usable, c, name, self.views, self.opts, self.where)


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


def calibrate_rig(
    views: Sequence[View],
    *,
    cameras: Sequence[str],
    sizes: Sequence[tuple[int, int]],
    shots: Sequence[str],
    board: BoardSpec,
    options: CalibrationOptions | None = None,
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
        views, cameras, sizes, shots, board, options or CalibrationOptions(), where or {}
    )
    rejections: list[Rejection] = []
    usable = _screen(views, cameras, shots, board, setup.opts, rejections)
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
    flags = _flags(setup.opts.dist_coeffs)
    intrinsics = np.zeros((len(setup.cameras), 4 + setup.n_dist))
    poses: dict[tuple[int, int], np.ndarray] = {}
    initial_rms = []
    for c, name in enumerate(setup.cameras):
        K, dist, cam_poses, rms = _calibrate_camera(
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
        _require_shots(usable, c, name, setup.views, setup.opts, setup.where)
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
    opts: CalibrationOptions,
    camera_rms: Sequence[float] | None = None,
) -> tuple[_Fit, dict[tuple[int, int], str]]:
    """4-5. Joint refinement, outliers out, again, until the selection settles (at most 8
    rounds): the last fit, and the views dropped as a whole (``(camera, shot)`` -> why)."""
    obs, keys, view_index = observations.corners, observations.keys, observations.view_index
    keep = np.ones(len(obs.camera), bool)
    dropped_views: dict[tuple[int, int], str] = {}
    moments = (
        _Moments(np.array([k[1] for k in keys], np.int64), np.asarray(camera_rms, float))
        if camera_rms is not None
        else None
    )
    for _ in range(8):
        result = refine(state, obs.subset(keep))
        state = result.state
        err = np.linalg.norm(project(state, obs) - obs.pixel, axis=1)
        new_keep, new_dropped = _inliers(
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


def _flags(dist_coeffs: int) -> int:
    flags = cv2.CALIB_RATIONAL_MODEL if dist_coeffs == 8 else 0
    if dist_coeffs < 5:
        flags |= cv2.CALIB_FIX_K3
    if dist_coeffs < 4:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    return flags


def _screen(
    views: Sequence[View],
    cameras: Sequence[str],
    shots: Sequence[str],
    board: BoardSpec,
    opts: CalibrationOptions,
    rejections: list[Rejection],
) -> list[View]:
    """The usable views; the others are recorded as rejections (whole shots when no camera
    could use the shot)."""
    usable: list[View] = []
    reasons: dict[int, list[tuple[str, str]]] = {}
    for v in sorted(views, key=lambda v: (v.shot, v.camera)):
        n = len(v.ids)
        if v.rejected:
            why = v.rejected
        elif n == 0:
            why = (
                "board not found"
                if v.markers == 0
                else f"board not found ({v.markers} of its markers, but no corner between two of them)"
            )
        elif n < opts.min_corners:
            why = (
                f"only {n} corner{'s' if n > 1 else ''} found (at least {opts.min_corners} needed)"
            )
        elif _collinear(board.corners[v.ids]):
            why = f"the {n} corners found lie on one line"
        else:
            usable.append(v)
            continue
        reasons.setdefault(v.shot, []).append((cameras[v.camera], why))
    seen = {v.shot for v in usable}
    for s in sorted(reasons):
        items = reasons[s]
        if s not in seen and len(items) == len(cameras) and len({w for _, w in items}) == 1:
            rejections.append(Rejection(shots[s], None, f"{items[0][1]} in any camera"))
        else:
            rejections.extend(Rejection(shots[s], cam, why) for cam, why in items)
    return usable


def _collinear(points: np.ndarray) -> bool:
    """True if the board points (n, 3) lie on a line (within a tenth of their extent)."""
    centred = points[:, :2] - points[:, :2].mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    return bool(s[1] <= 0.1 * s[0])


def _require_shots(
    usable: Sequence[View],
    c: int,
    name: str,
    views: Sequence[View],
    opts: CalibrationOptions,
    where: Mapping[str, Path],
) -> None:
    n = sum(1 for v in usable if v.camera == c)
    if n >= opts.min_shots:
        return
    total = sum(1 for v in views if v.camera == c)
    found = sum(1 for v in views if v.camera == c and len(v.ids) > 0)
    if found == 0:
        msg = f"the board was not found in any of the {total} images of camera {name}"
    else:
        msg = (
            f"too few shots: camera {name} has {n} usable of {total} (the board was found in "
            f"{found}), and calibration needs at least {opts.min_shots}"
        )
    raise UserError(msg, path=where.get(name))


def _calibrate_camera(
    views: list[View],
    board: BoardSpec,
    size: tuple[int, int],
    flags: int,
    rejections: list[Rejection],
    name: str,
    shots: Sequence[str],
    n_dist: int = 5,
) -> tuple[np.ndarray, np.ndarray, dict[tuple[int, int], np.ndarray], float]:
    """OpenCV's calibrateCamera on one camera's views; views it cannot fit are rejected.

    Returns K, dist (``n_dist``: 5, or 8 for the rational model), ``{(camera, shot):
    cam_T_board}`` and the RMS (px)."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    while True:
        obj = [board.corners[v.ids].astype(np.float32).reshape(-1, 1, 3) for v in views]
        img = [v.corners.astype(np.float32).reshape(-1, 1, 2) for v in views]
        try:
            with _one_opencv_thread():
                rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
                    obj, img, tuple(size), None, None, flags=flags, criteria=criteria
                )
        except cv2.error as exc:
            first = str(exc).strip().splitlines()[-1] if str(exc).strip() else "cv2.error"
            raise UserError(
                f"OpenCV could not calibrate camera {name} from its {len(views)} views ({first})"
            ) from None
        dist = np.asarray(dist, float).reshape(-1)[:n_dist]
        dist = np.pad(dist, (0, n_dist - len(dist)))
        view_rms = []
        for v, rv, tv in zip(views, rvecs, tvecs):
            uv, _ = cv2.projectPoints(board.corners[v.ids], rv, tv, K, dist)
            view_rms.append(np.sqrt(np.mean(np.sum((uv.reshape(-1, 2) - v.corners) ** 2, 1))))
        per_view = np.asarray(view_rms)
        limit = max(5.0 * float(np.median(per_view)), 2.0)
        bad = per_view > limit
        if not np.any(bad) or bad.sum() > len(views) // 2:
            break
        for v, e in zip(views, per_view):
            if e > limit:
                rejections.append(
                    Rejection(
                        shots[v.shot],
                        name,
                        f"calibrateCamera cannot fit it (RMS {e:.2f} px, limit {limit:.2f} px)",
                    )
                )
        views = [v for v, b in zip(views, bad) if not b]
    poses = {
        (v.camera, v.shot): make_transform(cv2.Rodrigues(rv)[0], np.ravel(tv))
        for v, rv, tv in zip(views, rvecs, tvecs)
    }
    return np.asarray(K, float), dist, poses, float(rms)


@contextmanager
def _one_opencv_thread() -> Iterator[None]:
    """OpenCV on one thread meanwhile: with several, ``calibrateCamera`` sums in a varying
    order and its results differ from run to run in the ninth digit, enough to change the
    written dataset.yaml when nothing else changed."""
    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


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


def _inliers(
    err: np.ndarray,
    keep: np.ndarray,
    view_index: np.ndarray,
    n_views: int,
    opts: CalibrationOptions,
    view_camera: np.ndarray | None = None,
    moments: _Moments | None = None,
) -> tuple[np.ndarray, dict[int, str]]:
    """Corners to keep after a refinement with residual norms ``err``, and the views dropped
    as a whole (index -> reason). Each camera is judged by its own noise (``view_camera``:
    the camera of each view), never below the rig's nor above three times it: a camera
    whose corners are noisier (a board seen through the paper) keeps its good corners, and
    one that runs off is not excused."""
    if view_camera is None:
        view_camera = np.zeros(n_views, np.int64)
    corner_camera = view_camera[view_index]
    # The norm of a 2D Gaussian residual has median 1.1774 sigma.
    rig_sigma = float(np.median(err[keep])) / 1.1774
    sigma = np.full(int(view_camera.max(initial=0)) + 1, rig_sigma)
    for c in np.unique(corner_camera[keep]).tolist():
        own = float(np.median(err[keep & (corner_camera == c)])) / 1.1774
        sigma[c] = min(max(own, rig_sigma), 3.0 * rig_sigma)
    limits = np.maximum(opts.outlier_sigmas * sigma, opts.min_outlier_px)
    ok = err <= limits[corner_camera]
    counts = np.bincount(view_index, minlength=n_views)
    good = np.bincount(view_index, weights=ok, minlength=n_views)
    sq = np.bincount(view_index, weights=np.where(ok, err**2, 0.0), minlength=n_views)
    rms = np.sqrt(sq / np.maximum(good, 1))
    present = counts > 0
    view_limits = {}
    for c in np.unique(view_camera[present]).tolist():
        mine = present & (good > 0) & (view_camera == c)
        median_rms = float(np.median(rms[mine])) if np.any(mine) else 0.0
        view_limits[c] = max(3.0 * median_rms, 1.0)
    dropped: dict[int, str] = {}
    for i in np.flatnonzero(present).tolist():
        lost = counts[i] - good[i]
        limit = float(limits[view_camera[i]])
        view_limit = view_limits[int(view_camera[i])]
        if good[i] < opts.min_corners or lost > 0.25 * counts[i]:
            dropped[i] = (
                f"outlier residuals: {int(lost)} of its {counts[i]} corners off by more than "
                f"{limit:.2f} px"
            )
            if lost == counts[i]:
                dropped[i] += " (an image of another moment, or the board moved during the shot?)"
        elif rms[i] > view_limit:
            dropped[i] = (
                f"outlier residuals: RMS {rms[i]:.2f} px, over {view_limit:.2f} px "
                "(three times the median view's of its camera)"
            )
    if moments is not None:
        was_kept = np.bincount(view_index, weights=keep, minlength=n_views) > 0
        fitted = present & (good > 0)
        dropped.update(
            moments.other_moments(rms, fitted, was_kept, dropped, view_camera, opts.min_shots)
        )
    ok &= ~np.isin(view_index, list(dropped))
    return ok, dropped


@dataclass(frozen=True)
class _Moments:
    """Views of a shot taken at another moment than the rest of the shot's (webcams that are
    not synchronised, a board held by hand): such a view fits its own camera as well as any,
    and the rig only with the board moved. A view whose RMS in the joint fit exceeds
    ``MOMENT_FACTOR`` times its camera's RMS alone (``calibrateCamera``: its own corner
    noise), and ``MOMENT_MARGIN_PX`` more, disagrees with its shot; of a shot's views that
    do, only the one furthest over its limit is left out in a round (it pulls the shot's
    board pose towards itself, and so the others' residuals up), and one left out stays out
    while it still disagrees; never so many that a camera keeps fewer than ``min_shots``
    views (a rig whose views disagree that much is one the checks refuse, naming why).

    Attributes:
        view_shot: The shot of each view.
        camera_rms: Each camera's RMS alone, px.
    """

    view_shot: np.ndarray
    camera_rms: np.ndarray

    def other_moments(
        self,
        rms: np.ndarray,
        fitted: np.ndarray,
        was_kept: np.ndarray,
        dropped: Mapping[int, str],
        view_camera: np.ndarray,
        min_shots: int,
    ) -> dict[int, str]:
        """Index -> why of the views left out as of another moment (see the class), among
        the ``fitted`` views not already ``dropped`` (``was_kept``: the views the last fit
        used)."""
        own = self.camera_rms[view_camera]
        limit = np.maximum(MOMENT_FACTOR * own, own + MOMENT_MARGIN_PX)
        over = rms / limit
        candidates = fitted & (over > 1.0)
        candidates[list(dropped)] = False
        # Left out before and still off: out again. Of the views the fit used, the worst of
        # each shot, unless it is the shot's last view (nothing to disagree with).
        chosen = set(np.flatnonzero(candidates & ~was_kept).tolist())
        used = fitted & was_kept
        used[list(dropped)] = False
        views_in_shot = np.bincount(self.view_shot[used], minlength=int(self.view_shot.max()) + 1)
        for s in np.unique(self.view_shot[candidates & was_kept]).tolist():
            mine = np.flatnonzero(candidates & was_kept & (self.view_shot == s))
            if views_in_shot[s] >= 2:
                chosen.add(int(mine[np.argmax(over[mine])]))
        left = np.bincount(view_camera[used], minlength=len(self.camera_rms))
        out: dict[int, str] = {}
        for i in sorted(chosen, key=lambda i: (-over[i], i)):
            if was_kept[i]:
                if left[view_camera[i]] <= min_shots:
                    continue
                left[view_camera[i]] -= 1
            out[i] = (
                f"disagrees with the shot's other views: RMS {rms[i]:.2f} px in the rig, "
                f"against {own[i]:.2f} px for its camera alone (limit {limit[i]:.2f} px): an "
                "image of another moment (the board moved between the cameras' images)?"
            )
        return out


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
