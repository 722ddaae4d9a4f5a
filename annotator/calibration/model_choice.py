"""Choosing the distortion model by the held-out error (:mod:`.heldout`).

Every candidate model (k1 k2 p1 p2, then + k3) is calibrated on all shots and measured on
shots it did not fit. The RMS on fitted shots always prefers more coefficients; the held-out
error does not when the extra ones only fit noise or extrapolate. Rule: the model with the
fewest coefficients whose held-out error is within ``REL_TOLERANCE`` (and ``ABS_TOLERANCE_PX``)
of the best one's: an extra coefficient must earn its place on unseen shots. The chosen
calibration carries the held-out error of every candidate, and a warning per camera whose
model is extrapolated at the image corners (:mod:`.extrapolation`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from annotator.calibration.board import BoardSpec
from annotator.calibration.checks import camera_held_out, rig_problems
from annotator.calibration.extrapolation import extrapolation
from annotator.calibration.heldout import FOLDS, HeldOut, held_out_error
from annotator.calibration.pairwise import pairwise_held_out
from annotator.calibration.readings import decide_readings
from annotator.calibration.records import Calibration, CalibrationSettings, View
from annotator.calibration.rig import solve_rig
from annotator.geometry.camera import Camera

#: The models tried by default (number of coefficients), simplest first.
CANDIDATES = (4, 5)
#: A model within this fraction of the best held-out error counts as good as the best ...
REL_TOLERANCE = 0.03
#: ... or within this many pixels.
ABS_TOLERANCE_PX = 0.003


@dataclass(frozen=True)
class ModelChoice:
    """Which distortion model was chosen and why.

    Attributes:
        dist_coeffs: The chosen model's number of coefficients.
        held_out: Held-out error of each model tried.
        reason: One line for the report.
    """

    dist_coeffs: int
    held_out: Mapping[int, HeldOut]
    reason: str


def choose(held_out: Mapping[int, HeldOut]) -> tuple[int, str]:
    """The model chosen by the rule of the module docstring, and why."""
    measured = {m: h.rms_px for m, h in held_out.items() if np.isfinite(h.rms_px)}
    if not measured:
        m = max(held_out)
        return m, f"no held-out error could be measured (too few shots): {m} coefficients"
    best = min(measured.values())
    good = [
        m
        for m, e in measured.items()
        if e <= max(best * (1 + REL_TOLERANCE), best + ABS_TOLERANCE_PX)
    ]
    m = min(good)
    figures = ", ".join(f"{k} coefficients {measured[k]:.3f} px" for k in sorted(measured))
    return (
        m,
        f"held-out error {figures}: {m} chosen (the fewest within {100 * REL_TOLERANCE:g}% of the best)",
    )


@dataclass(frozen=True)
class _Problem:
    """The detections and what they are of: everything :func:`solve_rig` needs besides
    its options."""

    views: Sequence[View]
    cameras: Sequence[str]
    sizes: Sequence[tuple[int, int]]
    shots: Sequence[str]
    board: BoardSpec
    where: Mapping[str, Path] | None

    def calibrate(self, options: CalibrationSettings) -> Calibration:
        """The calibration on every view."""
        return solve_rig(
            self.views,
            cameras=self.cameras,
            sizes=self.sizes,
            shots=self.shots,
            board=self.board,
            options=options,
            where=self.where,
        )

    def fit(self, options: CalibrationSettings, train: Sequence[View]) -> tuple[Camera, ...]:
        """The cameras calibrated on ``train`` only (a fold of the held-out error: its
        errors are passed over, so no folder needs naming)."""
        return solve_rig(
            train,
            cameras=self.cameras,
            sizes=self.sizes,
            shots=self.shots,
            board=self.board,
            options=options,
        ).rig_cameras


def calibrate_and_assess(
    views: Sequence[View],
    *,
    cameras: Sequence[str],
    sizes: Sequence[tuple[int, int]],
    shots: Sequence[str],
    board: BoardSpec,
    options: CalibrationSettings | None = None,
    candidates: Sequence[int] = CANDIDATES,
    folds: int = FOLDS,
    where: Mapping[str, Path] | None = None,
) -> Calibration:
    """Decide how each camera's board reads (:mod:`.readings`), calibrate with each candidate
    model, measure each on held-out shots, keep the chosen one (``candidates`` of one model:
    that model, still measured), and check that the rig holds together (:mod:`.checks`).
    The result carries ``readings``, ``held_out``, ``model_choice``, the extrapolation
    warnings, ``camera_held_out``, ``pair_held_out`` (each camera pair calibrated alone, the
    bar the rig is held to) and ``problems`` (empty: the rig may be written)."""
    opts = options or CalibrationSettings()
    readings = decide_readings(
        views, cameras=cameras, sizes=sizes, shots=shots, board=board, options=opts
    )
    views = readings.views
    problem = _Problem(views, cameras, sizes, shots, board, where)
    cals: dict[int, Calibration] = {}
    held: dict[int, HeldOut] = {}
    for m in candidates:
        cals[m], held[m] = _calibrate_and_hold_out(
            problem, dataclasses.replace(opts, dist_coeffs=m), folds
        )
    if len(candidates) > 1:
        chosen, reason = choose(held)
    else:
        chosen = candidates[0]
        reason = f"{chosen} coefficients (as asked); held-out error {held[chosen].rms_px:.3f} px"
    cal = _with_extrapolation(
        dataclasses.replace(
            cals[chosen],
            held_out=held[chosen],
            model_choice=ModelChoice(chosen, held, reason),
            readings=readings,
        )
    )
    used = _used_views(cal)
    alone = camera_held_out(
        [v for v in views if (v.camera, v.shot) in used],
        cameras=cameras,
        sizes=sizes,
        board=board,
        dist_coeffs=chosen,
        folds=folds,
        min_corners=opts.min_corners,
    )
    pairs = pairwise_held_out(
        [v for v in views if (v.camera, v.shot) in used],
        cameras=cameras,
        sizes=sizes,
        board=board,
        dist_coeffs=chosen,
        folds=folds,
        min_corners=opts.min_corners,
    )
    return dataclasses.replace(
        cal,
        camera_held_out=alone,
        pair_held_out=pairs,
        problems=tuple(rig_problems(cal, alone, pairs)),
    )


def _calibrate_and_hold_out(
    problem: _Problem, opts: CalibrationSettings, folds: int
) -> tuple[Calibration, HeldOut]:
    """One model's calibration on every shot, and its held-out error on the views it kept."""
    cal = problem.calibrate(opts)
    # Folds fit fewer shots: a camera with just enough shots in all must still fit.
    fold_opts = dataclasses.replace(opts, min_shots=3)

    def fit(train: Sequence[View]) -> tuple[Camera, ...]:
        return problem.fit(fold_opts, train)

    used = _used_views(cal)
    held = held_out_error(
        [v for v in problem.views if (v.camera, v.shot) in used],
        fit,
        problem.board,
        problem.cameras,
        folds=folds,
        min_corners=opts.min_corners,
    )
    return cal, held


def _with_extrapolation(cal: Calibration) -> Calibration:
    """``cal`` with where each camera's distortion is extrapolated, and a warning for each
    camera whose model is extrapolated at the image corners."""
    extra = []
    for c, rep in enumerate(cal.cameras):
        sel = cal.used & (cal.corners.camera == c)
        extra.append(extrapolation(rep.camera, cal.corners.pixel[sel]))
    warnings = list(cal.warnings) + [
        ex.warning(rep.camera.name) for ex, rep in zip(extra, cal.cameras) if ex.extrapolated
    ]
    return dataclasses.replace(cal, warnings=tuple(warnings), extrapolation=tuple(extra))


def _used_views(cal: Calibration) -> set[tuple[int, int]]:
    """(camera, shot) of the views the calibration kept (outlier views are not predicted)."""
    obs = cal.corners
    return {(int(c), int(s)) for c, s in zip(obs.camera[cal.used], obs.shot[cal.used])}
