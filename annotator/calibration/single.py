"""One camera alone: which views can be used, and OpenCV's ``calibrateCamera`` on them (the
views it cannot fit left out), the first step of a rig calibration (:mod:`.rig`)."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np

from annotator.calibration.board import BoardSpec
from annotator.calibration.records import CalibrationSettings, Rejection, View
from annotator.errors import UserError
from annotator.geometry.transforms import make_transform


def opencv_flags(dist_coeffs: int) -> int:
    flags = cv2.CALIB_RATIONAL_MODEL if dist_coeffs == 8 else 0
    if dist_coeffs < 5:
        flags |= cv2.CALIB_FIX_K3
    if dist_coeffs < 4:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    return flags


def screen_views(
    views: Sequence[View],
    cameras: Sequence[str],
    shots: Sequence[str],
    board: BoardSpec,
    opts: CalibrationSettings,
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


def require_shots(
    usable: Sequence[View],
    c: int,
    name: str,
    views: Sequence[View],
    opts: CalibrationSettings,
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


def calibrate_camera(
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
            with one_opencv_thread():
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
def one_opencv_thread() -> Iterator[None]:
    """OpenCV on one thread meanwhile: with several, ``calibrateCamera`` sums in a varying
    order and its results differ from run to run in the ninth digit, enough to change the
    written dataset.yaml when nothing else changed."""
    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(before)
