"""A dataset against its twin, every scene (:func:`~annotator.twins.report.compare_scene`):
the comparison behind ``annotator twin-report``, with its pictures (``<scene>.png``, the
real image with each instance green or red, and ``histogram.png``) and its JSON document.

A moving rig's sequence is compared frame by frame: every frame of the twin's gt.json
``frames`` against the real frame of that name, the poses (scene frame) taken through the
frame's ``scene_T_rig``; its rows are named ``<scene>/<frame>`` and its pictures
``<scene>/<frame>.png``."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from annotator.dataset import Dataset, InstancePose, Scene, read_poses
from annotator.dataset.frames import poses_in_frame, read_frames
from annotator.dataset.model import FRAMES_DIR, Capture
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
        if twin.rig.moving:
            rows.extend(
                _compare_sequence(ds, twin, sid, tsc, tolerance_mm, max_disagreement, folder, warn)
            )
            continue
        try:
            real_scene = ds.scene(sid)
        except KeyError:
            warn(f"warning: twin scene {sid} has no scene in {ds.root}")
            continue
        poses = read_poses(tsc.gt_path)
        comp = _compare_pair(
            ds, twin, sid, real_scene, tsc, poses, tolerance_mm, max_disagreement, folder, warn
        )
        if comp is not None:
            rows.append(comp)
    if not rows:
        raise UserError("no scene with depth in both datasets", path=twin.root)
    diffs = np.concatenate([r.part_diffs for r in rows])
    histogram_png(diffs, folder / "histogram.png")
    return TwinComparison(rows, diffs, tolerance_mm, max_disagreement, folder)


def _compare_sequence(
    ds: Dataset,
    twin: Dataset,
    sid: str,
    twin_scene: Scene,
    tolerance_mm: float,
    max_disagreement: float,
    folder: Path,
    warn: Callable[[str], None],
) -> list[SceneComparison]:
    """A sequence against its twin, one row per twin frame (``<scene>/<frame>``)."""
    if not ds.rig.moving:
        warn(f"warning: twin scene {sid} is a sequence, {ds.root} has a fixed rig")
        return []
    try:
        real_frames = {f.name: f for f in ds.scene(sid).frames()}
    except KeyError:
        warn(f"warning: twin scene {sid} has no scene in {ds.root}")
        return []
    poses = read_poses(twin_scene.gt_path)
    rows = []
    for name, entry in sorted(read_frames(twin_scene.gt_path).items()):
        fid = f"{sid}/{name}"
        if entry.scene_T_rig is None:
            continue
        if name not in real_frames:
            warn(f"warning: twin frame {fid} has no frame in {ds.root}")
            continue
        twin_frame = twin_scene.path / FRAMES_DIR / name
        comp = _compare_pair(
            ds,
            twin,
            fid,
            real_frames[name],
            _Folder(twin_frame, twin.rig.flipped),
            poses_in_frame(poses, entry.scene_T_rig),
            tolerance_mm,
            max_disagreement,
            folder,
            warn,
        )
        if comp is not None:
            rows.append(comp)
    return rows


@dataclass(frozen=True)
class _Folder(Capture):
    """A shot's folder (one twin frame)."""

    path: Path
    flipped: frozenset[str] = frozenset()


def _compare_pair(
    ds: Dataset,
    twin: Dataset,
    sid: str,
    real_scene: Capture,
    twin_scene: Capture,
    poses: list[InstancePose],
    tolerance_mm: float,
    max_disagreement: float,
    folder: Path,
    warn: Callable[[str], None],
) -> SceneComparison | None:
    """One shot (a scene, or a sequence's frame ``<scene>/<frame>``) against its twin with
    ``poses`` in its rig, and its picture ``<sid>.png``; None (and a warning) if either
    lacks a depth map."""
    real = real_scene.read_depth(ds.rig)
    sim = twin_scene.read_depth(twin.rig)
    if real is None or sim is None:
        warn(f"warning: scene {sid} has no depth map to compare")
        return None
    comp, front = compare_scene(ds, sid, real, sim, poses, tolerance_mm=tolerance_mm)
    depth_cam = ds.rig.depth_camera
    assert depth_cam is not None  # rig.depth is set
    img = real_scene.read_image(depth_cam)
    write_png(folder / f"{sid}.png", overlay(img, front, comp, max_disagreement, 2))
    return comp
