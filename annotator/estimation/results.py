"""Hypotheses as BOP's results CSV, which ``annotator evaluate DATASET --results FILE`` reads.

One line per hypothesis, ``scene_id,im_id,obj_id,score,R,t,time`` with the header line:
``scene_id`` our scene folder (a number for the usual ``000012``-style names, which BOP
requires), ``im_id`` 0 (one image per scene), ``obj_id`` the object's number in dataset.yaml's
order from 1 (as ``annotator export --format bop`` numbers them), ``R`` nine row-major numbers
and ``t`` three (mm, model to the reference camera) separated by spaces, ``time`` the seconds
the scene took (the same on every line of a scene, as BOP asks).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from annotator.estimation.estimator import Hypothesis

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
