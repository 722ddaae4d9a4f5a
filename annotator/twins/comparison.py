"""A dataset against its twin, every scene (:func:`~annotator.twins.report.compare_scene`):
the comparison behind ``annotator twin-report``, with its pictures (``<scene>.png``, the
real image with each instance green or red, and ``histogram.png``) and its JSON document."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from annotator.dataset import Dataset, Scene, read_poses
from annotator.errors import UserError
from annotator.io.images import write_png
from annotator.twins.report import SceneComparison, compare_scene, histogram_png, overlay


@dataclass(frozen=True)
class TwinComparison:
    """Every scene's comparison, the part-pixel depth differences of all of them (mm), the
    settings, and the pictures' folder."""

    scenes: list[SceneComparison]
    diffs: np.ndarray
    tolerance_mm: float
    max_disagreement: float
    pictures: Path

    def to_json(self) -> dict[str, Any]:
        """The report document (``twin-report --json``)."""
        lim = self.max_disagreement
        return {
            "tolerance_mm": self.tolerance_mm,
            "max_disagreement": lim,
            "scenes": [r.to_json(lim) for r in self.scenes],
            "overall": self._overall(),
            "pictures": str(self.pictures),
        }

    def _overall(self) -> dict[str, Any]:
        rows, d = self.scenes, np.abs(self.diffs)
        lim = self.max_disagreement
        return {
            "valid_real": round(float(np.mean([r.valid_real for r in rows])), 4),
            "valid_twin": round(float(np.mean([r.valid_twin for r in rows])), 4),
            "median_abs_mm": round(float(np.median(d)), 3) if len(d) else None,
            "p95_abs_mm": round(float(np.percentile(d, 95)), 3) if len(d) else None,
            "instances_disagreeing": sum(i.disagrees(lim) for r in rows for i in r.instances),
        }


def compare_twin(
    ds: Dataset,
    twin: Dataset,
    *,
    tolerance_mm: float,
    max_disagreement: float,
    pictures: Path | None = None,
    warn: Callable[[str], None] = lambda _: None,
) -> TwinComparison:
    """Compare every twin scene with its real scene and write the pictures into
    ``pictures`` (default ``TWIN/report``); ``warn`` hears of the scenes left out (no real
    scene, no depth map).

    Raises:
        UserError: the dataset has no depth maps, there is no twin scene, or no scene has
            depth in both.
    """
    if ds.rig.depth is None:
        raise UserError("the dataset has no depth maps to compare (rig.depth)", path=ds.root)
    twins = {s.id: s for s in twin.scenes() if s.gt_path.exists()}
    if not twins:
        raise UserError("no twin scene (run `annotator synth --twin` first)", path=twin.root)
    folder = pictures if pictures is not None else twin.root / "report"
    rows = []
    for sid, tsc in sorted(twins.items()):
        comp = _compare_pair(ds, twin, sid, tsc, tolerance_mm, max_disagreement, folder, warn)
        if comp is not None:
            rows.append(comp)
    if not rows:
        raise UserError("no scene with depth in both datasets", path=twin.root)
    diffs = np.concatenate([r.part_diffs for r in rows])
    histogram_png(diffs, folder / "histogram.png")
    return TwinComparison(rows, diffs, tolerance_mm, max_disagreement, folder)


def _compare_pair(
    ds: Dataset,
    twin: Dataset,
    sid: str,
    twin_scene: Scene,
    tolerance_mm: float,
    max_disagreement: float,
    folder: Path,
    warn: Callable[[str], None],
) -> SceneComparison | None:
    """One scene against its twin, and its picture; None (and a warning) if either lacks."""
    try:
        real_scene = ds.scene(sid)
    except KeyError:
        warn(f"warning: twin scene {sid} has no scene in {ds.root}")
        return None
    real = real_scene.read_depth(ds.rig)
    sim = twin_scene.read_depth(twin.rig)
    if real is None or sim is None:
        warn(f"warning: scene {sid} has no depth map to compare")
        return None
    poses = read_poses(twin_scene.gt_path)
    comp, front = compare_scene(ds, sid, real, sim, poses, tolerance_mm=tolerance_mm)
    depth_cam = ds.rig.depth_camera
    assert depth_cam is not None  # rig.depth is set
    img = real_scene.read_image(depth_cam)
    write_png(folder / f"{sid}.png", overlay(img, front, comp, max_disagreement, 2))
    return comp
