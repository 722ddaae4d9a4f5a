"""BOP's 2D detection and segmentation files: COCO results and a dataset's COCO ground truth.

Results (BOP Challenge 2022 on, ``METHOD_DATASET-SPLIT.json``): a JSON list of
``{"scene_id", "image_id", "category_id", "score", "bbox": [x, y, w, h], "segmentation":
{"size": [h, w], "counts": RLE}, "time"}`` (``bbox`` for detection, ``segmentation`` for
segmentation; ``time`` in seconds, the same for every result of an image), checked as
bop_toolkit's ``inout.check_coco_results`` checks them. The ground truth is each scene's
``scene_gt_coco[_<sensor>].json`` (the sensor :func:`annotator.formats.bop.evaluated_sensor`
picks), over the images of the targets file.
"""

from __future__ import annotations

import contextlib
import functools
import gc
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from annotator.errors import UserError
from annotator.formats.bop import evaluated_sensor, non_empty, target_ids
from annotator.formats.coco_rle import rle_problems
from annotator.io.documents import read_json

#: What COCO results are scored on: bounding boxes or segmentation masks.
ANN_TYPES = ("bbox", "segm")
#: The targets files whose images are scored, the first found (bop_toolkit's
#: ``eval_bop22_coco.py`` takes one by name; BOP 2024's 2D detection uses the first).
TARGET_FILES = ("test_targets_bop24.json", "test_targets_bop19.json")


