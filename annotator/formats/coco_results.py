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

from annotator.errors import UserError
from annotator.formats.bop import evaluated_sensor
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
    return doc


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
    doc = read_json(file)
    if not isinstance(doc, list):
        raise UserError("expected a list of {scene_id, im_id, ...}", path=file)
    images: dict[int, set[int]] = {}
    for i, e in enumerate(doc):
        try:
            images.setdefault(int(e["scene_id"]), set()).add(int(e["im_id"]))
        except (KeyError, TypeError, ValueError):
            raise UserError(f"entry {i}: needs integer scene_id and im_id", path=file) from None
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
        scenes.append((scene_id, gt))
    return CocoGroundTruth(scenes, images, file.name)
