"""The records of a rig calibration: the views it starts from, its settings, and what it
finds (each camera's and shot's figures, the views left out and why)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from annotator.calibration.bundle import Corners
from annotator.errors import UserError
from annotator.geometry.camera import Camera

#: The distortion models offered: number of coefficients -> coefficients estimated (8:
#: OpenCV's rational model).
DISTORTION_MODELS = {
    2: ("k1", "k2"),
    4: ("k1", "k2", "p1", "p2"),
    5: ("k1", "k2", "p1", "p2", "k3"),
    8: ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}


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
class CalibrationSettings:
    """Settings of :func:`solve_rig`.

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
    """The result of :func:`solve_rig`.

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
        pair_held_out: The held-out error of every camera pair calibrated alone by OpenCV's
            stereo pipeline on the same folds (:mod:`.pairwise`), when measured.
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
    pair_held_out: Any = None
    problems: tuple[Any, ...] = ()

    @property
    def rig_cameras(self) -> tuple[Camera, ...]:
        """The calibrated cameras, the first being the rig frame."""
        return tuple(c.camera for c in self.cameras)
