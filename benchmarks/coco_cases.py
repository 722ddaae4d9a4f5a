"""Generated BOP 2D detection cases at a real test set's size: a BOP folder whose scenes'
``scene_gt_coco.json`` hold elliptic instances (boxes, uncompressed RLE masks as
bop_toolkit's ``calc_gt_coco.py`` writes them, some flagged ``ignore``) and a COCO results
file with boxes and compressed RLE masks (found instances moved and resized, doubles, false
detections), deterministic for a seed.

    .venv/bin/python -m benchmarks.coco_cases OUT --images 2000
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

#: Image size (BOP's classic sensors) and images per scene.
WIDTH, HEIGHT = 640, 480
PER_SCENE = 50


def ellipse_rle(cx: float, cy: float, ax: float, ay: float) -> tuple[list[int], list[float], int]:
    """The column-major uncompressed RLE counts of an ellipse inside the image, its box and
    its area in pixels."""
    xs = np.arange(max(0, int(cx - ax)), min(WIDTH, int(cx + ax) + 1))
    half = ay * np.sqrt(np.clip(1 - ((xs + 0.5 - cx) / ax) ** 2, 0, None))
    top = np.clip(np.round(cy - half), 1, HEIGHT - 1).astype(np.int64)
    bottom = np.clip(np.round(cy + half), 1, HEIGHT - 1).astype(np.int64)
    keep = bottom > top
    xs, top, bottom = xs[keep], top[keep], bottom[keep]
    if not len(xs):
        xs, top, bottom = np.array([int(cx)]), np.array([int(cy)]), np.array([int(cy) + 1])
    starts, ends = xs * HEIGHT + top, xs * HEIGHT + bottom
    edges = np.empty(2 * len(xs) + 2, np.int64)
    edges[0], edges[1:-1:2], edges[2:-1:2], edges[-1] = 0, starts, ends, WIDTH * HEIGHT
    counts = np.diff(edges).tolist()
    box = [
        float(xs[0]),
        float(top.min()),
        float(xs[-1] + 1 - xs[0]),
        float(bottom.max() - top.min()),
    ]
    return counts, box, int((ends - starts).sum())


def make_case(
    out: Path, images: int, per_image: int = 20, categories: int = 8, seed: int = 0
) -> Path:
    """A BOP folder in ``out`` with ``images`` target images of ``per_image`` instances each;
    returns its results file (``mine_annotbig-test.json``)."""
    from pycocotools import mask as coco_mask

    rng = np.random.default_rng(seed)
    (out / "models").mkdir(parents=True, exist_ok=True)
    (out / "models" / "models_info.json").write_text(
        json.dumps({str(c): {"diameter": 100.0} for c in range(1, categories + 1)})
    )
    cats = [
        {"id": c, "name": str(c), "supercategory": "annotbig"} for c in range(1, categories + 1)
    ]
    targets: list[dict[str, int]] = []
    results: list[dict[str, Any]] = []

    def result(
        scene: int, image: int, cat: int, cx: float, cy: float, ax: float, ay: float
    ) -> None:
        counts, box, _ = ellipse_rle(cx, cy, ax, ay)
        rle = coco_mask.frPyObjects({"counts": counts, "size": [HEIGHT, WIDTH]}, HEIGHT, WIDTH)
        results.append(
            {"scene_id": scene, "image_id": image, "category_id": cat,
             "score": round(float(rng.uniform(0.05, 1)), 3), "bbox": box,
             "segmentation": {"counts": rle["counts"].decode("ascii"), "size": [HEIGHT, WIDTH]},
             "time": 0.25}
        )  # fmt: skip

    for scene in range((images + PER_SCENE - 1) // PER_SCENE):
        folder = out / "test" / f"{scene:06d}"
        folder.mkdir(parents=True, exist_ok=True)
        doc: dict[str, Any] = {
            "info": {},
            "licenses": [],
            "categories": cats,
            "images": [],
            "annotations": [],
        }
        for image in range(min(PER_SCENE, images - scene * PER_SCENE)):
            targets.append({"scene_id": scene, "im_id": image})
            doc["images"].append(
                {"id": image, "file_name": f"rgb/{image:06d}.png", "width": WIDTH, "height": HEIGHT}
            )
            for _ in range(per_image):
                cat = int(rng.integers(1, categories + 1))
                ax, ay = rng.uniform(6, 90, 2)
                cx, cy = rng.uniform(ax / 2, WIDTH - ax / 2), rng.uniform(ay / 2, HEIGHT - ay / 2)
                counts, box, area = ellipse_rle(cx, cy, ax, ay)
                doc["annotations"].append(
                    {"id": len(doc["annotations"]), "image_id": image, "category_id": cat,
                     "iscrowd": 0, "area": area, "bbox": box,
                     "segmentation": {"counts": counts, "size": [HEIGHT, WIDTH]},
                     "width": WIDTH, "height": HEIGHT, "ignore": bool(rng.random() < 0.1)}
                )  # fmt: skip
                for _ in range(int(rng.choice([0, 1, 1, 1, 2]))):
                    j = rng.normal(scale=0.12, size=4)
                    result(scene, image, cat, cx + j[0] * ax, cy + j[1] * ay,
                           ax * (1 + j[2]), ay * (1 + j[3]))  # fmt: skip
            for _ in range(per_image // 4):
                ax, ay = rng.uniform(6, 90, 2)
                result(scene, image, int(rng.integers(1, categories + 1)),
                       rng.uniform(ax / 2, WIDTH - ax / 2), rng.uniform(ay / 2, HEIGHT - ay / 2), ax, ay)  # fmt: skip
        (folder / "scene_gt.json").write_text("{}")
        (folder / "scene_gt_coco.json").write_text(json.dumps(doc))
    (out / "test_targets_bop24.json").write_text(json.dumps(targets))
    file = out / "mine_annotbig-test.json"
    file.write_text(json.dumps(results))
    return file


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--images", type=int, default=500)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    print(make_case(args.out, args.images, seed=args.seed))


if __name__ == "__main__":
    main()
