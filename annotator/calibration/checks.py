"""Whether a calibrated rig holds together, before anything is written into a dataset.

A joint solve can run off on views that do not describe one rig (a camera read the wrong
way, shots of other moments, a camera that moved) and still end with numbers. The rig is
refused, naming the camera and the check, when

- the joint refinement did not converge (it stopped at its iteration limit);
- a camera's RMS in the joint solve is far above its RMS alone (``RMS_FACTOR``, and
  ``RMS_MARGIN_PX`` more);
- a focal length is implausible for the image size (a horizontal field of view outside
  ``FOV_DEG``) or far from the camera's own ``calibrateCamera`` (``FOCAL_RATIO``);
- a camera is farther from the first than ``DISTANCE_FACTOR`` times the farthest any camera
  saw the board (two cameras that see one board are at most the sum of their distances to it
  apart);
- a camera pair's held-out error is far above the held-out error of those cameras alone
  (``HELD_OUT_FACTOR``, and ``HELD_OUT_MARGIN_PX`` more): each camera alone is measured
  the same way, k-fold over its shots, the board pose fitted to each left-out view.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from annotator.calibration.board import BoardSpec
from annotator.calibration.heldout import held_out_error
from annotator.calibration.records import Calibration, View
from annotator.calibration.single import calibrate_camera, opencv_flags
from annotator.geometry.camera import Camera

RMS_FACTOR, RMS_MARGIN_PX = 5.0, 1.0
FOV_DEG = (5.0, 160.0)
FOCAL_RATIO = 1.25
DISTANCE_FACTOR = 4.0
HELD_OUT_FACTOR, HELD_OUT_MARGIN_PX = 10.0, 2.0


@dataclass(frozen=True)
class Problem:
    """One failed check: the camera (None: the whole rig), which check, and the line."""

    camera: str | None
    check: str
    message: str

    def __str__(self) -> str:
        return self.message

    def to_dict(self) -> dict:
        return {"camera": self.camera, "check": self.check, "message": self.message}


def camera_held_out(
    views: Sequence[View],
    *,
    cameras: Sequence[str],
    sizes: Sequence[tuple[int, int]],
    board: BoardSpec,
    dist_coeffs: int,
    folds: int,
    min_corners: int = 8,
) -> tuple[float, ...]:
    """Per camera, the held-out error of that camera alone (OpenCV's ``calibrateCamera`` on
    the other folds, each left-out view's board pose fitted to it: px RMS); NaN when it
    cannot be measured."""
    out = []
    n_dist = 8 if dist_coeffs == 8 else 5
    for c, name in enumerate(cameras):
        mine = [replace(v, camera=0) for v in views if v.camera == c]
        w, h = sizes[c]

        def fit(train: Sequence[View], name: str = name, w: int = w, h: int = h) -> list[Camera]:
            shots = [str(k) for k in range(max((v.shot for v in train), default=0) + 1)]
            K, dist, _, _ = calibrate_camera(
                list(train), board, (w, h), opencv_flags(dist_coeffs), [], name, shots, n_dist
            )
            return [Camera(name, w, h, K, dist)]

        held = held_out_error(mine, fit, board, [name], folds=folds, min_corners=min_corners)
        out.append(held.rms_px)
    return tuple(out)


def rig_problems(cal: Calibration, camera_held: Sequence[float] = ()) -> list[Problem]:
    """Every check of the module docstring that ``cal`` fails."""
    problems: list[Problem] = []
    names = [rep.camera.name for rep in cal.cameras]
    if not cal.converged:
        problems.append(
            Problem(
                None,
                "converged",
                f"the joint solve did not converge in {cal.iterations} iterations (RMS "
                f"{cal.rms_px:.2f} px): the cameras' views do not describe one rig",
            )
        )
    for rep in cal.cameras:
        problems.extend(_camera_problems(cal, rep, names))
    if cal.held_out is not None and camera_held:
        alone = dict(zip(names, camera_held))
        for pair in cal.held_out.pairs:
            if pair.source == pair.target:
                continue
            base = max(alone.get(pair.source, np.nan), alone.get(pair.target, np.nan))
            if not np.isfinite(base) or not np.isfinite(pair.rms_px):
                continue
            limit = max(HELD_OUT_FACTOR * base, base + HELD_OUT_MARGIN_PX)
            if pair.rms_px > limit:
                problems.append(
                    Problem(
                        pair.target,
                        "held_out",
                        f"cameras {pair.source}->{pair.target}: held-out error "
                        f"{pair.rms_px:.2f} px, against {base:.2f} px for each camera alone "
                        f"(limit {limit:.2f} px): the rig does not predict one camera's "
                        "corners from the other's",
                    )
                )
                break  # one pair names the trouble; the others follow from it
    return problems


def _camera_problems(cal: Calibration, rep, names: Sequence[str]) -> list[Problem]:  # noqa: ANN001
    """The checks of one camera: RMS, focal lengths, distance from the first camera."""
    out = []
    cam = rep.camera
    name = cam.name
    limit = max(RMS_FACTOR * rep.initial_rms_px, rep.initial_rms_px + RMS_MARGIN_PX)
    if np.isfinite(rep.rms_px) and rep.rms_px > limit:
        out.append(
            Problem(
                name,
                "rms",
                f"camera {name}: RMS {rep.rms_px:.2f} px in the joint solve against "
                f"{rep.initial_rms_px:.2f} px for the camera alone: its views do not fit the "
                "rig",
            )
        )
    low, high = (cam.width / (2 * math.tan(math.radians(a) / 2)) for a in reversed(FOV_DEG))
    for axis, f, f0 in zip("xy", np.diag(cam.K)[:2], rep.initial_focal_px):
        bad_size = not low <= f <= high
        bad_alone = np.isfinite(f0) and not 1 / FOCAL_RATIO <= f / f0 <= FOCAL_RATIO
        if bad_size or bad_alone:
            out.append(
                Problem(
                    name,
                    "focal",
                    f"camera {name}: focal length f{axis} = {f:.0f} px for a {cam.width}x"
                    f"{cam.height} image ({low:.0f}-{high:.0f} px is plausible), against "
                    f"{f0:.0f} px for the camera alone",
                )
            )
            break
    reach = max((r.board_distance_mm for r in cal.cameras), default=np.nan)
    far = float(np.linalg.norm(cam.rig_T_cam[:3, 3]))
    if np.isfinite(reach) and far > DISTANCE_FACTOR * reach:
        out.append(
            Problem(
                name,
                "distance",
                f"camera {name}: {far:.0f} mm from camera {names[0]}, while no camera saw the "
                f"board farther than {reach:.0f} mm away",
            )
        )
    return out


def what_to_try(problems: Sequence[Problem], cameras: Sequence[str]) -> str:
    """One line of advice for a refused rig."""
    named = [p.camera for p in problems if p.camera is not None]
    # The camera most checks name; of several, not the first (the rig's frame).
    order = {c: k for k, c in enumerate(cameras)}
    cam = max(named, key=lambda c: (named.count(c), order.get(c, 0)), default=None)
    others = [c for c in cameras if c != cam]
    if cam is not None and others:
        leave_out = f"--cameras {','.join(others)} to calibrate without camera {cam}, "
        alone = f"--cameras {cam} to see it calibrated alone"
        return (
            f"try {leave_out}or {alone}; check that its shots are of the same moments as the "
            "others' and that it did not move; the report says how each camera's board was "
            "read"
        )
    return (
        "check that every camera's shots are of the same moments and that no camera moved; "
        "the report's per-shot RMS shows where the views disagree"
    )
