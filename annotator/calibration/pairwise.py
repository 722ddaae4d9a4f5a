"""What a simple per-pair stereo calibration reaches: the bar a rig's held-out transfer error
is held to before it is written (:mod:`.checks`).

For every pair of cameras, alone: OpenCV's ``calibrateCamera`` on each camera's views, then
``stereoCalibrate`` with those intrinsics fixed on the shots both saw (the corners both
found), measured the same way as the rig (:mod:`.heldout`: the same folds of the same views,
one camera's board pose predicting the other's corners). A pair solved alone uses only what
those two cameras saw together, so it never gains from the rest of the rig, but nor can the
rest of the rig pull it off: a rig whose pair predicts worse than the pair alone does not
hold together.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import cv2
import numpy as np

from annotator.calibration.board import BoardSpec
from annotator.calibration.heldout import HeldOut, PairError, held_out_error
from annotator.calibration.records import View
from annotator.calibration.single import one_opencv_thread, opencv_flags
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import invert, make_transform

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
#: Shots a pair must share to be calibrated alone.
MIN_COMMON_SHOTS = 3


def shared_corners(
    views: Sequence[View], board: BoardSpec, *, min_corners: int = 8
) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Per shot that cameras 0 and 1 both saw, the board corners both found (at least
    ``min_corners``): their board points and each camera's pixels, as OpenCV's
    ``stereoCalibrate`` takes them (float32, (N, 1, 3) and (N, 1, 2))."""
    by_shot: dict[int, dict[int, View]] = {}
    for v in views:
        by_shot.setdefault(v.shot, {})[v.camera] = v
    obj, img0, img1 = [], [], []
    for pair in by_shot.values():
        if 0 not in pair or 1 not in pair:
            continue
        common, i0, i1 = np.intersect1d(pair[0].ids, pair[1].ids, return_indices=True)
        if len(common) < min_corners:
            continue
        obj.append(board.corners[common].astype(np.float32).reshape(-1, 1, 3))
        img0.append(pair[0].corners[i0].astype(np.float32).reshape(-1, 1, 2))
        img1.append(pair[1].corners[i1].astype(np.float32).reshape(-1, 1, 2))
    return obj, img0, img1


def stereo_pair(
    views: Sequence[View],
    board: BoardSpec,
    sizes: Sequence[tuple[int, int]],
    names: Sequence[str],
    *,
    dist_coeffs: int = 4,
    min_corners: int = 8,
) -> list[Camera]:
    """Cameras 0 and 1 of ``views`` calibrated as a stereo pair (see the module docstring);
    UserError when they share too few shots."""
    good = [v for v in views if len(v.ids) >= min_corners and not v.rejected]
    flags = opencv_flags(dist_coeffs)
    alone = []
    for c in (0, 1):
        mine = [v for v in good if v.camera == c]
        if len(mine) < MIN_COMMON_SHOTS:
            raise UserError(f"camera {names[c]} has {len(mine)} views")
        with one_opencv_thread():  # the same figures on every run
            _, K, dist, _, _ = cv2.calibrateCamera(
                [board.corners[v.ids].astype(np.float32).reshape(-1, 1, 3) for v in mine],
                [v.corners.astype(np.float32).reshape(-1, 1, 2) for v in mine],
                tuple(sizes[c]),
                None,
                None,
                flags=flags,
                criteria=_CRITERIA,
            )
        n_dist = 8 if dist_coeffs == 8 else 5
        alone.append((np.asarray(K, float), np.asarray(dist, float).reshape(-1)[:n_dist]))
    obj, img0, img1 = shared_corners(good, board, min_corners=min_corners)
    if len(obj) < MIN_COMMON_SHOTS:
        raise UserError(f"cameras {names[0]} and {names[1]} share {len(obj)} shots")
    (K0, d0), (K1, d1) = alone
    with one_opencv_thread():
        out = cv2.stereoCalibrate(
            obj, img0, img1, K0, d0, K1, d1, tuple(sizes[0]),
            flags=cv2.CALIB_FIX_INTRINSIC, criteria=_CRITERIA,
        )  # fmt: skip
    R, T = out[5], out[6]
    rig_T_cam1 = invert(make_transform(np.asarray(R, float), np.ravel(T)))
    return [
        Camera(names[0], *sizes[0], K0, d0),
        Camera(names[1], *sizes[1], K1, d1, rig_T_cam1),
    ]


def pairwise_held_out(
    views: Sequence[View],
    *,
    cameras: Sequence[str],
    sizes: Sequence[tuple[int, int]],
    board: BoardSpec,
    dist_coeffs: int,
    folds: int,
    min_corners: int = 8,
) -> HeldOut:
    """The held-out error of every camera pair calibrated alone (both directions), on the
    folds :func:`~annotator.calibration.heldout.held_out_error` deals ``views`` into; pairs
    that share too few shots are left out."""
    pairs: list[PairError] = []
    errors: dict[tuple[str, str], np.ndarray] = {}
    # The rig's folds, not the pair's own: the same shots held out for both.
    fold_of = {v.shot for v in views if len(v.ids) >= min_corners}
    for a in range(len(cameras)):
        for b in range(a + 1, len(cameras)):
            two = [replace(v, camera=int(v.camera == b)) for v in views if v.camera in (a, b)]
            names = (cameras[a], cameras[b])

            def fit(train: Sequence[View], names: tuple[str, str] = names) -> list[Camera]:
                pair_sizes = (sizes[cameras.index(names[0])], sizes[cameras.index(names[1])])
                return stereo_pair(
                    train, board, pair_sizes, names, dist_coeffs=dist_coeffs,
                    min_corners=min_corners,
                )  # fmt: skip

            held = held_out_error(
                two, fit, board, names, folds=folds, min_corners=min_corners, fold_shots=fold_of
            )
            pairs.extend(held.pairs)
            errors.update(held.errors)
    every = np.concatenate(list(errors.values())) if errors else np.zeros(0)
    if not len(every):
        return HeldOut(folds, (), float("nan"), 0)
    return HeldOut(
        folds,
        tuple(pairs),
        float(np.sqrt(np.mean(every**2))),
        len(every),
        float(np.median(every)),
        errors,
    )
