"""How many of a pose estimator's estimates are physically impossible in the real pile: an
estimate that passes through a true part (other than the one it is of) or through the
support, or that rests on nothing (see :mod:`annotator.physics` for the conventions)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from annotator.dataset import Dataset
from annotator.dataset.frames import Shot, scene_shots
from annotator.formats.base import GroundTruth, PoseResults, PoseSet
from annotator.geometry.transforms import make_transform
from annotator.physics.check import PhysicsSettings, check_one
from annotator.physics.contact import Body
from annotator.physics.scene import shot_support


@dataclass
class ResultsPhysics:
    """Per object: estimates checked, and how many penetrate and float."""

    checked: dict[str, int] = field(default_factory=dict)
    penetrating: dict[str, int] = field(default_factory=dict)
    floating: dict[str, int] = field(default_factory=dict)
    impossible: dict[str, int] = field(default_factory=dict)
    images_without_support: int = 0

    def share(self, obj: str | None = None) -> float:
        """The share of estimates physically impossible (of ``obj``, or of all)."""
        n = self.checked.get(obj, 0) if obj else sum(self.checked.values())
        bad = self.impossible.get(obj, 0) if obj else sum(self.impossible.values())
        return bad / n if n else 0.0

    def to_json(self) -> dict[str, Any]:
        return {
            "impossible_share": round(self.share(), 4),
            "per_object": {
                o: {
                    "checked": n,
                    "penetrating": self.penetrating.get(o, 0),
                    "floating": self.floating.get(o, 0),
                    "impossible_share": round(self.share(o), 4),
                }
                for o, n in sorted(self.checked.items())
            },
            "images_without_support": self.images_without_support,
        }


def results_physics(
    ds: Dataset,
    gt: GroundTruth,
    results: PoseResults,
    *,
    per_object: int = 3,
    settings: PhysicsSettings | None = None,
) -> ResultsPhysics:
    """Check each image's best ``per_object`` estimates of every object against the true
    parts of that image (``gt``) and its support (from the dataset's depth)."""
    out = ResultsPhysics()
    true_poses = _by_image(gt.poses, ds)
    for image, estimates in sorted(_by_image(results.poses, ds).items()):
        truth = [
            Body(f"{obj}/truth{k}", ds.objects[obj].mesh, make_transform(R, t))
            for obj, poses in true_poses.get(image, [])
            for k, (R, t) in enumerate(zip(poses.R, poses.t))
        ]
        shot = _shot(ds, image)
        support = None if shot is None else shot_support(ds, shot, truth)
        out.images_without_support += support is None
        for obj, found in estimates:
            order = np.argsort(-np.asarray(found.values, float), kind="stable")[:per_object]
            for k in order:
                est = Body(
                    f"{obj}#{k}", ds.objects[obj].mesh, make_transform(found.R[k], found.t[k])
                )
                others = [b for b in truth if b is not _counterpart(est, obj, truth)]
                rec = check_one(est, others, support, settings=settings)
                out.checked[obj] = out.checked.get(obj, 0) + 1
                pen, flo = "penetrates" in rec.flags, "floats" in rec.flags
                out.penetrating[obj] = out.penetrating.get(obj, 0) + pen
                out.floating[obj] = out.floating.get(obj, 0) + flo
                out.impossible[obj] = out.impossible.get(obj, 0) + (pen or flo)
    return out


def _by_image(table: Any, ds: Dataset) -> dict[str, list[tuple[str, PoseSet]]]:
    """A pose table's entries by image, in object order; objects the dataset lacks left out."""
    out: dict[str, list[tuple[str, PoseSet]]] = {}
    for (image, obj), poses in sorted(table.items()):
        if obj in ds.objects:
            out.setdefault(image, []).append((obj, poses))
    return out


def _counterpart(est: Body, obj: str, truth: list[Body]) -> Body | None:
    """The true part of the same object an estimate is nearest (it is of that one)."""
    same = [b for b in truth if b.key.startswith(f"{obj}/")]
    if not same:
        return None
    return min(same, key=lambda b: float(np.linalg.norm(b.centroid - est.centroid)))


def _shot(ds: Dataset, image: str) -> Shot | None:
    """The shot an image key names: a scene (fixed rig) or ``<scene>/<frame>``, its poses
    in that shot's own reference camera."""
    sid, _, frame = image.partition("/")
    try:
        scene = ds.scene(sid)
    except KeyError:  # a scene the dataset does not have: no support to be had
        return None
    if not frame:
        return scene_shots(ds, scene)[0]
    folder = next((f for f in scene.frames() if f.name == frame), None)
    return None if folder is None else Shot(scene, folder, frame, np.eye(4))
