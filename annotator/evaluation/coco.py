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
  ``iscrowd``; :func:`coco_stats` keeps it.
- AP, AP50, ... AR_large are COCOeval's ``stats``, computed here on arrays for all images at
  once (:func:`coco_stats`: the same matching, interpolation and means; pycocotools still
  reads the results and computes the IoUs); no result at all gives -1 everywhere, as
  bop_toolkit.
"""

from __future__ import annotations

import contextlib
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
        nothing = {k: -1.0 for k in RES_TYPES}
        return CocoScores(ann_type, nothing, times, *counts, ["no result to score: -1"])
    with contextlib.redirect_stdout(quiet):
        cocoDt = cocoGt.loadRes(kept)  # ids, areas and boxes or masks as pycocotools makes them
    stats = dict(zip(RES_TYPES, map(float, coco_stats(cocoGt, cocoDt, ann_type))))
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
    last_image = last_ann = -1
    for i, (scene_id, doc) in enumerate(gt.scenes):
        targets = gt.images[scene_id]
        images = [dict(im) for im in doc["images"] if im["id"] in targets]
        anns = [dict(a) for a in doc["annotations"] if a["image_id"] in targets]
        mine = [dict(r) for r in by_scene.get(scene_id, []) if r["image_id"] in targets]
        if i == 0:
            merged = {**doc, "images": images, "annotations": anns}
            merged["categories"] = [dict(c) for c in doc["categories"]]
        else:
            offset = last_image + 1
            for cat in doc["categories"]:
                if cat not in merged["categories"]:
                    merged["categories"].append(dict(cat))
            first = last_ann + 1 if merged["annotations"] else 0
            for im in images:
                im["id"] += offset
            for a in anns:
                a["id"] += first
                a["image_id"] += offset
            merged["images"] += images
            merged["annotations"] += anns
            for r in mine:
                r["image_id"] += offset
        last_image = max([im["id"] for im in images] + [last_image])
        last_ann = max([a["id"] for a in anns] + [last_ann])
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


# ------------------------------------------------------------------ COCOeval, on arrays

#: COCOeval's default detection settings: IoU thresholds, recall points, detections per
#: image, area ranges (all, small, medium, large).
IOU_THRS = np.linspace(0.5, 0.95, int(np.round((0.95 - 0.5) / 0.05)) + 1, endpoint=True)
REC_THRS = np.linspace(0.0, 1.00, int(np.round((1.00 - 0.0) / 0.01)) + 1, endpoint=True)
MAX_DETS = (1, 10, 100)
AREA_RNG = ((0**2, 1e5**2), (0**2, 32**2), (32**2, 96**2), (96**2, 1e5**2))
AREA_LBL = ("all", "small", "medium", "large")


@dataclass
class _Group:
    """One (image, category): its true instances in the file's order and its detections in
    decreasing score (at most the largest of :data:`MAX_DETS`), with their IoUs."""

    gt_ids: np.ndarray
    gt_area: np.ndarray
    gt_ignore: np.ndarray  # the ``ignore`` flag, kept as BOP's pycocotools keeps it
    gt_crowd: np.ndarray
    dt_area: np.ndarray
    dt_scores: np.ndarray
    ious: np.ndarray  # (D, G)


def coco_stats(cocoGt: Any, cocoDt: Any, iou_type: str) -> np.ndarray:
    """COCOeval's 12 ``stats`` (``evaluate``, ``accumulate``, ``summarize`` with the default
    parameters, every image and category of ``cocoGt``), with BOP's ``ignore`` flags: the
    same matching, interpolation and means, computed on arrays, all images at once."""
    from pycocotools import mask as coco_mask

    img_ids = list(np.unique(sorted(cocoGt.getImgIds())))
    cat_ids = list(np.unique(sorted(cocoGt.getCatIds())))
    gts = cocoGt.loadAnns(cocoGt.getAnnIds(imgIds=img_ids, catIds=cat_ids))
    dts = cocoDt.loadAnns(cocoDt.getAnnIds(imgIds=img_ids, catIds=cat_ids))
    key = "bbox" if iou_type == "bbox" else "segmentation"

    def region(ann: dict[str, Any], coco: Any) -> Any:
        return ann["bbox"] if key == "bbox" else coco.annToRLE(ann)

    by: dict[tuple[int, int], tuple[list[Any], list[Any]]] = {}
    for g in gts:
        by.setdefault((g["image_id"], g["category_id"]), ([], []))[0].append(g)
    for d in dts:
        by.setdefault((d["image_id"], d["category_id"]), ([], []))[1].append(d)
    groups: dict[tuple[int, int], _Group] = {}
    for (img, cat), (g, d) in by.items():
        order = np.argsort([-x["score"] for x in d], kind="mergesort")[: MAX_DETS[-1]]
        d = [d[i] for i in order]
        crowd = [int(x.get("iscrowd", 0)) for x in g]
        ious = (
            np.asarray(
                coco_mask.iou(
                    [region(x, cocoDt) for x in d], [region(x, cocoGt) for x in g], crowd
                ),
                float,
            ).reshape(len(d), len(g))
            if g and d
            else np.zeros((len(d), len(g)))
        )
        groups[(img, cat)] = _Group(
            np.array([x["id"] for x in g], float),
            np.array([x["area"] for x in g], float),
            np.array([bool(x.get("ignore", 0)) for x in g], bool),
            np.array(crowd, bool),
            np.array([x["area"] for x in d], float),
            np.array([x["score"] for x in d], float),
            ious,
        )
    precision, recall = _accumulate(groups, img_ids, cat_ids)
    return _summarize(precision, recall)


def _matches(groups: list[_Group], area: tuple[float, float]) -> list[dict[str, np.ndarray]]:
    """COCOeval's ``evaluateImg`` for every group at once: per IoU threshold, each detection
    in decreasing score takes the free true instance of highest IoU at least the threshold
    (the last of equal ones), one not ignored if there is any; the detections' matched ids
    (0: none) and ignore flags, and the true instances' ignore flags, in their sorted order."""
    T, N = len(IOU_THRS), len(groups)
    G = max((len(g.gt_ids) for g in groups), default=0)
    D = max((len(g.dt_scores) for g in groups), default=0)
    ious = np.full((N, D, G), -np.inf)
    gt_ig = np.ones((N, G), bool)
    gt_id = np.zeros((N, G))
    crowd = np.zeros((N, G), bool)
    real = np.zeros((N, G), bool)
    n_dt = np.zeros(N, int)
    for n, g in enumerate(groups):
        ignore = g.gt_ignore | (g.gt_area < area[0]) | (g.gt_area > area[1])
        order = np.argsort(ignore, kind="mergesort")
        k, d = len(order), len(g.dt_scores)
        gt_ig[n, :k], gt_id[n, :k], crowd[n, :k] = ignore[order], g.gt_ids[order], g.gt_crowd[order]
        real[n, :k] = True
        ious[n, :d, :k] = g.ious[:, order]
        n_dt[n] = d
    thr = np.minimum(IOU_THRS, 1 - 1e-10)[None, :, None]
    taken = np.zeros((N, T, G), bool)
    dtm = np.zeros((N, T, D))
    dt_ig = np.zeros((N, T, D), bool)
    rows = np.arange(N)[:, None]
    for r in range(D if G else 0):
        active = n_dt > r
        v = ious[:, r, None, :]  # (N, 1, G)
        cand = (v >= thr) & real[:, None, :] & ~(taken & ~crowd[:, None, :])
        plain = cand & ~gt_ig[:, None, :]
        pick = np.where(plain.any(axis=2, keepdims=True), plain, cand)
        vals = np.where(pick, v, -np.inf)
        best = vals.max(axis=2, keepdims=True)
        m = G - 1 - np.argmax((vals == best)[:, :, ::-1], axis=2)  # the last of the best
        found = pick.any(axis=2) & active[:, None]
        dtm[:, :, r] = np.where(found, gt_id[rows, m], 0.0)
        dt_ig[:, :, r] = found & gt_ig[rows, m]
        n_i, t_i = np.nonzero(found)
        taken[n_i, t_i, m[n_i, t_i]] = True
    out = []
    for n, g in enumerate(groups):
        d = n_dt[n]
        outside = (g.dt_area < area[0]) | (g.dt_area > area[1])
        ig = dt_ig[n, :, :d] | ((dtm[n, :, :d] == 0) & outside[None, :])
        out.append(
            {"dtm": dtm[n, :, :d], "dt_ig": ig, "gt_ig": gt_ig[n, : len(g.gt_ids)],
             "scores": g.dt_scores}
        )  # fmt: skip
    return out


