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
- AP, AP50, ... AR_large are COCOeval's ``stats``, computed here on arrays for all images and
  categories at once (:func:`coco_stats`): the same IoUs (boxes with the arithmetic of
  pycocotools' ``bbIou``; masks by pycocotools' own C routines, ``rleFrString`` and
  ``rleIou``, called directly, with no mask decoded), matching, interpolation and means.
  What the arrays do not model (polygons, repeated annotation ids, a result of an image
  that is not in the ground truth) is left to pycocotools' COCOeval. No result at all gives
  -1 everywhere, as bop_toolkit.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import io
import itertools
import types
import weakref
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from annotator.formats.coco_results import CocoGroundTruth, paused_gc

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
    """COCO's scores of a result file, with what was counted.

    >>> s = CocoScores("bbox", {"AP": 0.5, "AP50": 0.8}, 0.1, images=4, annotations=36, results=37)
    >>> s.to_json()["AP50"]
    0.8
    """

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


@paused_gc()
def coco_scores(gt: CocoGroundTruth, results: list[dict[str, Any]], ann_type: str) -> CocoScores:
    """COCO's AP and AR of ``results`` (checked COCO results) on ``gt``, for ``ann_type``
    ``bbox`` or ``segm``. Neither argument is changed."""
    merged, kept = _merged(gt, results, ann_type)
    times = _times(results)
    counts = (len(merged["images"]), len(merged["annotations"]), len(kept))
    if not kept:
        nothing = {k: -1.0 for k in RES_TYPES}
        return CocoScores(ann_type, nothing, times, *counts, ["no result to score: -1"])
    stats = dict(zip(RES_TYPES, map(float, coco_stats(merged, kept, ann_type))))
    return CocoScores(ann_type, stats, times, *counts)


