"""BOP's 6D detection scores (BOP Challenge 2024 onwards): mAP over MSSD and MSPD.

The definitions are bop_toolkit's (``scripts/eval_bop24_pose.py`` with
``eval_calc_errors.py`` and ``eval_calc_scores.py`` in ``--eval_mode=detection``,
``pose_matching.py`` and ``score.calc_pose_detection_scores``), written again on arrays, on
the records :mod:`annotator.formats.bop_images` reads with ``task="detection"``.

- **Images** are those of ``test_targets_bop24.json``; object identities are not given, so
  every object with a true pose in an image is looked for there. Estimates of an object the
  image has no true pose of are not scored at all (bop_toolkit computes no error for them).
- **Per-image limit.** Each image keeps its :data:`MAX_ESTIMATES_PER_IMAGE` best-scored
  estimates (200 for ``xyzibd``), ties in the file's order; the others are dropped.
- **Errors** as in :mod:`annotator.evaluation.bop19`: MSSD over the diameter (infinite when
  the centres are a diameter or more apart), MSSD in mm, MSPD scaled to an image 640 pixels
  wide.
- **Matching.** Per (image, object), estimates in decreasing score each take the not yet
  taken true pose of least error, strictly below the threshold; every true pose may be taken.
- **Visibility cut-off.** True poses less than :data:`VISIB_GT_MIN` visible are not to be
  found, and an estimate that took one is ignored (neither a true nor a false positive).
- **AP** per object and threshold: COCO's 101-point interpolated precision over the
  estimates of the object in decreasing score (ties in image order, as bop_toolkit lists
  them). A metric's mAP is the mean over thresholds, then over the objects with something to
  find. ``bop24_mAP`` is the mean of MSSD's and MSPD's; ``bop25_mAP`` is MSSD's alone and
  ``bop25_mAP_mm`` MSSD's with thresholds in mm (:data:`MSSD_MM_TH`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from annotator.evaluation.bop19 import (
    CORRECT_TH,
    MSPD_REFERENCE_WIDTH_PX,
    MSPD_TH_PX,
    MSSD_MM_TH,
    error_tables,
    greedy_matches,
)
from annotator.formats.bop_images import BopEstimates, BopImage, BopObject

#: True poses less visible than this are not to be found (bop_toolkit's ``visib_gt_min``).
VISIB_GT_MIN = 0.1
#: Estimates kept per image (bop_toolkit's ``max_num_estimates_per_image``) ...
MAX_ESTIMATES_PER_IMAGE = 100
#: ... and for the datasets it gives more.
MAX_ESTIMATES_PER_DATASET = {"xyzibd": 200}
#: COCO's recall points for the interpolated precision.
RECALL_POINTS = np.linspace(0.0, 1.00, 101, endpoint=True)

#: Metric -> thresholds, in bop_toolkit's order of ``errors``.
THRESHOLDS = {"mssd": CORRECT_TH, "mssd_mm": MSSD_MM_TH, "mspd": MSPD_TH_PX.astype(float)}


@dataclass
class Bop24Scores:
    """BOP's 6D detection scores, overall and per object id (None where nothing is to be
    found).

    Attributes:
        maps: ``"mssd" | "mssd_mm" | "mspd"`` -> mAP over the objects.
        per_object: object id -> metric -> mAP over the thresholds (None: nothing to find).
        aps: metric -> object id -> AP per threshold.
        targets: True poses to find; ``estimates``: estimates scored; ``ignored``: those
            that took a true pose less than :data:`VISIB_GT_MIN` visible (at the first
            threshold of MSSD); ``dropped``: beyond the per-image limit.
        time_per_image: Mean of the result file's times per image (s); -1 when the file
            has none, as bop_toolkit.

    >>> from annotator.evaluation.bop24 import bop24_scores
    >>> s = bop24_scores([], {}, {})
    >>> s.targets, s.estimates, s.bop24_map
    (0, 0, None)
    """

    maps: dict[str, float | None]
    per_object: dict[int, dict[str, float | None]]
    aps: dict[str, dict[int, list[float]]]
    targets: int
    estimates: int
    ignored: int
    dropped: int
    time_per_image: float = -1.0
    notes: list[str] = field(default_factory=list)

    @property
    def bop24_map(self) -> float | None:
        """Mean of MSSD's and MSPD's mAP."""
        m, p = self.maps["mssd"], self.maps["mspd"]
        return None if m is None or p is None else float(np.mean([m, p]))

    def to_json(self) -> dict[str, Any]:
        """The ``"bop24"`` block of ``evaluate --json``: bop_toolkit's scores_bop24.json keys,
        then what was counted."""
        return {
            "bop24_mAP_mssd": self.maps["mssd"],
            "bop24_mAP_mssd_mm": self.maps["mssd_mm"],
            "bop24_mAP_mspd": self.maps["mspd"],
            "bop24_mAP": self.bop24_map,
            "bop25_mAP": self.maps["mssd"],
            "bop25_mAP_mm": self.maps["mssd_mm"],
            "bop24_average_time_per_image": self.time_per_image,
            "targets": self.targets,
            "estimates": self.estimates,
            "ignored": self.ignored,
            "dropped": self.dropped,
            "per_object": {
                str(oid): {f"mAP_{m}": v for m, v in row.items()}
                for oid, row in sorted(self.per_object.items())
            },
            "notes": self.notes,
        }


def max_estimates_for(result_name: str) -> int:
    """bop_toolkit's per-image limit for a result file named as BOP names them
    (``METHOD_DATASET-SPLIT[...].csv``): the dataset's own, else
    :data:`MAX_ESTIMATES_PER_IMAGE`."""
    parts = result_name.split("_")
    dataset = parts[1].split("-")[0] if len(parts) > 1 else ""
    return MAX_ESTIMATES_PER_DATASET.get(dataset, MAX_ESTIMATES_PER_IMAGE)


def average_precision(recalls: np.ndarray, precisions: np.ndarray) -> float:
    """bop_toolkit's ``score.calc_ap``: the mean over :data:`RECALL_POINTS` of the largest
    precision at a recall at least that high (0 past the last), with (0, 0) and (1, 0)
    added.

    >>> average_precision(np.array([0.5, 1.0]), np.array([1.0, 1.0]))
    1.0
    """
    mrec = np.concatenate(([0.0], np.asarray(recalls, float), [1.0]))
    mpre = np.concatenate(([0.0], np.asarray(precisions, float), [0.0]))
    order = np.argsort(mrec, kind="stable")
    rec = mrec[order]
    best_after = np.maximum.accumulate(mpre[order][::-1])[::-1]
    first = np.searchsorted(rec, RECALL_POINTS, side="left")
    inside = first < len(rec)
    interpolated = np.where(inside, best_after[np.minimum(first, len(rec) - 1)], 0.0)
    return float(np.mean(interpolated))


@dataclass
class _Detections:
    """One object's scored estimates over all images, in bop_toolkit's listing order."""

    scores: list[np.ndarray] = field(default_factory=list)
    # metric -> per group (E, thresholds): 1 true positive, 0 false, -1 ignored
    status: dict[str, list[np.ndarray]] = field(default_factory=dict)
    targets: int = 0


def bop24_scores(
    images: Sequence[BopImage],
    estimates: dict[tuple[int, int], BopEstimates],
    objects: dict[int, BopObject],
    *,
    max_per_image: int = MAX_ESTIMATES_PER_IMAGE,
    visib_gt_min: float = VISIB_GT_MIN,
    times: dict[tuple[int, int], float] | None = None,
    progress: Callable[[], None] | None = None,
) -> Bop24Scores:
    """BOP's 6D detection mAPs of ``estimates`` ((scene_id, im_id) -> estimates, in the
    result file's order) on ``images`` (in the targets file's order). ``times``: each
    image's time in the result file (None: not given)."""
    found = {oid: _Detections() for oid in objects}
    scored = ignored = dropped = 0
    for image in images:
        est = estimates.get((image.scene_id, image.im_id))
        keep = np.zeros(0, int)
        if est is not None:
            keep = np.argsort(-est.scores, kind="stable")
            dropped += max(0, len(keep) - max_per_image)
            keep = keep[:max_per_image]
        for oid in dict.fromkeys(image.obj_ids.tolist()):
            gts = np.flatnonzero(image.obj_ids == oid)
            visible = image.visib[gts] >= visib_gt_min
            det = found[oid]
            det.targets += int(visible.sum())
            mine = keep[est.obj_ids[keep] == oid] if est is not None else keep
            if not len(mine):
                continue
            errors = _errors(image, est, mine, gts, objects[oid])  # type: ignore[arg-type]
            det.scores.append(est.scores[mine])  # type: ignore[union-attr]
            for metric, ths in THRESHOLDS.items():
                taken = greedy_matches(errors[metric], np.ones(len(gts), bool), ths).T
                status = np.where(taken >= 0, np.where(visible[taken], 1, -1), 0)
                det.status.setdefault(metric, []).append(status.astype(np.int8))
            scored += len(mine)
            ignored += int(np.sum(det.status["mssd"][-1][:, 0] < 0))
        if progress:
            progress()
    return _summary(found, scored, ignored, dropped, times)


