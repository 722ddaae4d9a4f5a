"""Writes ``coco_results.json`` beside this file: 2D detection and segmentation results on
the sample's BOP export (as ``make_bop24_results.py``), made to exercise BOP's COCO scores.

Per true instance, maybe a result: its box moved and resized by up to 30 %, with the visible
mask or the whole silhouette as its mask; false boxes with rectangular masks; ties in
scores; a result of an image and of a scene that are not targets. Deterministic (seed 22)::

    python tests/data/make_coco_results.py EXPORT
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
from pycocotools import mask as coco_mask


def _rle(mask: np.ndarray) -> dict:
    code = coco_mask.encode(np.asfortranarray(mask.astype(np.uint8)))
    return {"counts": code["counts"].decode("ascii"), "size": [int(s) for s in code["size"]]}


def main(export: Path) -> None:
    rng = np.random.default_rng(22)
    out = []
    for scene in range(4):
        folder = export / "test" / f"{scene:06d}"
        coco = json.loads((folder / "scene_gt_coco.json").read_text())
        h, w = coco["images"][0]["height"], coco["images"][0]["width"]

        def add(
            cat: int, box: list[float], mask: np.ndarray, image: int = 0, scene: int = scene
        ) -> None:
            score = round(float(rng.uniform(0.05, 1.0)), 2)
            out.append(
                {"scene_id": scene, "image_id": image, "category_id": cat, "score": score,
                 "bbox": [round(v, 2) for v in box], "segmentation": _rle(mask), "time": 0.5 + 0.1 * scene}
            )  # fmt: skip

        for k, ann in enumerate(coco["annotations"]):
            if rng.random() < 0.2:
                continue
            x, y, bw, bh = ann["bbox"]
            jitter = rng.uniform(-0.3, 0.3, 4) * rng.uniform(0, 1)
            box = [
                x + jitter[0] * bw,
                y + jitter[1] * bh,
                bw * (1 + jitter[2]),
                bh * (1 + jitter[3]),
            ]
            which = "mask_visib" if rng.random() < 0.5 else "mask"
            mask = cv2.imread(str(folder / which / f"000000_{k:06d}.png"), 0) > 0
            add(int(ann["category_id"]), box, mask)
        for _ in range(3):
            x0, y0 = rng.uniform(0, w - 200), rng.uniform(0, h - 200)
            bw, bh = rng.uniform(40, 200, 2)
            mask = np.zeros((h, w), bool)
            mask[int(y0) : int(y0 + bh), int(x0) : int(x0 + bw)] = True
            add(int(rng.integers(1, 4)), [x0, y0, bw, bh], mask)
        add(1, [10.0, 10.0, 50.0, 50.0], np.ones((h, w), bool), image=5)  # not a target image
    out.append(dict(out[0], scene_id=9))  # not a target scene
    (Path(__file__).parent / "coco_results.json").write_text(json.dumps(out))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
