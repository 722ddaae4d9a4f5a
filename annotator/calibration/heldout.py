"""How well a calibration predicts shots it did not fit: the held-out error.

The RMS of a calibration is measured on the corners it was fitted to, so it cannot see a
model that bends where no corner was, or a rig pose that fits its own shots only. Here the
shots are split into ``k`` folds (every ``k``-th usable shot in each); for each fold the rig
is calibrated on the other shots, and every left-out shot is predicted across cameras: the
board pose from camera ``a`` alone (PnP with ``a``'s calibrated intrinsics), its corners
projected through the rig into camera ``b`` and compared with where ``b`` detected them. The
error (px, RMS over corners) per ordered pair ``a -> b`` is what a user of the rig gets when
one camera's observation is used to predict another's, which is what multi-view annotation
does. A rig of one camera is measured against itself (``a -> a``: new shots, the pose fitted
to them, the intrinsics not).

The fitting is a function given by the caller (:data:`Fit`): the rig calibration itself, or
OpenCV's pipeline (benchmarks), so that both are measured on the same folds.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from annotator.calibration.board import BoardSpec
from annotator.calibration.records import View
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import make_transform

#: Default number of folds.
FOLDS = 5

#: Fits cameras (rig order; K, dist, rig_T_cam) to the views of some shots.
Fit = Callable[[Sequence[View]], Sequence[Camera]]


@dataclass(frozen=True)
class PairError:
    """Held-out prediction error from camera ``source`` into camera ``target``."""

    source: str
    target: str
    rms_px: float
    median_px: float
    corners: int
    shots: int


@dataclass(frozen=True)
class HeldOut:
    """The held-out error of a calibration (see the module docstring).

    Attributes:
        folds: Folds used.
        pairs: One entry per ordered camera pair with predictions.
        rms_px: RMS over every predicted corner of every pair.
        corners: Corners predicted in all.
        median_px: Median over every predicted corner of every pair (the transfer error the
            summary states).
        errors: ``(source, target) -> `` the error (px) of each corner predicted.
    """

    folds: int
    pairs: tuple[PairError, ...]
    rms_px: float
    corners: int
    median_px: float = float("nan")
    errors: Mapping[tuple[str, str], np.ndarray] = field(default_factory=dict)

    def pooled_median(self, pairs: Iterable[tuple[str, str]]) -> float:
        """The median error over every corner predicted along ``pairs`` (NaN: none)."""
        found = [self.errors[p] for p in pairs if p in self.errors]
        every = np.concatenate(found) if found else np.zeros(0)
        return float(np.median(every)) if len(every) else float("nan")

    def to_dict(self) -> dict:
        """For report.json."""
        return {
            "folds": self.folds,
            "rms_px": round(self.rms_px, 4),
            "median_px": None if not np.isfinite(self.median_px) else round(self.median_px, 4),
            "corners": self.corners,
            "pairs": [
                {
                    "from": p.source,
                    "to": p.target,
                    "rms_px": round(p.rms_px, 4),
                    "median_px": round(p.median_px, 4),
                    "corners": p.corners,
                    "shots": p.shots,
                }
                for p in self.pairs
            ],
        }


def fold_of_shots(shots: Iterable[int], folds: int) -> dict[int, int]:
    """Shot index -> fold, dealt round-robin in shot order (so that every fold spans the
    whole capture session, not one stretch of it)."""
    return {s: k % folds for k, s in enumerate(sorted(shots))}


def held_out_error(
    views: Sequence[View],
    fit: Fit,
    board: BoardSpec,
    cameras: Sequence[str],
    *,
    folds: int = FOLDS,
    min_corners: int = 8,
    fold_shots: Iterable[int] | None = None,
) -> HeldOut:
    """The held-out error of ``fit`` on ``views`` (see the module docstring); a fold whose
    fit raises is passed over (too few shots left for some camera). ``fold_shots``: the shots
    dealt into folds (default: those of the usable views), so that two measures on
    different views of one capture hold out the same shots."""
    usable = [v for v in views if len(v.ids) >= min_corners]
    every_shot = {v.shot for v in usable} if fold_shots is None else set(fold_shots)
    fold = fold_of_shots(every_shot | {v.shot for v in usable}, folds)
    errors: dict[tuple[int, int], list[np.ndarray]] = {}
    shots: dict[tuple[int, int], set[int]] = {}
    for k in range(folds):
        train = [v for v in usable if fold[v.shot] != k]
        test = [v for v in usable if fold[v.shot] == k]
        if not test:
            continue
        try:
            rig = list(fit(train))
        except (UserError, cv2.error):  # too few shots left for some camera: no prediction
            continue
        for (a, b), err, s in _predict(test, rig, board, single=len(cameras) == 1):
            errors.setdefault((a, b), []).append(err)
            shots.setdefault((a, b), set()).add(s)
    pairs = []
    every = []
    for a, b in sorted(errors):
        e = np.concatenate(errors[(a, b)])
        every.append(e)
        pairs.append(
            PairError(
                cameras[a],
                cameras[b],
                float(np.sqrt(np.mean(e**2))),
                float(np.median(e)),
                len(e),
                len(shots[(a, b)]),
            )
        )
    allerr = np.concatenate(every) if every else np.zeros(0)
    return HeldOut(
        folds,
        tuple(pairs),
        float(np.sqrt(np.mean(allerr**2))) if len(allerr) else float("nan"),
        len(allerr),
        float(np.median(allerr)) if len(allerr) else float("nan"),
        {(cameras[a], cameras[b]): np.concatenate(e) for (a, b), e in errors.items()},
    )


def _predict(
    test: Sequence[View], rig: Sequence[Camera], board: BoardSpec, *, single: bool
) -> list[tuple[tuple[int, int], np.ndarray, int]]:
    """Per left-out shot and ordered camera pair: the error norms (px) of the predicted
    corners."""
    out = []
    by_shot: dict[int, list[View]] = {}
    for v in test:
        by_shot.setdefault(v.shot, []).append(v)
    for s, vs in by_shot.items():
        for va in vs:
            cam_a = rig[va.camera]
            a_T_board = board_pose(cam_a, board.corners[va.ids], va.corners)
            if a_T_board is None:
                continue
            rig_T_board = cam_a.rig_T_cam @ a_T_board
            for vb in vs:
                if (vb.camera == va.camera) != single:
                    continue
                cam_b = rig[vb.camera]
                X = board.corners[vb.ids] @ rig_T_board[:3, :3].T + rig_T_board[:3, 3]
                uv = cam_b.project_from_rig(X)
                err = np.linalg.norm(uv - vb.corners, axis=1)
                out.append(((va.camera, vb.camera), err[np.isfinite(err)], s))
    return out


def board_pose(cam: Camera, board_pts: np.ndarray, pixels: np.ndarray) -> np.ndarray | None:
    """``cam_T_board`` from one camera's corners (planar PnP, then iterative refinement), or
    None if OpenCV finds none."""
    obj = np.ascontiguousarray(board_pts, np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(pixels, np.float64).reshape(-1, 1, 2)
    ok, rvec, tvec = cv2.solvePnP(obj, img, cam.K, cam.dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return None
    ok, rvec, tvec = cv2.solvePnP(
        obj, img, cam.K, cam.dist, rvec, tvec, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE
    )
    if not ok:
        return None
    return make_transform(cv2.Rodrigues(rvec)[0], np.ravel(tvec))
