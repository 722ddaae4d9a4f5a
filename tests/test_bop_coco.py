"""BOP's 2D detection and segmentation scores (COCO's AP and AR) against bop_toolkit's own
numbers on the sample's BOP export, and results that are the ground truth itself."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_bop24 import LOW_VISIBILITY

pytestmark = pytest.mark.slow  # a BOP export of sample_scenes made first

DATA = Path(__file__).parent / "data"

#: bop_toolkit's scripts/eval_bop22_coco.py (commit cea62d6, with BOP's fork of pycocotools
#: that keeps the ``ignore`` flag, ``--targets_filename test_targets_bop24.json``) on the
#: sample's export (as tests/test_bop24.py) with tests/data/coco_results.json (made by
#: tests/data/make_coco_results.py): its scores_bop22_coco_<type>.json.
BOP_TOOLKIT = {
    "bbox": {"AP": 0.18271590254263517, "AP50": 0.44104481876759105,
             "AP75": 0.0896956362302897, "AP_large": 0.18948032898527947,
             "AR1": 0.08523809523809524, "AR10": 0.30341269841269836,
             "AR100": 0.30341269841269836, "AP_small": -1.0,
             "average_time_per_image": 0.6333333333333333},
    "segm": {"AP": 0.5444032974726044, "AP50": 0.6011697598331261,
             "AP75": 0.5392671409998143, "AP_large": 0.5657422885145656,
             "AR1": 0.24007936507936511, "AR10": 0.6827777777777778,
             "AR100": 0.6827777777777778, "AP_small": -1.0,
             "average_time_per_image": 0.6333333333333333},
}  # fmt: skip
#: The same with the instances of test_bop24.LOW_VISIBILITY flagged ``ignore`` (less than
#: 10 % visible) in scene_gt_coco.json.
BOP_TOOLKIT_LOW_VISIBILITY = {
    "bbox": {"AP": 0.17268048233394767, "AP50": 0.42590759075907597,
             "AP75": 0.07628477133427627, "AP_large": 0.17948125581788948,
             "AR1": 0.09025252525252524, "AR10": 0.29287878787878785},
    "segm": {"AP": 0.5443869386938693, "AP50": 0.5937018701870187,
             "AP75": 0.5498774877487749, "AP_large": 0.566935264955067,
             "AR1": 0.25176767676767675, "AR10": 0.6943939393939395},
}  # fmt: skip


@pytest.fixture(scope="module")
def export(bop_export: Path) -> Path:
    return bop_export


def _scores(data: Path, results: Path, tmp_path: Path) -> dict:
    report = tmp_path / "report.json"
    run = subprocess.run(
        [sys.executable, "-m", "annotator", "evaluate", str(data), "--coco-results"]
        + [str(results), "--json", str(report)],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr
    assert "2D detection (boxes)" in run.stdout and "2D segmentation (masks)" in run.stdout
    return json.loads(report.read_text())


def test_same_numbers_as_bop_toolkit(export: Path, tmp_path: Path) -> None:
    got = _scores(export, DATA / "coco_results.json", tmp_path)
    for kind, want in BOP_TOOLKIT.items():
        for key, value in want.items():
            assert got[f"bop22_coco_{kind}"][key] == pytest.approx(value, abs=1e-12), (kind, key)


def test_ignored_instances_as_bop_toolkit(export: Path, tmp_path: Path) -> None:
    """Instances flagged ``ignore`` are neither found nor missed (published pycocotools would
    count them: the numbers would be those of the export as it is)."""
    import shutil

    data = tmp_path / "lv"
    shutil.copytree(export, data)
    for scene, entries in LOW_VISIBILITY.items():
        file = data / "test" / f"{scene:06d}" / "scene_gt_coco.json"
        doc = json.loads(file.read_text())
        for ann in doc["annotations"]:
            ann["ignore"] = ann["ignore"] or ann["id"] - 1 in entries
        file.write_text(json.dumps(doc))
    got = _scores(data, DATA / "coco_results.json", tmp_path)
    for kind, want in BOP_TOOLKIT_LOW_VISIBILITY.items():
        for key, value in want.items():
            assert got[f"bop22_coco_{kind}"][key] == pytest.approx(value, abs=1e-12), (kind, key)


def test_ground_truth_as_results_scores_one(export: Path, tmp_path: Path) -> None:
    results = []
    for scene in range(4):
        doc = json.loads((export / "test" / f"{scene:06d}" / "scene_gt_coco.json").read_text())
        for ann in doc["annotations"]:
            results.append(
                {"scene_id": scene, "image_id": ann["image_id"], "category_id":
                 ann["category_id"], "score": 1.0, "bbox": ann["bbox"],
                 "segmentation": ann["segmentation"]}
            )  # fmt: skip
    file = tmp_path / "perfect.json"
    file.write_text(json.dumps(results))
    got = _scores(export, file, tmp_path)
    for kind in ("bbox", "segm"):
        assert got[f"bop22_coco_{kind}"]["AP"] == pytest.approx(1.0)
        assert got[f"bop22_coco_{kind}"]["average_time_per_image"] == -1.0


def test_bad_results_file_is_one_line(export: Path, tmp_path: Path) -> None:
    file = tmp_path / "bad.json"
    file.write_text(json.dumps([{"scene_id": 0, "image_id": "0", "category_id": 1}]))
    run = subprocess.run(
        [sys.executable, "-m", "annotator", "evaluate", str(export), "--coco-results", str(file)],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 2
    assert len(run.stderr.strip().splitlines()) == 1 and "bad.json" in run.stderr


def test_estimate_writes_coco_results_bop_reads(export: Path, sample: Path, tmp_path: Path) -> None:
    """``annotator estimate``'s COCO results of the true poses: the silhouettes' boxes are
    BOP's (amodal) true boxes, AP 1."""

    import annotator
    from annotator.estimation.results import ResultRow, coco_path, coco_results
    from annotator.export.undistort import pinhole_rig

    ds = annotator.load_dataset(sample)
    rows = []
    for scene in range(4):
        for g in json.loads((export / "test" / f"{scene:06d}" / "scene_gt.json").read_text())["0"]:
            T = np.eye(4)
            T[:3, :3] = np.reshape(g["cam_R_m2c"], (3, 3))
            T[:3, 3] = g["cam_t_m2c"]
            rows.append(ResultRow(str(scene), g["obj_id"], 0.9, T, 1.5))
    cam = pinhole_rig(ds.rig).cameras[0]
    meshes = [ds.objects[name].mesh for name in ds.objects]
    file = coco_path(tmp_path / "mine_annot-test.csv")
    assert file.name == "mine_annot-test.json"
    file.write_text(json.dumps(coco_results(rows, meshes, cam.K, cam.width, cam.height)))
    got = _scores(export, file, tmp_path)
    assert got["bop22_coco_bbox"]["AP"] == pytest.approx(1.0)
    assert got["bop22_coco_bbox"]["average_time_per_image"] == 1.5


