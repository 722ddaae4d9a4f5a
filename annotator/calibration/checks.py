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
- the rig's held-out transfer error between cameras (the median over every corner
  predicted from one camera into another, along the pairs that can be calibrated alone) is
  worse than what those pairs reach calibrated alone, each as a stereo pair by OpenCV's
  pipeline on the same folds of the same views (:mod:`.pairwise`; ``RIG_FACTOR``, and
  ``RIG_MARGIN_PX`` more), or one pair's (the median of each way, weighted by its corners)
  is far worse than that pair's alone (``PAIR_FACTOR``, and ``PAIR_MARGIN_PX`` more): a
  joint rig is held to what the simplest
  pipeline reaches on the same data. One pair alone may beat the rig by a little (its
  extrinsics absorb what its two cameras' board poses share, which a rig of many cameras
  cannot for every pair at once), hence the wider bar per pair. A pair that cannot be
  calibrated alone (too few shots together) is held instead to the held-out error of each
  of its cameras alone (``HELD_OUT_FACTOR``, and ``HELD_OUT_MARGIN_PX`` more, on the RMS):
  each camera alone is measured the same way, k-fold over its shots, the board pose fitted
  to each left-out view.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from itertools import permutations

import numpy as np

from annotator.calibration.board import BoardSpec
from annotator.calibration.heldout import HeldOut, held_out_error
from annotator.calibration.records import Calibration, View
from annotator.calibration.single import calibrate_camera, opencv_flags
from annotator.geometry.camera import Camera

RMS_FACTOR, RMS_MARGIN_PX = 5.0, 1.0
FOV_DEG = (5.0, 160.0)
FOCAL_RATIO = 1.25
DISTANCE_FACTOR = 4.0
HELD_OUT_FACTOR, HELD_OUT_MARGIN_PX = 10.0, 2.0
RIG_FACTOR, RIG_MARGIN_PX = 1.1, 0.1
PAIR_FACTOR, PAIR_MARGIN_PX = 2.0, 1.0


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


def rig_problems(
    cal: Calibration, camera_held: Sequence[float] = (), pair_held: HeldOut | None = None
) -> list[Problem]:
    """Every check of the module docstring that ``cal`` fails (``camera_held``: each camera
    alone; ``pair_held``: each pair alone)."""
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
    if cal.held_out is not None:
        problem = _transfer_problem(cal.held_out, names, camera_held, pair_held)
        problems.extend([problem] if problem is not None else [])
    return problems


def _transfer_problem(
    held: HeldOut, names: Sequence[str], camera_held: Sequence[float], pair_held: HeldOut | None
) -> Problem | None:
    """The transfer error's failure (the module docstring), or None; one line names the
    trouble, the others follow from it."""
    ours, stereo = both_ways(held), both_ways(pair_held)
    common = [k for k in ours if k in stereo]
    if common and pair_held is not None:
        # Medians over every corner, so that a pair OpenCV could not calibrate alone (its
        # folds run off) does not lift the bar for the others.
        ways = [(a, b) for k in common for a, b in permutations(sorted(k))]
        error, bar = held.pooled_median(ways), pair_held.pooled_median(ways)
        limit = max(RIG_FACTOR * bar, bar + RIG_MARGIN_PX)
        worst = max(common, key=lambda k: (ours[k][0] / max(stereo[k][0], 1e-9), sorted(k)))
        if error > limit:
            return Problem(
                max(worst, key=names.index),
                "held_out",
                f"held-out transfer error {error:.2f} px (median, over the pairs that could be "
                f"calibrated alone), against {bar:.2f} px for each pair calibrated alone as a "
                f"stereo pair (limit {limit:.2f} px; worst {_pair_name(worst, names)} "
                f"{ours[worst][0]:.2f} px against {stereo[worst][0]:.2f} px): the rig predicts "
                "one camera's corners from another's worse than the pairs alone",
            )
    for key in common:
        error, bar = ours[key][0], stereo[key][0]
        limit = max(PAIR_FACTOR * bar, bar + PAIR_MARGIN_PX)
        if error > limit:
            return Problem(
                max(key, key=names.index),
                "held_out",
                f"cameras {_pair_name(key, names)}: held-out transfer error {error:.2f} px "
                f"(median), against {bar:.2f} px for the two calibrated alone as a stereo pair "
                f"(limit {limit:.2f} px): the rig predicts one camera's corners from the "
                "other's far worse than the pair alone",
            )
    alone = dict(zip(names, camera_held))
    for pair in held.pairs:
        if pair.source == pair.target or frozenset((pair.source, pair.target)) in stereo:
            continue
        base = max(alone.get(pair.source, np.nan), alone.get(pair.target, np.nan))
        if not np.isfinite(base) or not np.isfinite(pair.rms_px):
            continue
        limit = max(HELD_OUT_FACTOR * base, base + HELD_OUT_MARGIN_PX)
        if pair.rms_px > limit:
            return Problem(
                pair.target,
                "held_out",
                f"cameras {pair.source}->{pair.target}: held-out error "
                f"{pair.rms_px:.2f} px, against {base:.2f} px for each camera alone "
                f"(limit {limit:.2f} px): the rig does not predict one camera's "
                "corners from the other's",
            )
    return None


def _pair_name(key: frozenset[str], names: Sequence[str]) -> str:
    """``a<->b`` in rig order."""
    return "<->".join(sorted(key, key=names.index))


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


def both_ways(held: HeldOut | None) -> dict[frozenset[str], tuple[float, int]]:
    """Per camera pair (either order), the median transfer error of both ways weighted by
    their corners, and those corners."""
    sums: dict[frozenset[str], list[float]] = {}
    for p in held.pairs if held is not None else ():
        if p.source != p.target and np.isfinite(p.median_px) and p.corners:
            acc = sums.setdefault(frozenset((p.source, p.target)), [0.0, 0.0])
            acc[0] += p.median_px * p.corners
            acc[1] += p.corners
    return {k: (total / n, int(n)) for k, (total, n) in sums.items()}


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
