"""BOP's 2D detection and segmentation scores: COCO's AP and AR (pycocotools' COCOeval), as
bop_toolkit's ``scripts/eval_bop22_coco.py`` computes them (BOP 2022 on; BOP 2024's 2D
detection tasks).

- The ground truth of the target images of every target scene is merged into one COCO
  document, scene after scene, each scene's image ids shifted past the largest so far (and
  annotation ids likewise); the results' image ids are shifted with their scene's.
- Results without a box (detection) or mask (segmentation), and results of images or scenes
  that are not targets, are left out.
- True instances less than 10 % visible carry ``ignore`` (bop_toolkit's ``calc_gt_coco.py``)
  and are ignored as BOP's own pycocotools (a fork) ignores them: a detection that matches
  one is neither right nor wrong. pycocotools as published overwrites that flag with
  ``iscrowd``; :class:`_BopCOCOeval` keeps it.
- AP, AP50, ... AR_large are COCOeval's ``stats``; no result at all gives -1 everywhere, as
  bop_toolkit.
"""

from __future__ import annotations

import contextlib
import copy
import io
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from annotator.formats.coco_results import CocoGroundTruth

#: COCOeval's ``stats``, named as bop_toolkit's ``scores_bop22_coco_<type>.json``.
RES_TYPES = (
    "AP",
    "AP50",
    "AP75",
    "AP_small",
    "AP_medium",
    "AP_large",
    "AR1",
    "AR10",
    "AR100",
    "AR_small",
    "AR_medium",
    "AR_large",
)


@dataclass
class CocoScores:
    """COCO's scores of a result file, with what was counted."""

    ann_type: str
    stats: dict[str, float]
    average_time_per_image: float
    images: int
    annotations: int
    results: int
    notes: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        """bop_toolkit's ``scores_bop22_coco_<type>.json`` keys, then what was counted."""
        return {
            **self.stats,
            "average_time_per_image": self.average_time_per_image,
            "images": self.images,
            "annotations": self.annotations,
            "results": self.results,
            "notes": self.notes,
        }


def coco_scores(gt: CocoGroundTruth, results: list[dict[str, Any]], ann_type: str) -> CocoScores:
    """COCO's AP and AR of ``results`` (checked COCO results) on ``gt``, for ``ann_type``
    ``bbox`` or ``segm``. Neither argument is changed."""
    from pycocotools import mask as coco_mask
    from pycocotools.coco import COCO

    merged, kept = _merged(gt, results, ann_type)
    quiet = io.StringIO()
    with contextlib.redirect_stdout(quiet):
        cocoGt = COCO()
        cocoGt.dataset = merged
        cocoGt.createIndex()
    if ann_type == "segm":
        for r in kept:  # pycocotools needs compressed RLE when no box comes with the mask
            seg = r["segmentation"]
            if "bbox" not in r and isinstance(seg.get("counts"), list):
                img = cocoGt.imgs[r["image_id"]]
                r["segmentation"] = coco_mask.frPyObjects(seg, img["height"], img["width"])
    times = _times(results)
    counts = (len(merged["images"]), len(merged["annotations"]), len(kept))
    if not kept:
        stats = {k: -1.0 for k in RES_TYPES}
        return CocoScores(ann_type, stats, times, *counts, ["no result to score: -1"])
    with contextlib.redirect_stdout(quiet):
        cocoDt = cocoGt.loadRes(kept)
        ev = _BopCOCOeval(cocoGt, cocoDt, ann_type)
        ev.params.imgIds = sorted(cocoGt.getImgIds())
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    stats = {k: float(v) for k, v in zip(RES_TYPES, ev.stats)}
    return CocoScores(ann_type, stats, times, *counts)


def _merged(
    gt: CocoGroundTruth, results: list[dict[str, Any]], ann_type: str
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """bop_toolkit's merge of the scenes' documents and results (copies)."""
    wanted = "bbox" if ann_type == "bbox" else "segmentation"
    by_scene: dict[int, list[dict[str, Any]]] = {}
    for r in results:
        if r.get(wanted):
            by_scene.setdefault(r["scene_id"], []).append(r)
    merged: dict[str, Any] = {}
    kept: list[dict[str, Any]] = []
    for i, (scene_id, doc) in enumerate(gt.scenes):
        targets = gt.images[scene_id]
        scene = copy.deepcopy(doc)
        scene["images"] = [im for im in scene["images"] if im["id"] in targets]
        scene["annotations"] = [a for a in scene["annotations"] if a["image_id"] in targets]
        mine = [dict(r) for r in by_scene.get(scene_id, []) if r["image_id"] in targets]
        if i == 0:
            merged = scene
        else:
            offset = max(im["id"] for im in merged["images"]) + 1
            for cat in scene["categories"]:
                if cat not in merged["categories"]:
                    merged["categories"].append(cat)
            first = max((a["id"] for a in merged["annotations"]), default=-1) + 1
            for im in scene["images"]:
                im["id"] += offset
            for a in scene["annotations"]:
                a["id"] += first
                a["image_id"] += offset
            merged["images"] += scene["images"]
            merged["annotations"] += scene["annotations"]
            for r in mine:
                r["image_id"] += offset
        kept += mine
    return merged, kept


def _times(results: list[dict[str, Any]]) -> float:
    """Mean time per image, -1 when a result has none (bop_toolkit's
    ``check_consistent_timings``)."""
    times: dict[tuple[int, int], float] = {}
    for r in results:
        if "time" not in r or r["time"] < 0:
            return -1.0
        times.setdefault((r["scene_id"], r["image_id"]), float(r["time"]))
    return float(np.mean(list(times.values()))) if times else -1.0


def _bop_cocoeval() -> type:
    from pycocotools.cocoeval import COCOeval

    class BopCOCOeval(COCOeval):
        """COCOeval that ignores the true instances flagged ``ignore``, as BOP's fork of
        pycocotools does (the published one replaces the flag by ``iscrowd``)."""

        def __init__(self, cocoGt: Any, cocoDt: Any, iouType: str) -> None:
            super().__init__(cocoGt, cocoDt, iouType)
            self._ignore = {a["id"]: a.get("ignore", 0) for a in cocoGt.dataset["annotations"]}

        def _prepare(self) -> None:
            super()._prepare()
            for gts in self._gts.values():
                for g in gts:
                    g["ignore"] = self._ignore.get(g["id"], 0)
                    g["iscrowd"] = bool(g.get("iscrowd", 0))

    return BopCOCOeval


def _BopCOCOeval(cocoGt: Any, cocoDt: Any, iouType: str) -> Any:
    """A :func:`_bop_cocoeval` evaluator (pycocotools is imported only when scoring)."""
    return _bop_cocoeval()(cocoGt, cocoDt, iouType)