def _reference(doc: dict, results: list, iou_type: str) -> np.ndarray:
    """pycocotools' COCOeval made to keep ``ignore`` as BOP's fork does."""
    import contextlib
    import io

    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    class ForkEval(COCOeval):
        def _prepare(self) -> None:
            keep = {a["id"]: a.get("ignore", 0) for a in self.cocoGt.dataset["annotations"]}
            super()._prepare()
            for gts in self._gts.values():
                for g in gts:
                    g["ignore"] = keep[g["id"]]

    with contextlib.redirect_stdout(io.StringIO()):
        gt = COCO()
        gt.dataset = json.loads(json.dumps(doc))
        gt.createIndex()
        ev = ForkEval(gt, gt.loadRes(json.loads(json.dumps(results))), iou_type)
        ev.params.imgIds = sorted(gt.getImgIds())
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    return np.asarray(ev.stats)


@pytest.mark.parametrize("seed", range(6))
def test_same_stats_as_cocoeval(seed: int) -> None:
    """coco_stats against pycocotools' own COCOeval, made to keep ``ignore`` as BOP's fork
    does, on random boxes: several categories, every area range, tied scores, ignored and
    crowd instances, images without detections or without instances, more than 100
    detections in an image."""

    from annotator.evaluation.coco import coco_stats

    rng = np.random.default_rng(seed)
    images = [{"id": i, "width": 640, "height": 480} for i in range(12)]
    anns, results = [], []
    for img in range(12):
        for _ in range(int(rng.integers(0, 8)) if img != 3 else 0):
            w, h = rng.uniform(5, 200, 2)
            box = [float(rng.uniform(0, 400)), float(rng.uniform(0, 300)), float(w), float(h)]
            anns.append({"id": len(anns) + 1, "image_id": img, "category_id": int(rng.integers(1, 4)),
                         "bbox": box, "area": float(w * h * rng.uniform(0.3, 1)),
                         "iscrowd": int(rng.random() < 0.05), "ignore": bool(rng.random() < 0.15)})  # fmt: skip
            for _ in range(int(rng.integers(0, 4))):
                j = rng.normal(scale=0.2, size=4)
                results.append({"image_id": img, "category_id": anns[-1]["category_id"],
                                "bbox": [box[0] + j[0] * w, box[1] + j[1] * h, w * (1 + j[2]),
                                         h * (1 + j[3])],
                                "score": round(float(rng.uniform()), 1)})  # fmt: skip
        for _ in range(int(rng.integers(0, 5)) if img != 5 else 130):
            results.append({"image_id": img, "category_id": int(rng.integers(1, 4)),
                            "bbox": [float(v) for v in rng.uniform(0, 300, 2)]
                            + [float(v) for v in rng.uniform(5, 150, 2)],
                            "score": round(float(rng.uniform()), 1)})  # fmt: skip
    doc = {"images": images, "annotations": anns,
           "categories": [{"id": c, "name": str(c)} for c in (1, 2, 3)]}  # fmt: skip
    assert np.array_equal(coco_stats(doc, results, "bbox"), _reference(doc, results, "bbox"))


