"""What the review knows of one scene (:class:`SceneInfo`): its poses with the reviewers'
repairs applied, its decisions, which version of it a page displayed (``view``), and the
errors a decision may meet (:class:`SaveError`, :class:`Conflict`). The state that reads and
writes them is :class:`annotator.review.state.ReviewState`."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from annotator.dataset import Scene
from annotator.dataset.figures import SceneWarning
from annotator.dataset.flags import PHYSICS_FLAGS
from annotator.dataset.frames import shown_frames
from annotator.dataset.records import (
    FramePose,
    InstanceAnnotation,
)
from annotator.dataset.review import (
    EditedPose,
    Review,
    ReviewStatus,
    poses_fingerprint,
)

FILTERS = ("all", "pending", "flagged", "rejected", "stale")

# (inode, mtime_ns) of a file, or None if it does not exist. Atomic writes replace the
# file, so the inode changes with every write even within one clock tick.
Stamp = tuple[int, int] | None


def stamp(path: str) -> Stamp:
    try:
        st = os.stat(path)
    except OSError:  # missing (or unreadable: reading it will say so)
        return None
    return (st.st_ino, st.st_mtime_ns)


class SaveError(Exception):
    """A decision could not be written; the message is one line naming the file and why."""


class Conflict(SaveError):
    """A pose edit or an undo was not made: another reviewer changed that part's pose
    after the page computed its change (the message says who and when)."""


def same_edit(a: EditedPose | None, b: EditedPose | None) -> bool:
    """Whether two states of a part's edit are the same one (None: no edit, the auto pose):
    made by the same page at the same time into the same pose."""
    if a is None or b is None:
        return a is b
    return (
        a.decided_by == b.decided_by
        and a.at == b.at
        and np.allclose(a.R, b.R, rtol=0, atol=1e-9)
        and np.allclose(a.t, b.t, rtol=0, atol=1e-6)
    )


def describe(edit: EditedPose | None, by: str | None = None) -> str:
    if edit is None:
        return "put back to its auto pose"
    mine = by is not None and edit.decided_by == by  # a page never blames itself by its id
    who = "another key of yours on this page" if mine else edit.decided_by or "another reviewer"
    return f"changed by {who}" + (f" at {edit.at}" if edit.at else "")


@dataclass(frozen=True)
class Staged:
    """A pose edit made in memory and not written yet (:meth:`ReviewState.commit` writes it)."""

    sid: str
    review: Review
    info: SceneInfo  # the scene as it is once ``review`` is written
    by: str | None


@dataclass(frozen=True)
class SceneInfo:
    """What is known about a scene: its proposed poses, the decisions about them, and what
    deserves a look."""

    id: str
    annotated: bool
    poses: tuple[InstanceAnnotation, ...]
    review: Review
    stale: bool
    flagged: bool  # a pose has flags, or the annotation has warnings
    error: str | None  # a problem to show (unreadable annotation, corrupt review.json)
    warnings: tuple[SceneWarning, ...] = ()
    fingerprint: str = ""  # of the auto poses (annotator.dataset.review.poses_fingerprint)
    gone: bool = False  # the scene's folder is no longer there (error says where)
    auto: tuple[InstanceAnnotation, ...] = ()  # the poses as annotate wrote them
    edited: frozenset[str] = frozenset()  # instances whose pose is a reviewer's edit
    stale_edits: frozenset[str] = frozenset()  # edits made on an auto pose changed since
    view: str = ""  # fingerprint of the poses shown (edits applied): what pictures are made of
    #: A sequence's frames (annotation.json ``frames``) and those the pages show side by side
    #: (:func:`annotator.dataset.frames.shown_frames`); empty for a fixed rig's scene.
    frames: Mapping[str, FramePose] = field(default_factory=dict)
    shown: tuple[str, ...] = ()

    @property
    def physics_flagged(self) -> bool:
        """A pose is physically impossible in its pile (penetrates, floats, unstable)."""
        return any(f in PHYSICS_FLAGS for p in self.auto for f in p.flags)

    @property
    def rejected_frames(self) -> set[str]:
        """The sequence's frames a reviewer rejected on their own."""
        return self.review.rejected_frames

    @property
    def status(self) -> ReviewStatus:
        return self.review.status

    @property
    def decided(self) -> bool:
        """A current decision: not pending and not stale."""
        return self.status != ReviewStatus.PENDING and not self.stale

    def instance_status(self, key: str) -> ReviewStatus:
        """``accepted``, ``rejected`` or ``pending`` (no decision yet)."""
        return self.review.instances.get(
            key,
            ReviewStatus.ACCEPTED
            if self.review.status == ReviewStatus.ACCEPTED
            else ReviewStatus.PENDING,
        )

    def pose(self, key: str) -> InstanceAnnotation | None:
        return next((p for p in self.poses if p.key == key), None)

    def auto_pose(self, key: str) -> InstanceAnnotation | None:
        return next((p for p in self.auto if p.key == key), None)

    def with_pose(self, key: str, T: np.ndarray) -> tuple[list[InstanceAnnotation], str]:
        """The poses shown with ``key``'s at ``T`` (4x4) instead, and their fingerprint: the
        :attr:`view` the scene has once that pose is saved (what overlays made ahead of a
        repair are kept under)."""
        poses = [
            replace(p, R=np.array(T[:3, :3]), t=np.array(T[:3, 3])) if p.key == key else p
            for p in self.poses
        ]
        return poses, view_key(poses, self.shown, self.frames)