def _merged(
    gt: CocoGroundTruth, results: list[dict[str, Any]], ann_type: str
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """bop_toolkit's merge of the scenes' documents and of the results with a box (or a
    mask) of their target images, their image ids shifted with their scene's (copies)."""
    doc, offsets = gt.merged
    wanted = "bbox" if ann_type == "bbox" else "segmentation"
    by_scene: dict[int, list[dict[str, Any]]] = {}
    for r in results:
        if r.get(wanted):
            by_scene.setdefault(r["scene_id"], []).append(r)
    kept: list[dict[str, Any]] = []
    for scene_id, offset in offsets.items():
        targets = gt.images[scene_id]
        kept += [
            {**r, "image_id": r["image_id"] + offset}
            for r in by_scene.get(scene_id, [])
            if r["image_id"] in targets
        ]
    return doc, kept


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


#: The matching's lanes: every (area range, IoU threshold), area range major; a lane's area
#: range and its threshold as COCOeval compares it.
_LANE_AREA = np.repeat(np.arange(len(AREA_RNG)), len(IOU_THRS))
_LANE_THR = np.tile(np.minimum(IOU_THRS, 1 - 1e-10), len(AREA_RNG))


@dataclass
class _Table:
    """The instances and detections COCOeval scores, as arrays: the true instances grouped
    by (category, image), in the file's order within a group; the detections grouped alike,
    in decreasing score within a group (stable), at most the largest of :data:`MAX_DETS`."""

    n_img: int
    n_cat: int
    g_id: np.ndarray
    g_key: np.ndarray  # category index * images + image index
    g_area: np.ndarray
    g_ignore: np.ndarray  # the ``ignore`` flag, kept as BOP's pycocotools keeps it
    g_crowd: np.ndarray
    g_region: np.ndarray | _Rles  # boxes (n, 4) or masks
    d_key: np.ndarray
    d_rank: np.ndarray  # the place in its group
    d_score: np.ndarray
    d_area: np.ndarray
    d_region: np.ndarray | _Rles


class _Unusual(Exception):
    """Input the array path does not model (pycocotools' own evaluation decides)."""


def coco_stats(doc: dict[str, Any], results: list[dict[str, Any]], iou_type: str) -> np.ndarray:
    """COCOeval's 12 ``stats`` of ``results`` (as ``COCO.loadRes`` takes them) on the COCO
    document ``doc`` (``evaluate``, ``accumulate``, ``summarize`` with the default
    parameters, every image and category of ``doc``), with BOP's ``ignore`` flags: the same
    IoUs (pycocotools' own RLE IoU for masks, its box IoU's arithmetic for boxes), matching,
    interpolation and means, on arrays for all images and categories at once. Input it does
    not model (repeated annotation ids, polygons, a result of an unknown image) goes to
    pycocotools' COCOeval itself."""
    if not results:
        return -np.ones(len(RES_TYPES))  # bop_toolkit's outcome (loadRes fails)
    try:
        table = _table(doc, results, iou_type)
    except _Unusual:
        return _cocoeval_stats(doc, results, iou_type)
    precision, recall = _accumulate(table, *_match(table, _ious(table)))
    return _summarize(precision, recall)


def _cocoeval_stats(
    doc: dict[str, Any], results: list[dict[str, Any]], iou_type: str
) -> np.ndarray:
    """pycocotools' COCOeval, keeping the ``ignore`` flag as BOP's fork does."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    class ForkEval(COCOeval):
        def _prepare(self) -> None:
            keep = {id(a): a.get("ignore", 0) for a in self.cocoGt.dataset["annotations"]}
            super()._prepare()
            for gts in self._gts.values():
                for g in gts:
                    g["ignore"] = keep[id(g)]

    with contextlib.redirect_stdout(io.StringIO()):
        gt = COCO()
        gt.dataset = copy.deepcopy(doc)
        gt.createIndex()
        ev = ForkEval(gt, gt.loadRes(copy.deepcopy(results)), iou_type)
        ev.params.imgIds = sorted(gt.getImgIds())
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    return np.asarray(ev.stats, float)


def _index(ids: np.ndarray, known: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each of ``ids`` stands in the sorted ``known``, and whether it is there."""
    at = np.minimum(np.searchsorted(known, ids), max(len(known) - 1, 0))
    return at, (known[at] == ids) if len(known) else np.zeros(len(ids), bool)


def _rows(values: list[Any], width: int, dtype: type) -> np.ndarray:
    """Lists of ``width`` numbers as an (n, width) array (quicker than ``np.array``)."""
    if any(len(v) != width for v in values):
        raise _Unusual
    flat: np.ndarray = np.fromiter(
        itertools.chain.from_iterable(values), dtype, len(values) * width
    )
    return flat.reshape(len(values), width)


def _table(doc: dict[str, Any], results: list[dict[str, Any]], iou_type: str) -> _Table:
    """COCO's prepared instances and detections (``COCO.loadRes``, ``COCOeval._prepare``)."""
    img_ids = np.unique(np.array([im["id"] for im in doc["images"]]))
    cat_ids = np.unique(np.array([c["id"] for c in doc["categories"]]))
    n_img, n_cat = len(img_ids), len(cat_ids)
    anns = doc["annotations"]
    if len({a["id"] for a in anns}) != len(anns):
        raise _Unusual
    g_img, in_img = _index(np.array([a["image_id"] for a in anns]), img_ids)
    g_cat, in_cat = _index(np.array([a["category_id"] for a in anns]), cat_ids)
    g_key = (g_cat * n_img + g_img)[in_img & in_cat]
    g_keep = np.flatnonzero(in_img & in_cat)[np.argsort(g_key, kind="stable")]
    gts = [anns[i] for i in g_keep]
    d_img, d_in_img = _index(np.array([r["image_id"] for r in results]), img_ids)
    if not d_in_img.all():
        raise _Unusual  # pycocotools' loadRes refuses it
    d_cat, d_in_cat = _index(np.array([r["category_id"] for r in results]), cat_ids)
    d_key_all = d_cat * n_img + d_img
    d_score_all = np.array([r["score"] for r in results], float)
    order = np.lexsort((np.arange(len(results)), -d_score_all, d_key_all))
    order = order[d_in_cat[order]]
    d_key = d_key_all[order]
    first = np.searchsorted(d_key, d_key)
    d_rank = np.arange(len(d_key)) - first
    order, d_key, d_rank = (
        order[d_rank < MAX_DETS[-1]],
        d_key[d_rank < MAX_DETS[-1]],
        d_rank[d_rank < MAX_DETS[-1]],
    )
    dts = [results[i] for i in order]
    d_rles: _Rles | None = None
    # loadRes: the area of the box, as the first result has one (all of them must: where
    # some lack it, pycocotools would fail; their masks' areas serve then).
    boxed = "bbox" in results[0] and results[0]["bbox"] != [] and all("bbox" in r for r in dts)
    if boxed:
        d_box = _rows([r["bbox"] for r in dts], 4, np.float64)
        d_area = d_box[:, 2] * d_box[:, 3]
    elif iou_type == "segm":
        d_rles = _rles([r["segmentation"] for r in dts])
        d_area = d_rles.area
    else:
        raise _Unusual
    if iou_type == "bbox":
        g_region: np.ndarray | _Rles = _rows([a["bbox"] for a in gts], 4, np.float64)
        d_region: np.ndarray | _Rles = d_box
    else:
        g_region = _rles([a["segmentation"] for a in gts])
        d_region = d_rles if d_rles is not None else _rles([r["segmentation"] for r in dts])
    return _Table(
        n_img,
        n_cat,
        np.array([a["id"] for a in gts], float),
        np.sort(g_key),
        np.array([a["area"] for a in gts], float),
        np.array([bool(a.get("ignore", 0)) for a in gts], bool),
        np.array([int(a.get("iscrowd", 0) or 0) != 0 for a in gts], bool),
        g_region,
        d_key,
        d_rank,
        d_score_all[order],
        d_area,
        d_region,
    )


@dataclass
class _Pairs:
    """Every (detection, true instance) of a group, detection major, and their IoU."""

    det: np.ndarray
    gt: np.ndarray
    iou: np.ndarray
    g_start: np.ndarray  # per detection: where its group's true instances start


def _ious(t: _Table) -> _Pairs:
    """COCOeval's ``computeIoU`` for every group: boxes with pycocotools' arithmetic
    (``bbIou``), masks with pycocotools' RLE IoU, a call a group."""
    g_start = np.searchsorted(t.g_key, t.d_key, "left")
    count = np.searchsorted(t.g_key, t.d_key, "right") - g_start
    det = np.repeat(np.arange(len(t.d_key)), count)
    gt = (
        np.arange(len(det)) - np.repeat(np.cumsum(count) - count, count) + np.repeat(g_start, count)
    )
    crowd = t.g_crowd[gt]
    if isinstance(t.d_region, np.ndarray) and isinstance(t.g_region, np.ndarray):
        d, g = t.d_region[det], t.g_region[gt]
        w = np.minimum(d[:, 2] + d[:, 0], g[:, 2] + g[:, 0]) - np.maximum(d[:, 0], g[:, 0])
        h = np.minimum(d[:, 3] + d[:, 1], g[:, 3] + g[:, 1]) - np.maximum(d[:, 1], g[:, 1])
        inter = w * h
        union = np.where(crowd, d[:, 2] * d[:, 3], d[:, 2] * d[:, 3] + g[:, 2] * g[:, 3] - inter)
        with np.errstate(divide="ignore", invalid="ignore"):
            iou = np.where((w > 0) & (h > 0), inter / union, 0.0)
        return _Pairs(det, gt, iou, g_start)
    assert isinstance(t.d_region, _Rles) and isinstance(t.g_region, _Rles)
    rle_iou = _c_routines().rleIou
    crowd = t.g_crowd.astype(np.uint8)
    d0 = np.flatnonzero((count > 0) & np.r_[True, t.d_key[1:] != t.d_key[:-1]])
    nd = np.searchsorted(t.d_key, t.d_key[d0], "right") - d0
    g0, ng = g_start[d0], count[d0]
    at = np.cumsum(ng * nd) - ng * nd
    block = np.zeros(int((ng * nd).sum()))  # a group's (G, D), as rleIou writes it
    calls = zip(
        (t.d_region.structs.ctypes.data + 32 * d0).tolist(),
        (t.g_region.structs.ctypes.data + 32 * g0).tolist(),
        nd.tolist(),
        ng.tolist(),
        (crowd.ctypes.data + g0).tolist(),
        (block.ctypes.data + 8 * at).tolist(),
    )
    for call in calls:
        rle_iou(*call)
    group = np.searchsorted(d0, det, "right") - 1
    iou = block[at[group] + (gt - g0[group]) * nd[group] + (det - d0[group])]
    return _Pairs(det, gt, iou, g_start)


def _match(t: _Table, p: _Pairs) -> tuple[np.ndarray, np.ndarray]:
    """COCOeval's ``evaluateImg`` for every group and lane at once, a detection rank at a
    time: each detection takes the free true instance of highest IoU at least the threshold
    (the last of equal ones in the order that puts ignored instances last), one not ignored
    if there is any. The detections' matched ids (0: none) and ignore flags, (D, lanes)."""
    lo, hi = np.array([a for a, _ in AREA_RNG]), np.array([b for _, b in AREA_RNG])
    g_ig = t.g_ignore[:, None] | (t.g_area[:, None] < lo) | (t.g_area[:, None] > hi)  # (G, A)
    n_gt, n_area, lanes = len(t.g_key), len(AREA_RNG), len(_LANE_AREA)
    pos = np.zeros((n_gt, n_area), np.int64)  # the place in its group, ignored ones last
    at = np.zeros((n_area, n_gt), np.int64)  # the inverse: group start + place -> instance
    first = np.searchsorted(t.g_key, t.g_key)
    for a in range(n_area):
        order = np.lexsort((np.arange(n_gt), g_ig[:, a], t.g_key))
        pos[order, a] = np.arange(n_gt) - first[order]
        at[a, first[order] + pos[order, a]] = order
    dtm = np.zeros((len(t.d_key), lanes))
    dt_ig = np.zeros((len(t.d_key), lanes), bool)
    taken = np.zeros((n_gt, lanes), bool)
    useful = np.flatnonzero(p.iou >= _LANE_THR.min())  # others are no lane's candidates
    by_rank = useful[np.argsort(t.d_rank[p.det[useful]], kind="stable")]
    det, gt, iou = p.det[by_rank], p.gt[by_rank], p.iou[by_rank]
    bounds = np.searchsorted(t.d_rank[det], np.arange(MAX_DETS[-1] + 1))
    for r in range(MAX_DETS[-1]):
        sl = slice(bounds[r], bounds[r + 1])
        if bounds[r] == bounds[r + 1]:
            continue
        d, g, v = det[sl], gt[sl], iou[sl, None]
        new = np.r_[True, d[1:] != d[:-1]]
        starts, seg = np.flatnonzero(new), np.cumsum(new) - 1
        ig = g_ig[g][:, _LANE_AREA]
        cand = (v >= _LANE_THR) & ~(taken[g] & ~t.g_crowd[g, None])
        plain = cand & ~ig
        pick = np.where(np.logical_or.reduceat(plain, starts, axis=0)[seg], plain, cand)
        val = np.where(pick, v, -np.inf)
        best = np.maximum.reduceat(val, starts, axis=0)
        place = np.where(pick & (val == best[seg]), pos[g][:, _LANE_AREA], -1)
        chosen = np.maximum.reduceat(place, starts, axis=0)
        s_i, l_i = np.nonzero(chosen >= 0)
        m = at[_LANE_AREA[l_i], p.g_start[d[starts[s_i]]] + chosen[s_i, l_i]]
        dd = d[starts[s_i]]
        dtm[dd, l_i] = t.g_id[m]
        dt_ig[dd, l_i] = g_ig[m, _LANE_AREA[l_i]]
        taken[m, l_i] = True
    outside = (t.d_area[:, None] < lo) | (t.d_area[:, None] > hi)
    dt_ig |= (dtm == 0) & outside[:, _LANE_AREA]
    return dtm, dt_ig


def _accumulate(t: _Table, dtm: np.ndarray, dt_ig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """COCOeval's ``accumulate``: precision (T, R, K, A, M) and recall (T, K, A, M), -1
    where a category has nothing to find; a category's detections of all images in
    decreasing score (stable in image order), the precision envelope and its reading at the
    recall points on arrays."""
    T, R, K, A, M = len(IOU_THRS), len(REC_THRS), t.n_cat, len(AREA_RNG), len(MAX_DETS)
    lanes = len(_LANE_AREA)
    precision = -np.ones((T, R, K, A, M))
    recall = -np.ones((T, K, A, M))
    lo, hi = np.array([a for a, _ in AREA_RNG]), np.array([b for _, b in AREA_RNG])
    g_ig = t.g_ignore[:, None] | (t.g_area[:, None] < lo) | (t.g_area[:, None] > hi)
    g_cat = t.g_key // max(t.n_img, 1)
    npig = np.stack([np.bincount(g_cat[~g_ig[:, a]], minlength=K) for a in range(A)], 1)
    d_cat, d_img = t.d_key // max(t.n_img, 1), t.d_key % max(t.n_img, 1)
    order = np.lexsort((t.d_rank, d_img, -t.d_score, d_cat))
    tps = (dtm != 0) & ~dt_ig
    fps = (dtm == 0) & ~dt_ig
    cat_bounds = np.searchsorted(d_cat[order], np.arange(K + 1))
    for k in range(K):
        if not npig[k].any():
            continue
        mine = order[cat_bounds[k] : cat_bounds[k + 1]]
        n_pig = npig[k][_LANE_AREA].astype(float)
        for m, max_det in enumerate(MAX_DETS):
            sel = mine[t.d_rank[mine] < max_det]
            nd = len(sel)
            rc_last = np.zeros(lanes)
            q = np.zeros((lanes, R))
            if nd:
                tp = np.cumsum(tps[sel], axis=0).astype(float)
                fp = np.cumsum(fps[sel], axis=0).astype(float)
                with np.errstate(divide="ignore", invalid="ignore"):
                    rc = tp / n_pig
                pr = tp / (fp + tp + np.spacing(1))
                envelope = np.maximum.accumulate(pr[::-1], axis=0)[::-1]
                s = np.searchsorted(REC_THRS, rc.ravel(), side="right").reshape(nd, lanes)
                hist = np.bincount(
                    (np.arange(lanes) * (R + 1) + s).ravel(), minlength=lanes * (R + 1)
                )
                inds = np.cumsum(hist.reshape(lanes, R + 1), axis=1)[:, :R]
                q = np.where(
                    inds < nd, envelope[np.minimum(inds, nd - 1), np.arange(lanes)[:, None]], 0.0
                )
                rc_last = rc[-1]
            live = npig[k] > 0  # (A,)
            qa = q.reshape(A, T, R).transpose(1, 2, 0)
            precision[:, :, k, live, m] = qa[:, :, live]
            recall[:, k, live, m] = rc_last.reshape(A, T).T[:, live]
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


# ------------------------------------------------------------ masks, as pycocotools' C holds them


@dataclass
class _Rles:
    """Run-length masks as pycocotools' C ``RLE`` structs (h, w, runs, the address of the
    runs): uncompressed counts in :attr:`runs`, compressed ones decoded by ``rleFrString``
    into memory of its own, freed with the object."""

    structs: np.ndarray  # (n, 4) uint64
    runs: np.ndarray  # uint32: the uncompressed masks' runs, one after the other
    area: np.ndarray  # pixels set (``rleArea``)

    def __len__(self) -> int:
        return len(self.structs)


def _rles(segs: list[Any]) -> _Rles:
    """RLE segmentations, compressed or not, as pycocotools reads them (``frPyObjects``,
    ``rleFrString``), in one pass."""
    import ctypes

    c = _c_routines()
    structs = np.zeros((len(segs), 4), np.uint64)
    out = _Rles(structs, np.zeros(0, np.uint32), np.zeros(len(segs)))
    owned: list[int] = []  # rleFrString allocates their runs
    weakref.finalize(out, _free, c.rleFree, structs, owned)
    listed: list[int] = []
    lists: list[list[int]] = []
    sizes: list[tuple[int, int]] = []
    base, from_string = structs.ctypes.data, c.rleFrString
    try:
        for i, seg in enumerate(segs):
            counts, (h, w) = seg["counts"], seg["size"]
            if type(counts) is str:
                owned.append(i)
                from_string(base + 32 * i, counts.encode(), h, w)
            elif type(counts) is list:
                listed.append(i)
                lists.append(counts)
                sizes.append((h, w))
            else:
                raise _Unusual
    except (TypeError, KeyError, ValueError, ctypes.ArgumentError):
        raise _Unusual from None  # polygons, or no RLE
    lengths = np.fromiter(map(len, lists), np.int64, len(lists))
    out.runs = np.fromiter(itertools.chain.from_iterable(lists), np.uint32, int(lengths.sum()))
    structs[listed, :2] = np.array(sizes, np.uint64).reshape(-1, 2)
    structs[listed, 2] = lengths
    structs[listed, 3] = out.runs.ctypes.data + 4 * (np.cumsum(lengths) - lengths)
    area = np.zeros(len(segs), np.uint32)
    c.rleArea(base, len(segs), area.ctypes.data)
    out.area = area.astype(float)
    return out


def _free(rle_free: Any, structs: np.ndarray, owned: list[int]) -> None:
    base = structs.ctypes.data
    for i in owned:
        rle_free(base + 32 * i)


@functools.cache
def _c_routines() -> Any:
    """pycocotools' C routines on RLEs (those its ``iou``, ``area`` and ``frPyObjects``
    call), reached directly: ``rleIou``, ``rleArea``, ``rleFrString``, ``rleFree``."""
    import ctypes

    from pycocotools import _mask

    # maskApi.h's RLE is {siz h, w, m; uint *cnts} with siz an unsigned long: 32 bytes, as
    # the arrays here lay it out, only where a long is 8 bytes (not on Windows: COCOeval then).
    if ctypes.sizeof(ctypes.c_ulong) != 8 or ctypes.sizeof(ctypes.c_void_p) != 8:
        raise _Unusual
    try:
        lib = ctypes.CDLL(_mask.__file__)
        routines = {n: getattr(lib, n) for n in ("rleIou", "rleArea", "rleFrString", "rleFree")}
    except (OSError, AttributeError):
        raise _Unusual from None
    p, n = ctypes.c_void_p, ctypes.c_ulong  # siz
    signatures = {
        "rleIou": [p, p, n, n, p, p],
        "rleArea": [p, n, p],
        "rleFrString": [p, ctypes.c_char_p, n, n],
        "rleFree": [p],
    }
    for name, fn in routines.items():
        fn.argtypes, fn.restype = signatures[name], None
    return types.SimpleNamespace(**routines)