def _uncompressed(mask: np.ndarray) -> dict:
    """A mask's uncompressed RLE, as bop_toolkit's calc_gt_coco.py writes it."""

    flat = np.asfortranarray(mask).ravel(order="F").astype(np.int8)
    edges = np.flatnonzero(np.diff(np.r_[0, flat, 0])) if flat.any() else np.array([], int)
    counts = np.diff(np.r_[0, edges, flat.size]).tolist()
    return {"counts": counts, "size": list(mask.shape)}


def test_large_case_same_stats_as_cocoeval() -> None:
    """Hundreds of images with boxes and masks (uncompressed true masks, compressed results),
    many instances a category and image, ignored ones, an instance of id 0, a category
    without results and results of a category without instances: every stat of boxes and
    masks exactly as COCOeval's."""
    from pycocotools import mask as coco_mask

    from annotator.evaluation.coco import coco_stats

    rng = np.random.default_rng(7)
    w, h = 160, 120
    yy, xx = np.mgrid[:h, :w]

    def blob(cx: float, cy: float, ax: float, ay: float) -> tuple[np.ndarray, list[float]]:
        mask = ((xx + 0.5 - cx) / ax) ** 2 + ((yy + 0.5 - cy) / ay) ** 2 <= 1
        if not mask.any():
            mask[int(np.clip(cy, 0, h - 1)), int(np.clip(cx, 0, w - 1))] = True
        ys, xs = np.nonzero(mask)
        return mask, [
            float(xs.min()),
            float(ys.min()),
            float(np.ptp(xs) + 1),
            float(np.ptp(ys) + 1),
        ]

    images = [{"id": i, "width": w, "height": h} for i in range(300)]
    anns: list[dict] = []
    results: list[dict] = []
    for img in range(300):
        for _ in range(int(rng.integers(0, 12))):
            cat = int(rng.integers(1, 5))
            cx, cy, ax, ay = rng.uniform(0, w), rng.uniform(0, h), *rng.uniform(2, 60, 2)
            mask, box = blob(cx, cy, ax, ay)
            anns.append({"id": len(anns), "image_id": img, "category_id": cat, "iscrowd": 0,
                         "area": int(mask.sum()), "bbox": box, "segmentation": _uncompressed(mask),
                         "ignore": bool(rng.random() < 0.1)})  # fmt: skip
            for _ in range(int(rng.choice([0, 1, 1, 2]))):
                j = rng.normal(scale=0.15, size=4)
                dmask, dbox = blob(cx + j[0] * ax, cy + j[1] * ay, ax * (1 + j[2]), ay * (1 + j[3]))
                rle = coco_mask.encode(np.asfortranarray(dmask.astype(np.uint8)))
                results.append({"image_id": img, "category_id": cat, "bbox": dbox,
                                "segmentation": {"counts": rle["counts"].decode(), "size": [h, w]},
                                "score": round(float(rng.uniform()), 2)})  # fmt: skip
        for _ in range(int(rng.integers(0, 4))):
            dmask, dbox = blob(rng.uniform(0, w), rng.uniform(0, h), *rng.uniform(2, 60, 2))
            rle = coco_mask.encode(np.asfortranarray(dmask.astype(np.uint8)))
            results.append({"image_id": img, "category_id": int(rng.integers(1, 6)), "bbox": dbox,
                            "segmentation": {"counts": rle["counts"].decode(), "size": [h, w]},
                            "score": round(float(rng.uniform()), 2)})  # fmt: skip
    cats = [{"id": c, "name": str(c)} for c in (1, 2, 3, 4, 7)]
    doc = {"images": images, "annotations": anns, "categories": cats}
    for iou_type in ("bbox", "segm"):
        want = _reference(doc, results, iou_type)
        assert np.array_equal(coco_stats(doc, results, iou_type), want), iou_type
    masks_only = [{k: v for k, v in r.items() if k != "bbox"} for r in results]  # masks' areas
    assert np.array_equal(coco_stats(doc, masks_only, "segm"), _reference(doc, masks_only, "segm"))