@contextlib.contextmanager
def paused_gc() -> Iterator[None]:
    """Python's cyclic garbage collector paused: the documents read and scored here hold
    millions of objects and no cycles, and collecting while they are built costs more than
    building them."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def read_coco_results(path: Path, ann_type: str) -> list[dict[str, Any]]:
    """The results of a COCO result file, checked for ``ann_type`` (``bbox`` or ``segm``);
    the first bad entry is named. The file is parsed once while it is unchanged: a second
    call returns the same list (to read, not to change)."""
    if path.is_dir() or not path.exists():
        raise UserError("expected a COCO results file (JSON list)", path=path)
    doc = _parsed(path.resolve(), path.stat().st_mtime_ns, path.stat().st_size)
    if not isinstance(doc, list) or not doc:
        raise UserError("expected a non-empty JSON list of COCO results", path=path)
    key = "bbox" if ann_type == "bbox" else "segmentation"
    kind = list if ann_type == "bbox" else dict
    for i, r in enumerate(doc):  # the common case at a glance; _problem words the rest
        if (
            type(r) is not dict
            or type(r.get("scene_id")) is not int
            or type(r.get("image_id")) is not int
            or type(r.get("category_id")) is not int
            or type(r.get("score")) not in (float, int)
            or type(r.get(key)) is not kind
            or (kind is dict and not {"counts", "size"} <= r[key].keys())
            or type(r.get("time", 0.0)) not in (float, int)
        ):
            problem = _problem(r, ann_type)
            if problem:
                raise UserError(f"result {i}: {problem}", path=path)
    _check_values(doc, ann_type, path)
    return doc


def _check_values(doc: list[dict[str, Any]], ann_type: str, path: Path) -> None:
    """Refuse (naming the first bad result) numbers no detector gives: NaN or infinite
    scores and times, negative times but BOP's -1 (unknown), negative ids, boxes of
    negative size, masks whose size or runs do not make an image (:mod:`.coco_rle`)."""

    def first(bad: Any, what: str) -> None:
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise UserError(f"result {i}: {what}", path=path)

    scores = np.array([r["score"] for r in doc], np.float64)
    first(~np.isfinite(scores), "'score' is not a finite number")
    times = np.array([r.get("time", -1) for r in doc], np.float64)
    first(~np.isfinite(times), "'time' is not a finite number")
    first((times < 0) & (times != -1), "'time' is negative (seconds, or -1 when unknown)")
    for key in ("scene_id", "image_id", "category_id"):
        first(np.array([r[key] for r in doc], np.int64) < 0, f"'{key}' is negative")
    if ann_type == "bbox":
        boxes = [r["bbox"] for r in doc]
        first(np.array([len(b) != 4 for b in boxes]), "'bbox' must be [x, y, width, height]")
        try:
            box = np.array(boxes, np.float64).reshape(-1, 4)
        except (TypeError, ValueError):
            box = np.full((len(boxes), 4), np.nan)
        first(~np.isfinite(box).all(axis=1), "'bbox' holds something that is not a number")
        first((box[:, 2] < 0) | (box[:, 3] < 0), "'bbox' has a negative width or height")
        return
    sizes = [r["segmentation"]["size"] for r in doc]
    good = np.array(
        [
            type(s) is list and len(s) == 2 and all(type(v) is int and v > 0 for v in s)
            for s in sizes
        ]
    )
    first(~good, "segmentation 'size' must be [height, width], two positive integers")
    problems = rle_problems([r["segmentation"]["counts"] for r in doc], [tuple(s) for s in sizes])
    if problems:
        i, why = next(iter(problems.items()))
        more = f" ({len(problems) - 1} more results alike)" if len(problems) > 1 else ""
        raise UserError(f"result {i}: segmentation: {why}{more}", path=path)


def _check_true_masks(doc: dict[str, Any], path: Path) -> None:
    """Refuse (naming the first) a ground-truth mask that is no mask: it would reach
    pycocotools' C routines as the results' do."""
    segs, sizes, where = [], [], []
    for i, a in enumerate(doc["annotations"]):
        seg = a.get("segmentation") if isinstance(a, dict) else None
        if not isinstance(seg, dict):
            continue  # polygons or none: COCOeval's own reading
        size = seg.get("size")
        if not (
            type(size) is list and len(size) == 2 and all(type(v) is int and v > 0 for v in size)
        ):
            raise UserError(
                f"annotation {i}: segmentation 'size' must be [height, width]", path=path
            )
        segs.append(seg.get("counts"))
        sizes.append((size[0], size[1]))
        where.append(i)
    problems = rle_problems(segs, sizes)
    if problems:
        k, why = next(iter(problems.items()))
        raise UserError(f"annotation {where[k]}: segmentation: {why}", path=path)


def check_against_images(
    results: list[dict[str, Any]], gt: CocoGroundTruth, path: Path, ann_type: str
) -> list[str]:
    """Refuse masks whose size is not their image's (one line naming the first); and say
    (notes) how many results are of images that are not targets, or of scenes the dataset
    does not have: bop_toolkit leaves them out unscored, silently."""
    sizes = {
        (scene_id, im["id"]): (im.get("height"), im.get("width"))
        for scene_id, doc in gt.scenes
        for im in doc["images"]
    }
    scenes = {scene_id for scene_id, _ in gt.scenes}
    unknown_scene: set[int] = set()
    untargeted = 0
    for i, r in enumerate(results):
        key = (r["scene_id"], r["image_id"])
        if r["scene_id"] not in scenes:
            unknown_scene.add(r["scene_id"])
            continue
        if r["image_id"] not in gt.images[r["scene_id"]] or key not in sizes:
            untargeted += 1
            continue
        if ann_type == "segm":
            h, w = r["segmentation"]["size"]
            ih, iw = sizes[key]
            if ih is not None and iw is not None and (h, w) != (ih, iw):
                raise UserError(
                    f"result {i}: its mask is {w}x{h} but image {r['image_id']} of scene "
                    f"{r['scene_id']} is {iw}x{ih}",
                    path=path,
                )
    notes = []
    if unknown_scene:
        listed = ", ".join(map(str, sorted(unknown_scene)[:5]))
        n = sum(r["scene_id"] in unknown_scene for r in results)
        notes.append(f"{n} results of scenes the targets do not list ({listed}): not scored")
    if untargeted:
        notes.append(f"{untargeted} results of images that are not targets: not scored")
    return notes


def coco_result_kinds(path: Path) -> list[str]:
    """What a COCO result file can be scored on (of :data:`ANN_TYPES`): ``bbox`` if every
    result has a box, ``segm`` if every one has a segmentation; none for a file that is not
    a non-empty list (:func:`read_coco_results` says what is wrong with it). It parses the
    file as :func:`read_coco_results` does, once for both."""
    if not path.is_file():
        return []
    doc = _parsed(path.resolve(), path.stat().st_mtime_ns, path.stat().st_size)
    if not isinstance(doc, list) or not doc:
        return []
    has = {"bbox": "bbox", "segm": "segmentation"}
    return [t for t in ANN_TYPES if all(isinstance(r, dict) and has[t] in r for r in doc)]


@functools.lru_cache(maxsize=1)
@paused_gc()
def _parsed(path: Path, mtime_ns: int, size: int) -> Any:
    return read_json(path)


def _problem(r: Any, ann_type: str) -> str | None:
    if not isinstance(r, dict):
        return "expected an object"
    for key in ("scene_id", "image_id", "category_id"):
        if not isinstance(r.get(key), int) or isinstance(r.get(key), bool):
            return f"'{key}' must be an integer"
    if not isinstance(r.get("score"), (int, float)) or isinstance(r.get("score"), bool):
        return "'score' must be a number"
    if ann_type == "bbox" and not isinstance(r.get("bbox"), list):
        return "'bbox' must be a list [x, y, width, height] (2D detection)"
    if ann_type == "segm":
        seg = r.get("segmentation")
        if not isinstance(seg, dict) or "counts" not in seg or "size" not in seg:
            return "'segmentation' must be an RLE {size, counts} (2D segmentation)"
    if "time" in r and not isinstance(r["time"], (int, float)):
        return "'time' must be a number of seconds"
    return None


@dataclass
class CocoGroundTruth:
    """A BOP dataset's COCO ground truth, as bop_toolkit's ``eval_bop22_coco.py`` gathers it.

    Attributes:
        scenes: (scene id, its scene_gt_coco document) in the targets file's order of scenes.
        images: scene id -> the image ids to score.
        targets_file: The targets file read.
    """

    scenes: list[tuple[int, dict[str, Any]]]
    images: dict[int, set[int]]
    targets_file: str

    @functools.cached_property
    def merged(self) -> tuple[dict[str, Any], dict[int, int]]:
        """The target images of every scene and their instances in one COCO document, as
        bop_toolkit merges them (``pycoco_utils.merge_coco_annotations``): scene after scene,
        each scene's image ids shifted past the largest so far, and its annotation ids past
        the largest annotation id so far; and each scene's shift of image ids. The scenes'
        documents are not changed (the merged one shares what is not shifted)."""
        merged: dict[str, Any] = {}
        offsets: dict[int, int] = {}
        last_image = last_ann = -1
        for i, (scene_id, doc) in enumerate(self.scenes):
            targets = self.images[scene_id]
            images = [im for im in doc["images"] if im["id"] in targets]
            anns = [a for a in doc["annotations"] if a["image_id"] in targets]
            first = 0
            if i == 0:
                offsets[scene_id] = 0
                merged = {**doc, "images": images, "annotations": anns}
                merged["categories"] = list(doc["categories"])
            else:
                offset = offsets[scene_id] = last_image + 1
                for cat in doc["categories"]:
                    if cat not in merged["categories"]:
                        merged["categories"].append(cat)
                first = last_ann + 1 if merged["annotations"] else 0
                merged["images"] += [{**im, "id": im["id"] + offset} for im in images]
                merged["annotations"] += [
                    {**a, "id": a["id"] + first, "image_id": a["image_id"] + offset} for a in anns
                ]
            last_image = max([im["id"] + offsets[scene_id] for im in images] + [last_image])
            last_ann = max([a["id"] + first for a in anns] + [last_ann])
        return merged, offsets


@paused_gc()
def read_coco_ground_truth(path: Path) -> CocoGroundTruth:
    """Each target scene's ``scene_gt_coco`` document and its target images."""
    file = next((path / n for n in TARGET_FILES if (path / n).is_file()), None)
    if file is None:
        raise UserError(f"no {' or '.join(TARGET_FILES)} to say which images to score", path=path)
    doc = non_empty(read_json(file), file, "{scene_id, im_id, ...}")
    images: dict[int, set[int]] = {}
    for i, e in enumerate(doc):
        scene_id, im_id = target_ids(e, ("scene_id", "im_id"), i, file)
        images.setdefault(scene_id, set()).add(im_id)
    split = path / "test"
    scenes = []
    for scene_id in images:
        folder = split / f"{scene_id:06d}"
        coco = folder / f"scene_gt_coco{evaluated_sensor(folder)}.json"
        if not coco.is_file():
            raise UserError(
                "missing: 2D detection needs each scene's COCO ground truth (bop_toolkit's "
                "calc_gt_coco.py; `annotator export --format bop` writes it)",
                path=coco,
            )
        gt = read_json(coco)
        if not isinstance(gt, dict) or not {"images", "annotations", "categories"} <= set(gt):
            raise UserError("expected a COCO document {images, annotations, categories}", path=coco)
        _check_true_masks(gt, coco)
        scenes.append((scene_id, gt))
    return CocoGroundTruth(scenes, images, file.name)
