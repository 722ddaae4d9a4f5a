"""Hypotheses as BOP's results CSV, which ``annotator evaluate DATASET --results FILE`` reads.

One line per hypothesis, ``scene_id,im_id,obj_id,score,R,t,time`` with the header line:
``scene_id`` our scene folder (a number for the usual ``000012``-style names, which BOP
requires), ``im_id`` 0 (one image per scene), ``obj_id`` the object's number in dataset.yaml's
order from 1 (as ``annotator export --format bop`` numbers them), ``R`` nine row-major numbers
and ``t`` three (mm, model to the reference camera) separated by spaces, ``time`` the seconds
the scene took (the same on every line of a scene, as BOP asks).

Beside it, the same hypotheses as BOP's COCO results for 2D detection and segmentation
(:func:`coco_results`, read by ``annotator evaluate BOP --coco-results``): per hypothesis its
``scene_id``, ``image_id`` 0, ``category_id`` (the object's number), ``score``, the
silhouette's box ``bbox`` ``[x, y, width, height]`` and ``segmentation`` (its mask as COCO's
compressed RLE) in the reference camera without distortion (the images ``annotator export
--format bop`` writes), and ``time``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from annotator.estimation.estimator import Hypothesis
from annotator.geometry.mesh import Mesh

HEADER = "scene_id,im_id,obj_id,score,R,t,time"


@dataclass(frozen=True)
class ResultRow:
    """One line of the CSV."""

    scene_id: str
    obj_id: int
    score: float
    pose: np.ndarray
    seconds: float

    def line(self) -> str:
        R = " ".join(f"{v:.9g}" for v in self.pose[:3, :3].ravel())
        t = " ".join(f"{v:.6f}" for v in self.pose[:3, 3])
        return f"{self.scene_id},0,{self.obj_id},{self.score:.6g},{R},{t},{self.seconds:.3f}"


def result_rows(
    scene_id: str, hypotheses: Iterable[Hypothesis], objects: Sequence[str], seconds: float
) -> list[ResultRow]:
    """The rows of one scene's hypotheses; ``objects`` is dataset.yaml's object list."""
    ids = {name: k + 1 for k, name in enumerate(objects)}
    sid = str(int(scene_id)) if scene_id.isdigit() else scene_id
    return [ResultRow(sid, ids[h.object], h.score, h.pose, seconds) for h in hypotheses]


def write_results(path: str | Path, rows: Iterable[ResultRow]) -> None:
    """The CSV, written atomically (a reader never sees half of it)."""
    from annotator.io.atomic import write_text

    write_text(path, "\n".join([HEADER] + [r.line() for r in rows]) + "\n")


def coco_path(csv: str | Path) -> Path:
    """Where the COCO results go beside the CSV ``csv``: the same name ending ``.json``."""
    csv = Path(csv)
    return csv.with_suffix(".json") if csv.suffix != ".json" else csv.with_suffix(".coco.json")


def coco_results(
    rows: Iterable[ResultRow],
    meshes: Sequence[Mesh],
    K: np.ndarray,
    width: int,
    height: int,
) -> list[dict[str, object]]:
    """The rows as COCO results (see the module): ``meshes[obj_id - 1]`` rendered in each
    row's pose by a pinhole camera ``K`` of ``width`` x ``height`` pixels. A hypothesis out
    of view has an empty box and mask."""
    from annotator.export.bop import rle
    from annotator.rendering.raycast import render_depth

    out: list[dict[str, object]] = []
    for r in rows:
        mask = np.zeros((height, width), bool)
        rendered = render_depth(meshes[r.obj_id - 1], r.pose, K, width, height)
        if rendered is not None:
            (x0, y0, x1, y1), depth = rendered
            mask[y0:y1, x0:x1] = depth > 0
        ys, xs = np.nonzero(mask)
        box = (
            [
                int(xs.min()),
                int(ys.min()),
                int(xs.max() - xs.min() + 1),
                int(ys.max() - ys.min() + 1),
            ]
            if len(xs)
            else [0, 0, 0, 0]
        )
        out.append(
            {
                "scene_id": int(r.scene_id) if r.scene_id.isdigit() else r.scene_id,
                "image_id": 0,
                "category_id": r.obj_id,
                "score": float(r.score),
                "bbox": box,
                "segmentation": rle(mask),
                "time": round(r.seconds, 3),
            }
        )
    return out