def test_what_arrays_do_not_model_goes_to_cocoeval() -> None:
    """Polygon masks and repeated annotation ids are left to pycocotools' COCOeval."""
    from annotator.evaluation.coco import coco_stats

    images = [{"id": i, "width": 100, "height": 80} for i in range(3)]
    square = [[10.0, 10.0, 40.0, 10.0, 40.0, 50.0, 10.0, 50.0]]
    anns = [{"id": 1 + (i > 2), "image_id": i % 3, "category_id": 1, "iscrowd": 0,
             "area": 1200.0, "bbox": [10.0, 10.0, 30.0, 40.0], "segmentation": square}
            for i in range(5)]  # fmt: skip
    results = [{"image_id": i, "category_id": 1, "score": 0.5 + 0.1 * i,
                "bbox": [12.0, 9.0, 30.0, 40.0 - i]} for i in range(3)]  # fmt: skip
    doc = {"images": images, "annotations": anns, "categories": [{"id": 1, "name": "1"}]}
    assert np.array_equal(coco_stats(doc, results, "bbox"), _reference(doc, results, "bbox"))
    segm = [{**r, "segmentation": square} for r in results]
    unique = {**doc, "annotations": [{**a, "id": i} for i, a in enumerate(anns)]}
    assert np.array_equal(coco_stats(unique, segm, "segm"), _reference(unique, segm, "segm"))
