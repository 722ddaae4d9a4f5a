"""The physics check over a dataset: every scene's posed parts (annotation.json, repaired
poses applied, or gt.json), one line per scene that cannot be read (see
:mod:`annotator.physics` for the conventions)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from annotator.dataset import Dataset, InstancePose, Scene
from annotator.dataset.frames import scene_shots
from annotator.dataset.load import Problem
from annotator.dataset.poses import read_pose_file
from annotator.dataset.records import FramePose, SceneAnnotation, frames_from_json
from annotator.dataset.review import apply_edits, read_review
from annotator.dataset.selection import matching_scenes
from annotator.errors import UserError
from annotator.physics.check import InstancePhysics, PhysicsSettings
from annotator.physics.contact import check_solid
from annotator.physics.scene import shot_physics
from annotator.summary import failure_lines


@dataclass
class ScenePhysics:
    """One scene's physics: per instance (:class:`InstancePhysics`), whether a support was
    found, and how long the check took (s)."""

    scene: str
    instances: list[InstancePhysics]
    support: dict[str, Any] | None
    seconds: float

    @property
    def flagged(self) -> list[InstancePhysics]:
        return [r for r in self.instances if r.flags]

    def to_json(self) -> dict[str, Any]:
        return {
            "support": self.support,
            "instances": {
                r.key: {**r.check.to_json(), "flags": [str(f) for f in r.flags]}
                for r in self.instances
            },
        }


@dataclass
class PhysicsSummary:
    """:func:`physics_of_dataset`'s scenes, and the scenes it could not check (one line).

    >>> s = PhysicsSummary(failed={"000002": "no frame is posed"})
    >>> s.text()
    'physics: 0 scenes checked, 0 instances flagged, 1 not checked'
    >>> s.warnings()
    ['failed: scene 000002: no frame is posed']
    """

    scenes: list[ScenePhysics] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)

    def counts(self) -> dict[str, int]:
        return {
            "scenes": len(self.scenes),
            "flagged": sum(len(sp.flagged) for sp in self.scenes),
            "failed": len(self.failed),
        }

    def warnings(self) -> list[str]:
        return failure_lines(self.failed)

    def written_paths(self) -> list[Path]:
        return []  # it only reads: ``check --physics`` reports, nothing is written

    def text(self) -> str:
        n = self.counts()
        return (
            f"physics: {n['scenes']} scenes checked, {n['flagged']} instances flagged, "
            f"{n['failed']} not checked"
        )

    def to_json(self) -> dict[str, Any]:
        """``check --physics --json``'s ``physics``: per scene, its support and instances."""
        return {
            "scenes": {sp.scene: sp.to_json() for sp in self.scenes},
            "flagged": sum(len(sp.flagged) for sp in self.scenes),
            "failures": dict(sorted(self.failed.items())),
        }

    def exit_status(self) -> int:
        return 0  # a flagged pose or a scene not checked is a warning, as ``check`` says it


def scene_poses(
    ds: Dataset, scene: Scene, poses: str
) -> tuple[list[InstancePose], dict[str, float | None], dict[str, FramePose]]:
    """A scene's poses as the export takes them (annotation.json with the review's repairs,
    or gt.json), their uncertainties, and the pose file's ``frames`` (a sequence's)."""
    path = scene.annotation_path if poses == "annotation" else scene.gt_path
    if not path.exists():
        raise UserError(f"no {path.name}", path=scene.path)
    if poses == "gt":
        found, top = read_pose_file(path)
        return found, {}, frames_from_json(top.get("frames"), path)
    ann = SceneAnnotation.read(path)
    edits = apply_edits(ann.instances, read_review(scene.review_path))
    u = {i.key: i.uncertainty_mm for i in ann.instances if i.key not in edits.edited}
    posed = [p.pose if hasattr(p, "pose") else p for p in edits.poses]
    return posed, u, ann.frames


def physics_of_dataset(
    ds: Dataset,
    *,
    poses: str = "annotation",
    scenes: str = "*",
    stability: bool = False,
    settings: PhysicsSettings | None = None,
) -> PhysicsSummary:
    """The physics of every scene matching ``scenes`` that has ``poses`` (``annotation`` or
    ``gt``); a sequence's in its scene frame, the support from its first posed frame.

    >>> import annotator
    >>> summary = annotator.physics_of_dataset(annotator.load_dataset("sample_scenes"), poses="gt")
    >>> [sp.scene for sp in summary.scenes], sum(len(sp.flagged) for sp in summary.scenes)
    (['000000', '000001', '000002', '000003'], 0)
    """
    out = PhysicsSummary()
    for obj in ds.objects.values():
        check_solid(obj.mesh, obj.mesh_path)
    for scene in matching_scenes(ds, scenes, required=False):
        path = scene.annotation_path if poses == "annotation" else scene.gt_path
        if not path.exists():
            continue
        t0 = time.perf_counter()
        try:
            posed, u, frames = scene_poses(ds, scene, poses)
            shots = scene_shots(ds, scene, frames)
            if not shots:
                raise UserError("no frame is posed", path=path)
            recs, support = shot_physics(
                ds, shots[0], posed, uncertainty=u, settings=settings, stability=stability
            )
        except UserError as exc:
            out.failed[scene.id] = str(exc)
            continue
        plane = None if support is None else support.plane.to_json()
        out.scenes.append(ScenePhysics(scene.id, recs, plane, time.perf_counter() - t0))
    return out


def physics_problems(ds: Dataset, summary: PhysicsSummary, poses: str) -> list[Problem]:
    """``check``'s warning lines: one per flagged instance, one per scene not checked."""
    out = []
    for sp in summary.scenes:
        scene = ds.scene(sp.scene)
        path = scene.annotation_path if poses == "annotation" else scene.gt_path
        out += [Problem(path, f"physics: {r.describe()}", warning=True) for r in sp.flagged]
    for sid, why in sorted(summary.failed.items()):
        out.append(Problem(ds.scene(sid).path, f"physics not checked: {why}", warning=True))
    return out
