"""OpenCV's own two-camera calibration pipelines, kept as the reference that the joint
refinement (:mod:`annotator.calibration.rig`) is measured against (tests, benchmark).

- **Two-step:** ``calibrateCamera`` per camera, then ``stereoCalibrate`` with the intrinsics
  fixed (``CALIB_FIX_INTRINSIC``): the extrinsics absorb the intrinsics' errors.
- **Joint:** ``stereoCalibrate`` initialised from the per-camera results with every
  intrinsic free (``CALIB_USE_INTRINSIC_GUESS``): one Levenberg-Marquardt over both cameras'
  intrinsics, the relative pose and the board poses, but only on the shots both cameras saw
  and only on the corners both found in them.

:func:`opencv_rig` is the two-step pipeline for a rig of any number of cameras, each paired
with the first. Both stereo pipelines use every view with at least ``min_corners`` corners, OpenCV's default distortion model
(k1, k2, p1, p2, k3) and up to 100 iterations.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from annotator.calibration.board import BoardSpec
from annotator.calibration.pairwise import shared_corners
from annotator.calibration.records import View
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import invert, make_transform

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass(frozen=True)
class StereoResult:
    """Intrinsics of both cameras and ``rig_T_cam`` of the second (camera 0 = rig frame)."""

    K: tuple[np.ndarray, np.ndarray]
    dist: tuple[np.ndarray, np.ndarray]
    rig_T_cam1: np.ndarray
    rms_px: float


def _calibrate_alone(
    board: BoardSpec, views: Sequence[View], size: tuple[int, int], flags: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """One camera's ``calibrateCamera`` on its views: K and the first five distortion terms."""
    _, K, dist, _, _ = cv2.calibrateCamera(
        [board.corners[v.ids].astype(np.float32).reshape(-1, 1, 3) for v in views],
        [v.corners.astype(np.float32).reshape(-1, 1, 2) for v in views],
        tuple(size),
        None,
        None,
        flags=flags,
        criteria=_CRITERIA,
    )
    return np.asarray(K, float), np.asarray(dist, float).reshape(-1)[:5]


def opencv_stereo(
    views: Sequence[View],
    board: BoardSpec,
    sizes: Sequence[tuple[int, int]],
    *,
    joint: bool,
    min_corners: int = 8,
) -> StereoResult:
    """OpenCV's two-step (``joint=False``) or joint (``joint=True``) stereo calibration of
    cameras 0 and 1 from the same detections the rig calibration uses."""
    good = [v for v in views if len(v.ids) >= min_corners and v.camera in (0, 1)]
    alone = [_calibrate_alone(board, [v for v in good if v.camera == c], sizes[c]) for c in (0, 1)]
    Ks, dists = [K for K, _ in alone], [d for _, d in alone]
    obj, img0, img1 = shared_corners(good, board, min_corners=min_corners)
    flags = cv2.CALIB_USE_INTRINSIC_GUESS if joint else cv2.CALIB_FIX_INTRINSIC
    rms, K0, d0, K1, d1, R, T, _, _ = cv2.stereoCalibrate(
        obj,
        img0,
        img1,
        Ks[0].copy(),
        dists[0].copy(),
        Ks[1].copy(),
        dists[1].copy(),
        tuple(sizes[0]),
        flags=flags,
        criteria=_CRITERIA,
    )
    cam1_T_cam0 = make_transform(R, np.ravel(T))
    return StereoResult(
        K=(np.asarray(K0, float), np.asarray(K1, float)),
        dist=(np.asarray(d0, float).reshape(-1)[:5], np.asarray(d1, float).reshape(-1)[:5]),
        rig_T_cam1=invert(cam1_T_cam0),
        rms_px=float(rms),
    )


def opencv_rig(
    views: Sequence[View],
    board: BoardSpec,
    sizes: Sequence[tuple[int, int]],
    names: Sequence[str],
    *,
    min_corners: int = 8,
) -> list[Camera]:
    """OpenCV's pairwise pipeline for a rig of any size: ``calibrateCamera`` per camera
    (k1 k2 p1 p2, as the rig calibration chooses on these captures), then ``stereoCalibrate``
    with the intrinsics fixed of every camera against camera 0 over the shots both saw (the
    corners both found). ``views`` must already be read right (a mirrored camera's corners
    flipped: :func:`annotator.calibration.readings.decide_readings`)."""
    good = [v for v in views if len(v.ids) >= min_corners and not v.rejected]
    alone = [
        _calibrate_alone(board, [v for v in good if v.camera == c], sizes[c], cv2.CALIB_FIX_K3)
        for c in range(len(names))
    ]
    Ks, dists = [K for K, _ in alone], [d for _, d in alone]
    by_shot: dict[int, dict[int, View]] = {}
    for v in good:
        by_shot.setdefault(v.shot, {})[v.camera] = v
    cameras = [Camera(names[0], *sizes[0], Ks[0], dists[0])]
    for c in range(1, len(names)):
        obj, img0, img1 = [], [], []
        for pair in by_shot.values():
            if 0 not in pair or c not in pair:
                continue
            common, i0, i1 = np.intersect1d(pair[0].ids, pair[c].ids, return_indices=True)
            if len(common) < min_corners:
                continue
            obj.append(board.corners[common].astype(np.float32).reshape(-1, 1, 3))
            img0.append(pair[0].corners[i0].astype(np.float32).reshape(-1, 1, 2))
            img1.append(pair[c].corners[i1].astype(np.float32).reshape(-1, 1, 2))
        _, _, _, _, _, R, T, _, _ = cv2.stereoCalibrate(
            obj,
            img0,
            img1,
            Ks[0].copy(),
            dists[0].copy(),
            Ks[c].copy(),
            dists[c].copy(),
            tuple(sizes[0]),
            flags=cv2.CALIB_FIX_INTRINSIC,
            criteria=_CRITERIA,
        )
        rig_T_cam = invert(make_transform(R, np.ravel(T)))
        cameras.append(Camera(names[c], *sizes[c], Ks[c], dists[c], rig_T_cam))
    return cameras
