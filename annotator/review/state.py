"""Review decisions of a dataset, read from and written to each scene's review.json.

Every action writes review.json atomically at once (killing the server loses nothing), and
every read goes back to the files (cached by inode and modification time), so several pages,
and several servers, on the same dataset see the same decisions. :meth:`ReviewState.poll`
tells which scenes changed on disk by other hands since it was last asked.

A decision that cannot be written (read-only folder, full disk) raises :class:`SaveError`
with one line for the person who made it; nothing is changed then.

Several servers (processes) and several pages on one dataset: every change of a scene is
made under the scene's lock (a ``flock`` on its folder, across processes, and the state's
own lock, across the pages of a server), on review.json as the file holds it then, and
changes only what it is about: a decision keeps the poses other reviewers repaired, a pose
edit keeps their decisions and their edits of other parts. A pose edit is a compare-and-set:
it names the edit it was computed from (``expect``), and if another reviewer has changed
that part's pose since, nothing is written and :class:`Conflict` (a :class:`SaveError`)
says who did it and when; an undo likewise undoes only the page's own step, while it is
still the part's last one.

A pose edit can be shown before it is written: :meth:`ReviewState.stage_pose` (and
:meth:`ReviewState.stage_restore`) make the scene's next state in memory, which
:meth:`ReviewState.info` returns from then on, and :meth:`ReviewState.commit` writes it. No
other write happens in between (both locks are held), so nothing written meanwhile can be
overwritten, and a failed commit puts the scene back as the file has it.

Poses repaired in a page (review.json ``poses``) are applied to the scene's poses here:
:attr:`SceneInfo.poses` are what the pages show and the export takes, :attr:`SceneInfo.auto`
what ``annotate`` wrote. An edit made on an auto pose that has changed since is stale: the
auto pose is shown, and the scene is stale as a decision on it would be.

A decision is for what the page showed: it names that version of the scene (``seen``), and if
annotate has written other poses or frames since, or another reviewer has repaired a part
since, nothing is written and :class:`Conflict` says so (the page then shows the new poses).
A sequence's pages each show their own few frames (``at``: how many frames on; a page's P
moves its own window only), so a key acts on the frames its page shows.

A scene whose folder disappears while the server runs (deleted, moved, the whole dataset
gone) is known as :attr:`SceneInfo.gone`: it is shown as gone, and a decision for it is a
:class:`SaveError` (writing it would make the folder again, holding only a review.json).
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from annotator.dataset import Dataset, Scene, load_dataset
from annotator.dataset.figures import SceneWarning
from annotator.dataset.frames import frames_view, shown_frames
from annotator.dataset.records import (
    FramePose,
    InstanceAnnotation,
    SceneAnnotation,
)
from annotator.dataset.review import (
    NO_POSE_REASON,
    EditedPose,
    MissingPart,
    RepairStep,
    Review,
    ReviewStatus,
    apply_edits,
    as_step,
    instance_fingerprint,
    now_iso,
    poses_fingerprint,
    read_review,
    write_review,
)
from annotator.dataset.validity import unknown_name
from annotator.errors import UserError
from annotator.review.locks import FolderLocks
from annotator.review.scenes import (
    Conflict,
    SaveError,
    SceneInfo,
    Staged,
    Stamp,
    added,
    changed_since,
    describe,
    frames_digest,
    gone_info,
    same_edit,
    stamp,
    view_key,
    window,
)

#: ``expect`` of a pose edit that is not checked against what the file holds.
ANY = object()

#: Frames views of sequences kept (:meth:`ReviewState.view`): a few pages, each on a scene.
VIEWS_KEPT = 16


class ReviewState:
    """The review state of one dataset, shared by every page of a server."""

    def __init__(self, root: str | Path) -> None:
        self.ds = load_dataset(root)
        scenes = self.ds.scenes()
        self.ids = [s.id for s in scenes]
        self._scenes = {s.id: s for s in scenes}
        # Paths as strings once: stat-ing every scene is what polling and progress cost.
        self._paths = {s.id: (str(s.annotation_path), str(s.review_path)) for s in scenes}
        self._lock = threading.RLock()
        self._cache: dict[str, tuple[tuple[Stamp, Stamp], SceneInfo]] = {}
        self._seen: dict[str, tuple[Stamp, Stamp]] = {}
        self._staged: dict[str, Staged] = {}  # scene -> its edit shown and not yet written
        # scene -> (descriptor holding the folder's flock, how many holds): taken and given
        # back only under self._lock, so one thread at a time holds a scene's file lock.
        self._flocks = FolderLocks()
        self.started = time.time()
        self.decided = 0  # decisions made through this server
        #: (scene, shown frames, their digest) -> the frames view (:meth:`view`), the latest
        #: few kept.
        self._views: dict[tuple[str, tuple[str, ...], str], tuple[Dataset, Scene]] = {}

    def _stamps(self, sid: str) -> tuple[Stamp, Stamp]:
        annotation, review = self._paths[sid]
        return (stamp(annotation), stamp(review))

    def scene(self, sid: str) -> Scene:
        """The scene's folder (which may have gone since: :attr:`SceneInfo.gone`); a
        sequence's as its shown frames make it (:meth:`dataset_of`)."""
        return self.view(sid)[1]

    def dataset_of(self, sid: str) -> Dataset:
        """The dataset as the scene's pages work on it: the dataset itself, or for a
        sequence its shown frames' cameras as one rig in the scene frame
        (:func:`annotator.dataset.frames.frames_view`), so that overlays and repairs are
        made in the scene frame and show in every frame."""
        return self.view(sid)[0]

    def view(self, sid: str, info: SceneInfo | None = None) -> tuple[Dataset, Scene]:
        """:meth:`dataset_of` and :meth:`scene` together; with ``info``, as that version
        of the scene shows it (the frames it shows, where its annotation put them), not
        as the scene is now (pictures being prepared for it while P shows other frames)."""
        scene = self._scenes[sid]
        if not self.ds.rig.moving:
            return self.ds, scene
        if info is None:
            info = self.info(sid)
        frames, shown = info.frames, info.shown
        if not shown:
            # Not annotated yet (or no frame posed): its first frame's images, as they are,
            # rather than the scene folder's, which a sequence does not have.
            folders = scene.frames()
            if not folders:
                return self.ds, scene
            first = folders[0].name
            frames, shown = {first: FramePose(first, np.eye(4))}, (first,)
        key = (sid, shown, frames_digest(frames, shown))
        with self._lock:
            hit = self._views.pop(key, None)
            if hit is None:
                hit = frames_view(self.ds, scene, frames, shown)
            self._views[key] = hit  # the latest last
            while len(self._views) > VIEWS_KEPT:
                self._views.pop(next(iter(self._views)))
            return hit

    def shifted(self, sid: str, at: int, step: int) -> SceneInfo | None:
        """The scene as a page whose window is ``at`` frames on shows it after P (``step``
        1) or Shift+P (-1), so that its pictures can be prepared ahead; None for a fixed
        rig's scene, or when the shift shows the same frames."""
        info = self.info(sid, at)
        if not info.shown:
            return None
        after = self.info(sid, at + step)
        return None if after.shown == info.shown else after

    def toggle_frame(
        self, sid: str, frame: str, *, by: str | None = None, seen: SceneInfo | None = None
    ) -> bool:
        """Reject one frame of a sequence on its own, or take it back; True if it is now
        rejected (the scene's other frames and its decision are not touched). ``seen``: the
        scene as the page showed it (:meth:`_changing`)."""
        with self._changing(sid, seen, by) as info:
            frames = dict(info.review.frames)
            rejected = frames.pop(frame, None) != ReviewStatus.REJECTED
            if rejected:
                frames[frame] = ReviewStatus.REJECTED
            self._write(sid, self._next_review(info, frames=frames), by, decision=False)
            return rejected

    def is_gone(self, sid: str) -> bool:
        """True if the scene's folder is no longer there."""
        return not os.path.isdir(self._scenes[sid].path)

    def info(self, sid: str, at: int = 0) -> SceneInfo:
        """The scene as the files say now (re-read only when a file changed), or as a staged
        edit makes it (:meth:`stage_pose`) until it is written; a sequence's with the frames
        a page whose window is ``at`` frames on shows."""
        staged = self._staged.get(sid)
        return window(staged.info if staged is not None else self._info(sid), at)

    def _info(self, sid: str) -> SceneInfo:
        key = self._stamps(sid)
        # Neither file: a scene not yet annotated, or one whose folder has gone.
        gone = key == (None, None) and self.is_gone(sid)
        hit = self._cache.get(sid)
        if hit and hit[0] == key and hit[1].gone == gone:
            return hit[1]
        sc = self._scenes[sid]
        if gone:
            info = gone_info(sid, sc)
            self._cache[sid] = (key, info)
            return info
        error = None
        poses: list[InstanceAnnotation] = []
        warnings: tuple[SceneWarning, ...] = ()
        annotated = key[0] is not None
        frames: dict[str, FramePose] = {}
        if annotated:
            try:
                ann = SceneAnnotation.read(sc.annotation_path)
                poses = ann.instances
                warnings = tuple(ann.warnings)
                if self.ds.rig.moving:
                    frames = ann.frames
            except (UserError, OSError) as exc:  # OSError: it went between stat and read
                error = str(exc)
        shown = tuple(shown_frames(frames))
        try:
            review = read_review(sc.review_path) or Review()
        except (UserError, OSError) as exc:
            review, error = Review(), f"{exc} (it will be replaced by the next decision)"
        fingerprint = poses_fingerprint(poses)
        edits = apply_edits(poses, review, added=added)
        unknown = {p.key: unknown_name(self.ds, p.object, p.instance) for p in edits.poses}
        unknown = {k: why for k, why in unknown.items() if why is not None}
        if unknown:  # nothing to draw them with: shown as an error, never drawn
            key, why = sorted(unknown.items())[0]
            error = (
                error or f"{sc.review_path if key in edits.edited else sc.annotation_path}: {why}"
            )
            edits.poses = [p for p in edits.poses if p.key not in unknown]
        info = SceneInfo(
            id=sid,
            annotated=annotated,
            poses=tuple(edits.poses),
            review=review,
            stale=review.is_stale(fingerprint) or bool(edits.stale),
            flagged=bool(warnings) or any(p.flags for p in poses),
            error=error,
            warnings=warnings,
            fingerprint=fingerprint,
            auto=tuple(poses),
            edited=frozenset(edits.edited),
            stale_edits=frozenset(edits.stale),
            view=view_key(edits.poses, shown, frames),
            frames=frames,
            shown=shown,
        )
        self._cache[sid] = (key, info)
        return info

    def poll(self) -> set[str]:
        """Scenes whose annotation.json or review.json changed since the last poll, other than
        by this server's own writes."""
        changed = set()
        with self._lock:  # a write between the stat and the update must not look foreign
            for sid in self.ids:
                stamps = self._stamps(sid)
                if self._seen.get(sid, stamps) != stamps:
                    changed.add(sid)
                self._seen[sid] = stamps
        return changed

    # ------------------------------------------------------------ locks
    @contextlib.contextmanager
    def _changing(
        self, sid: str, seen: SceneInfo | None = None, by: str | None = None
    ) -> Iterator[SceneInfo]:
        """Hold both locks of the scene while it is changed; yields it as the files say.
        ``seen``: the scene as the page deciding showed it; :class:`Conflict` if it has
        changed since (:func:`changed_since`)."""
        with self._lock:
            self._flocks.hold(sid, self._scenes[sid].path)
            try:
                info = self.info(sid)
                why = None if seen is None else changed_since(info, seen, by)
                if why is not None:
                    raise Conflict(
                        f"scene {sid}: {why}; nothing was written: the page shows the scene "
                        "as it is now, look at it and decide again"
                    )
                yield info
            finally:
                self._flocks.release(sid)

    @staticmethod
    def _check_expected(
        info: SceneInfo, key: str, expect: object, what: str, by: str | None
    ) -> None:
        """Conflict unless ``key``'s edit is still ``expect`` (:data:`ANY`: not checked)."""
        if expect is ANY:
            return
        current = info.review.poses.get(key)
        if not same_edit(current, expect):  # type: ignore[arg-type]
            raise Conflict(
                f"{key} was {describe(current, by)} after your page computed this {what}; "
                "nothing was written: look at the part as it is now"
            )

    # ------------------------------------------------------------ decisions
    def _write(self, sid: str, review: Review, by: str | None, *, decision: bool = True) -> Review:
        """Write ``review``; a ``decision`` is stamped with the poses it judged, when and by
        whom (a pose edit is not a decision: a decision made earlier stays as it was, stale
        or not)."""
        info = self.info(sid)
        path = self._scenes[sid].review_path
        # The atomic write makes missing folders: it would bring a deleted scene back as a
        # folder holding only this review.json.
        if info.gone or self.is_gone(sid):
            raise SaveError(f"{path.parent}: the scene's folder is gone (deleted or moved)")
        if decision:
            review.annotation_fingerprint = info.fingerprint
            review.decided_at = now_iso()
            review.decided_by = by
        try:
            write_review(path, review)
        except OSError as exc:
            # annotator.io.atomic may already say it in one line ("<path>: cannot write (...)").
            msg = (
                str(exc)
                if isinstance(exc, UserError)
                else f"{path}: cannot write ({exc.strerror or exc})"
            )
            raise SaveError(msg) from None
        self._seen[sid] = self._stamps(sid)
        self.decided += decision
        return review

    def _next_review(self, info: SceneInfo, **changes: object) -> Review:
        base = replace(
            info.review,
            extra=dict(info.review.extra),
            missing=list(info.review.missing),
            poses=dict(info.review.poses),
            frames=dict(info.review.frames),
        )
        return replace(base, **changes)  # type: ignore[arg-type]

    def set_scene(
        self, sid: str, status: str, *, by: str | None = None, seen: SceneInfo | None = None
    ) -> Review:
        """Accept or reject a whole scene. Per-instance rejections are kept. Rejecting keeps
        the reason and the "no pose here" marks; accepting says every part is posed, so it
        clears them. ``seen``: the scene as the page deciding showed it; :class:`Conflict`
        if its poses have changed since (:func:`changed_since`)."""
        status = ReviewStatus(status)
        with self._changing(sid, seen, by) as info:
            instances = {
                k: v for k, v in info.review.instances.items() if v == ReviewStatus.REJECTED
            }
            accepted = status == ReviewStatus.ACCEPTED
            changes: dict[str, object] = {"status": status, "instances": instances}
            if accepted:
                changes.update(reason=None, missing=[])
            return self._write(sid, self._next_review(info, **changes), by)

    def set_instance(
        self,
        sid: str,
        key: str,
        status: str,
        *,
        by: str | None = None,
        seen: SceneInfo | None = None,
    ) -> Review:
        """Accept or reject one instance of a scene (``seen``: as :meth:`set_scene`)."""
        with self._changing(sid, seen, by) as info:
            instances = dict(info.review.instances)
            instances[key] = ReviewStatus(status)
            return self._write(sid, self._next_review(info, instances=instances), by)

    def toggle_instance(self, sid: str, key: str, *, by: str | None = None) -> ReviewStatus:
        """Flip one instance between accepted and rejected; return its new status."""
        with self._changing(sid) as info:
            new = (
                ReviewStatus.ACCEPTED
                if info.instance_status(key) == ReviewStatus.REJECTED
                else ReviewStatus.REJECTED
            )
            self.set_instance(sid, key, new, by=by)
            return new

    def mark_missing(
        self,
        sid: str,
        camera: str,
        pixel: tuple[float, float],
        *,
        by: str | None = None,
        seen: SceneInfo | None = None,
    ) -> Review:
        """Record "a part has no pose here" at ``pixel`` of ``camera``: the scene is rejected
        with that reason (``seen``: as :meth:`set_scene`)."""
        with self._changing(sid, seen, by) as info:
            mark = MissingPart(camera, (round(pixel[0], 1), round(pixel[1], 1)), now_iso())
            return self._write(
                sid,
                self._next_review(
                    info,
                    status=ReviewStatus.REJECTED,
                    reason=NO_POSE_REASON,
                    missing=[*info.review.missing, mark],
                ),
                by,
            )

    # ------------------------------------------------------------ pose edits
    def set_pose(
        self,
        sid: str,
        key: str,
        T: object,
        steps: list[RepairStep | dict],
        *,
        by: str | None = None,
        unmark: tuple[str, tuple[float, float]] | None = None,
        expect: object = ANY,
    ) -> Review:
        """Save a repaired pose of instance ``key`` (see :meth:`stage_pose`) at once."""
        return self.commit(self.stage_pose(sid, key, T, steps, by=by, unmark=unmark, expect=expect))

    def stage_pose(
        self,
        sid: str,
        key: str,
        T: object,
        steps: list[RepairStep | dict],
        *,
        by: str | None = None,
        unmark: tuple[str, tuple[float, float]] | None = None,
        expect: object = ANY,
    ) -> Staged:
        """A repaired pose of instance ``key`` (``T``: 4x4 ``cam_T_model``, reference
        camera) made by ``steps`` from its auto pose, in memory until :meth:`commit`.
        ``unmark``: the "no pose here" mark (camera, pixel) the instance was added at, which
        it now explains (the scene goes back to pending when that was the only reason it
        was rejected). ``expect``: the part's edit ``T`` was computed from (None: its auto
        pose); :class:`Conflict` if the file holds another one now."""
        M = np.asarray(T, float)
        with self._changing(sid) as info:
            self._check_expected(info, key, expect, "change", by)
            auto = info.auto_pose(key)
            edit = EditedPose(
                R=M[:3, :3].copy(),
                t=M[:3, 3].copy(),
                steps=[as_step(step) for step in steps],
                decided_by=by,
                at=now_iso(),
                auto_fingerprint=None if auto is None else instance_fingerprint(auto),
            )
            review = self._next_review(info)
            review.poses[key] = edit
            if unmark is not None:
                self._unmark(review, *unmark)
            return self._stage(sid, info, review, by)

    @staticmethod
    def _unmark(review: Review, camera: str, pixel: tuple[float, float]) -> None:
        keep = [
            m
            for m in review.missing
            if not (
                m.camera == camera
                and abs(m.pixel[0] - pixel[0]) < 0.05 + 1e-9
                and abs(m.pixel[1] - pixel[1]) < 0.05 + 1e-9
            )
        ]
        if len(keep) < len(review.missing):
            review.missing = keep
            if not keep and review.reason == NO_POSE_REASON:
                review.status, review.reason = ReviewStatus.PENDING, None

    def restore_pose(
        self,
        sid: str,
        key: str,
        edit: EditedPose | None,
        *,
        by: str | None = None,
        expect: object = ANY,
    ) -> Review:
        """Put back an earlier state of instance ``key``'s edit at once (see
        :meth:`stage_restore`)."""
        return self.commit(self.stage_restore(sid, key, edit, by=by, expect=expect))

    def stage_restore(
        self,
        sid: str,
        key: str,
        edit: EditedPose | None,
        *,
        by: str | None = None,
        expect: object = ANY,
    ) -> Staged:
        """An earlier state of instance ``key``'s edit (None: no edit, the auto pose), for
        undo, redo and reset, in memory until :meth:`commit`. ``expect``: the edit it
        replaces (an undo: the page's own step); :class:`Conflict` if the file holds
        another one now."""
        with self._changing(sid) as info:
            self._check_expected(info, key, expect, "undo, redo or reset", by)
            review = self._next_review(info)
            if edit is None:
                review.poses.pop(key, None)
            else:
                review.poses[key] = edit
            return self._stage(sid, info, review, by)

    def _stage(self, sid: str, info: SceneInfo, review: Review, by: str | None) -> Staged:
        """Hold ``review`` as the scene's state in memory; both locks stay taken (by this
        thread) until :meth:`commit`, so that no other write comes in between."""
        if info.gone or self.is_gone(sid):  # as _write would say, before anything is shown
            raise SaveError(
                f"{self._scenes[sid].review_path.parent}: the scene's folder is gone "
                "(deleted or moved)"
            )
        edits = apply_edits(list(info.auto), review, added=added)
        staged = Staged(
            sid,
            review,
            replace(
                info,
                poses=tuple(edits.poses),
                review=review,
                stale=review.is_stale(info.fingerprint) or bool(edits.stale),
                edited=frozenset(edits.edited),
                stale_edits=frozenset(edits.stale),
                view=view_key(edits.poses, info.shown, info.frames),
            ),
            by,
        )
        self._lock.acquire()
        self._flocks.hold(sid, self._scenes[sid].path)
        self._staged[sid] = staged
        return staged

    def commit(self, staged: Staged) -> Review:
        """Write a staged edit (:meth:`stage_pose`); on a SaveError the scene is as the file
        says again. Called once per staged edit, by the thread that staged it."""
        try:
            with self._lock:
                try:
                    return self._write(staged.sid, staged.review, staged.by, decision=False)
                finally:
                    if self._staged.get(staged.sid) is staged:
                        del self._staged[staged.sid]
        finally:
            self._flocks.release(staged.sid)
            self._lock.release()

    # ----------------------------------------------------------- summaries
    def matches(self, sid: str, flt: str) -> bool:
        info = self.info(sid)
        return {
            "all": True,
            "pending": info.status == ReviewStatus.PENDING or info.stale,
            "flagged": info.flagged,
            "rejected": info.status == ReviewStatus.REJECTED,
            "stale": info.stale,
        }[flt]

    def progress(self) -> tuple[int, int]:
        """(scenes with a current decision, total)."""
        return sum(self.info(sid).decided for sid in self.ids), len(self.ids)

    def pace(self) -> float:
        """Decisions per minute made through this server."""
        minutes = max((time.time() - self.started) / 60.0, 1e-6)
        return self.decided / minutes