def _accumulate(
    groups: dict[tuple[int, int], _Group], img_ids: list[Any], cat_ids: list[Any]
) -> tuple[np.ndarray, np.ndarray]:
    """COCOeval's ``accumulate``: precision (T, R, K, A, M) and recall (T, K, A, M), -1
    where a category has nothing to find; the precision envelope and its reading at the
    recall points on arrays."""
    T, R, K, A, M = len(IOU_THRS), len(REC_THRS), len(cat_ids), len(AREA_RNG), len(MAX_DETS)
    precision = -np.ones((T, R, K, A, M))
    recall = -np.ones((T, K, A, M))
    order = [(img, cat) for cat in cat_ids for img in img_ids if (img, cat) in groups]
    for a, area in enumerate(AREA_RNG):
        evals = dict(zip(order, _matches([groups[key] for key in order], area)))
        for k, cat in enumerate(cat_ids):
            E = [evals[(img, cat)] for img in img_ids if (img, cat) in evals]
            if not E:
                continue
            gt_ig = np.concatenate([e["gt_ig"] for e in E])
            npig = np.count_nonzero(gt_ig == 0)
            if npig == 0:
                continue
            for m, max_det in enumerate(MAX_DETS):
                scores = np.concatenate([e["scores"][:max_det] for e in E])
                inds = np.argsort(-scores, kind="mergesort")
                dtm = np.concatenate([e["dtm"][:, :max_det] for e in E], axis=1)[:, inds]
                dt_ig = np.concatenate([e["dt_ig"][:, :max_det] for e in E], axis=1)[:, inds]
                tp = np.cumsum((dtm != 0) & ~dt_ig, axis=1).astype(float)
                fp = np.cumsum((dtm == 0) & ~dt_ig, axis=1).astype(float)
                nd = tp.shape[1]
                rc = tp / npig
                pr = tp / (fp + tp + np.spacing(1))
                recall[:, k, a, m] = rc[:, -1] if nd else 0
                if not nd:
                    precision[:, :, k, a, m] = 0.0
                    continue
                envelope = np.maximum.accumulate(pr[:, ::-1], axis=1)[:, ::-1]
                for t in range(T):
                    at = np.searchsorted(rc[t], REC_THRS, side="left")
                    precision[t, :, k, a, m] = np.where(
                        at < nd, envelope[t, np.minimum(at, nd - 1)], 0.0
                    )
    return precision, recall


def _summarize(precision: np.ndarray, recall: np.ndarray) -> np.ndarray:
    """COCOeval's ``summarize``: the means of the settings' values that are not -1."""

    def mean(ap: bool, iou: float | None = None, area: str = "all", dets: int = 100) -> float:
        aind = [i for i, lbl in enumerate(AREA_LBL) if lbl == area]
        mind = [i for i, m in enumerate(MAX_DETS) if m == dets]
        s = precision if ap else recall
        if iou is not None:
            s = s[np.where(iou == IOU_THRS)[0]]
        s = s[:, :, :, aind, mind] if ap else s[:, :, aind, mind]
        return -1.0 if len(s[s > -1]) == 0 else float(np.mean(s[s > -1]))

    return np.array(
        [
            mean(True),
            mean(True, iou=0.5),
            mean(True, iou=0.75),
            mean(True, area="small"),
            mean(True, area="medium"),
            mean(True, area="large"),
            mean(False, dets=1),
            mean(False, dets=10),
            mean(False),
            mean(False, area="small"),
            mean(False, area="medium"),
            mean(False, area="large"),
        ]
    )