def view_key(
    poses: list[InstanceAnnotation],
    shown: tuple[str, ...],
    frames: Mapping[str, FramePose] | None = None,
) -> str:
    """What a scene's pictures are made of: the poses shown and, for a sequence, which
    frames and where the rig was for each (a new annotation may move a frame and no part:
    :attr:`SceneInfo.view`)."""
    key = poses_fingerprint(poses)
    if not shown:
        return key
    return f"{key}#{frames_digest(frames or {}, shown)}@{','.join(shown)}"


def frames_digest(frames: Mapping[str, FramePose], shown: tuple[str, ...]) -> str:
    """A short digest of the shown frames' ``scene_T_rig`` (missing or unposed: none)."""
    h = hashlib.sha256()
    for name in shown:
        T = frames[name].scene_T_rig if name in frames else None
        h.update(name.encode() + b"\0")
        if T is not None:
            h.update(np.ascontiguousarray(T, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


def window(info: SceneInfo, at: int) -> SceneInfo:
    """``info`` with the frames a page whose window is ``at`` frames on shows."""
    if not info.frames:
        return info
    shown = tuple(shown_frames(info.frames, offset=at))
    if shown == info.shown:
        return info
    return replace(info, shown=shown, view=view_key(list(info.poses), shown, info.frames))


def changed_since(now: SceneInfo, seen: SceneInfo, by: str | None) -> str | None:
    """Why a decision made looking at ``seen`` (the scene as a page showed it) is not one
    about the scene as it is ``now``: annotate wrote other poses or frames, or a part was
    repaired by someone other than ``by`` since; None if the page showed what is there."""
    if now.fingerprint != seen.fingerprint or frames_digest(
        now.frames, tuple(now.frames)
    ) != frames_digest(seen.frames, tuple(seen.frames)):
        return "the annotation changed on disk after your page showed it (annotate ran again?)"
    for key in sorted(set(now.review.poses) | set(seen.review.poses)):
        edit = now.review.poses.get(key)
        if not same_edit(edit, seen.review.poses.get(key)) and (
            edit is None or edit.decided_by != by
        ):
            return f"{key} was {describe(edit, by)} after your page showed it"
    return None


def added(obj: str, inst: str, R: object, t: object) -> InstanceAnnotation:
    """The record of an instance added by hand: a pose, and none of annotate's figures."""
    return InstanceAnnotation(obj, inst, R, t)  # type: ignore[arg-type]


def gone_info(sid: str, scene: Scene) -> SceneInfo:
    """What is known of a scene whose folder has gone."""
    return SceneInfo(
        id=sid,
        annotated=False,
        poses=(),
        review=Review(),
        stale=False,
        flagged=False,
        error=f"{scene.path}: the scene's folder is gone (deleted or moved since the viewer "
        "started)",
        fingerprint=poses_fingerprint([]),
        gone=True,
        view=poses_fingerprint([]),
    )