def _errors(
    image: BopImage, est: BopEstimates, mine: np.ndarray, gts: np.ndarray, obj: BopObject
) -> dict[str, np.ndarray]:
    """metric -> (E, G) errors of the estimates ``mine`` against the true poses ``gts``
    (:func:`annotator.evaluation.bop19.error_tables`); errors past every threshold are
    infinite."""
    mm, px = error_tables(image, est, mine, gts, obj)
    scale = MSPD_REFERENCE_WIDTH_PX / image.width
    return {"mssd": mm / obj.diameter, "mssd_mm": mm, "mspd": scale * px}


def _summary(
    found: dict[int, _Detections],
    scored: int,
    ignored: int,
    dropped: int,
    times: dict[tuple[int, int], float] | None,
) -> Bop24Scores:
    aps: dict[str, dict[int, list[float]]] = {m: {} for m in THRESHOLDS}
    per_object: dict[int, dict[str, float | None]] = {}
    for oid, det in sorted(found.items()):
        row: dict[str, float | None] = {m: None for m in THRESHOLDS}
        if det.targets:
            scores = np.concatenate(det.scores) if det.scores else np.zeros(0)
            order = np.argsort(-scores, kind="stable")
            for metric, ths in THRESHOLDS.items():
                status = (
                    np.concatenate(det.status[metric])[order]
                    if det.scores
                    else np.zeros((0, len(ths)), np.int8)
                )
                aps[metric][oid] = [_ap(status[:, k], det.targets) for k in range(len(ths))]
                row[metric] = float(np.mean(aps[metric][oid]))
        per_object[oid] = row
    maps: dict[str, float | None] = {}
    for metric in THRESHOLDS:
        got = [v for r in per_object.values() if (v := r[metric]) is not None]
        maps[metric] = float(np.mean(got)) if got else None
    time = float(np.mean(list(times.values()))) if times else -1.0
    targets = sum(d.targets for d in found.values())
    return Bop24Scores(maps, per_object, aps, targets, scored, ignored, dropped, time)


def _ap(status: np.ndarray, targets: int) -> float:
    """AP of estimates in decreasing score, each a true (1) or false (0) positive or
    ignored (-1), with ``targets`` true poses to find."""
    kept = status[status >= 0]
    tp = np.cumsum(kept == 1)
    fp = np.cumsum(kept == 0)
    recalls = tp / float(targets)
    with np.errstate(invalid="ignore", divide="ignore"):
        precisions = tp / (tp + fp)
    precisions[~np.isfinite(precisions)] = 0.0
    return average_precision(recalls, precisions)
