"""Which scenes an export takes, from the human decisions in review.json.

By default only *accepted* scenes whose decision is not stale (the annotation has not changed
since) and that have no rejected instance are exported; ``include_pending`` adds undecided
scenes, ``drop_rejected_instances`` exports scenes with rejected instances without them.

Poses a reviewer repaired in the viewer (review.json ``poses``) replace annotation.json's,
and instances added by hand are exported with the others; a scene with a stale edit (made
on an auto pose that ``annotate`` has changed since) is left out, as a stale decision is.
A sequence's frames a reviewer rejected on their own are left out of it (its other frames go).
A scene with a pose that cannot be right (:mod:`annotator.dataset.validity`: an unknown
object or instance, a part behind the camera) is left out and named.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from annotator.dataset import Dataset, InstancePose, Scene
from annotator.dataset.frames import Shot, frames_left_out, scene_shots
from annotator.dataset.poses import read_pose_file
from annotator.dataset.records import frames_from_json
from annotator.dataset.review import ReviewStatus, apply_edits, poses_fingerprint, read_review
from annotator.dataset.selection import EVERY_SCENE, matching_scenes
from annotator.dataset.validity import pose_problem
from annotator.errors import UserError


@dataclass
class Selected:
    """A scene to export: its poses (the scene frame for a sequence, else the reference
    camera) and its shots (:func:`~annotator.dataset.frames.scene_shots`: the scene itself,
    or every posed frame a reviewer did not reject)."""

    scene: Scene
    poses: list[InstancePose]
    shots: list[Shot] = field(default_factory=list)


@dataclass
class Selection:
    scenes: list[Selected] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)  # scene id -> reason
    #: A selected sequence's frames left out -> why (not posed: its flags; or rejected).
    frames_left: dict[str, dict[str, str]] = field(default_factory=dict)

    def nothing_error(self, ds: Dataset, *, include_pending: bool, what: str) -> UserError:
        """The one line for no scene selected, ``what`` being the work ("to export")."""
        why = ", ".join(f"{n} {r}" for r, n in sorted(self.reasons().items())) or "no scenes"
        pending = str(ReviewStatus.PENDING) in self.reasons()
        advice = ", or use --include-pending" if pending and not include_pending else ""
        accepted = "" if include_pending else "accepted "
        return UserError(
            f"no {accepted}scene {what} ({why}); review them with `annotator review`{advice}",
            path=ds.root,
        )

    def reasons(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for r in self.skipped.values():
            out[r] = out.get(r, 0) + 1
        return out


def select_scenes(
    ds: Dataset,
    *,
    include_pending: bool = False,
    drop_rejected_instances: bool = False,
    poses_from: str = "annotation",
    scenes: str = EVERY_SCENE,
) -> Selection:
    """Scenes to export among those whose id matches ``scenes``
    (:func:`annotator.dataset.selection.matching_scenes`), and why the others are left out."""
    sel = Selection()
    for scene in matching_scenes(ds, scenes, required=False):
        path = scene.annotation_path if poses_from == "annotation" else scene.gt_path
        if not path.exists():
            sel.skipped[scene.id] = f"no {path.name}"
            continue
        try:
            poses, top = read_pose_file(path)
            review = read_review(scene.review_path)
            shots = scene_shots(
                ds,
                scene,
                frames_from_json(top.get("frames"), path),
                rejected=review.rejected_frames if review else (),
            )
        except UserError as exc:
            sel.skipped[scene.id] = f"error: {exc}"
            continue
        status = ReviewStatus.PENDING if review is None else review.status
        if (
            review is not None
            and poses_from == "annotation"
            and review.is_stale(poses_fingerprint(poses))
        ):
            sel.skipped[scene.id] = "stale review (annotation changed since)"
            continue
        if status == ReviewStatus.REJECTED:
            sel.skipped[scene.id] = str(status)
            continue
        if status == ReviewStatus.PENDING and not include_pending:
            sel.skipped[scene.id] = str(status)
            continue
        if poses_from == "annotation":
            edits = apply_edits(poses, review)
            if edits.stale:
                sel.skipped[scene.id] = "stale pose edit (annotation changed since)"
                continue
            poses = edits.poses
        rejected = {
            k for k, v in (review.instances if review else {}).items() if v == ReviewStatus.REJECTED
        }
        if rejected and not drop_rejected_instances:
            sel.skipped[scene.id] = "has a rejected instance"
            continue
        kept = [p for p in poses if p.key not in rejected]
        problems = [(p.key, x) for p in kept if (x := pose_problem(ds, p)) is not None]
        if problems:
            key, problem = problems[0]
            edited = review is not None and key in review.poses
            sel.skipped[scene.id] = f"error: {scene.review_path if edited else path}: {problem}"
            continue
        if not shots:
            sel.skipped[scene.id] = "every frame rejected or unposed"
            continue
        sel.scenes.append(Selected(scene, kept, shots))
        if ds.rig.moving:
            left = frames_left_out(
                frames_from_json(top.get("frames"), path), review.rejected_frames if review else ()
            )
            if left:
                sel.frames_left[scene.id] = left
    return sel
