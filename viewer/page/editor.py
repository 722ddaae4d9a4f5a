"""The repairs of one review page: nudges, the gizmo, R's refinement (in a thread of its
own), A's candidate poses (the next one made ahead in the background), adding a part where
the reviewer clicked, and per-scene undo and redo of the page's own steps.

Every change is shown first (the scene's overlays re-rendered only where it changed,
:func:`viewer.drawing.overlays.repose`), then written to review.json before the key is done with and
the next change is made (:meth:`annotator.review.state.ReviewState.stage_pose`, then ``commit``); one
that cannot be written is said so in red and taken back. Each change names the edit it was
computed from, so one made on a pose that another page or server has changed since is
refused and said (:class:`annotator.review.scenes.Conflict`), never written over theirs; undo and redo
only undo the page's own steps, while each is still its part's last change.

The editor needs of its page only what :class:`EditorPage` lists, so it is tested with a
fake page on a real :class:`~annotator.review.state.ReviewState`.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from enum import Enum
from typing import Protocol

import numpy as np

from annotator.dataset.review import EditedPose, RepairOp, RepairStep
from annotator.repair import NudgeKind
from annotator.review import Conflict, SaveError, SceneInfo, Staged
from viewer.drawing.overlays import Prepared, repose
from viewer.page import repair
from viewer.page.host import ReviewHost

AHEAD_WAIT = 1.0  # seconds a repair waits for its overlays being made ahead, at most
#: seconds work ahead waits after a key's pixels went out: the browser draws them meanwhile
#: (on two cores the work would slow that down), and a next key in between makes it moot
AHEAD_DELAY = 0.3


@dataclass(frozen=True)
class Step:
    """One repair of this page, for undo and redo: ``key``'s edit before and after it
    (None: the auto pose)."""

    key: str
    before: EditedPose | None
    after: EditedPose | None


@dataclass(frozen=True)
class Offer:
    """The instances without a pose offered after M and a click: "Add here" starts one at
    ``pixel`` of ``camera`` in ``scene``."""

    scene: str
    camera: str
    pixel: tuple[float, float]
    instances: tuple[str, ...]


class Unsaved(Enum):
    """Why a pose change was not written."""

    FAILED = "failed"  # the file could not be written: the same change may be tried again
    CONFLICT = (
        "conflict"  # another reviewer changed the part first (annotator.review.scenes.Conflict)
    )


class EditorPage(Protocol):
    """What the repair editor needs of its page (:class:`viewer.page.session.Session`)."""

    @property
    def id(self) -> str: ...  # the page's id, recorded as ``decided_by``
    @property
    def host(self) -> ReviewHost: ...
    @property
    def closed(self) -> bool: ...

    def cursor(self) -> tuple[str | None, str | None]:
        """The scene the cursor is on and its selected instance."""
        ...

    def info(self, sid: str) -> SceneInfo:
        """Scene ``sid`` as the page shows it now (a sequence: with the page's frames)."""
        ...

    def shown_scene(self, what: str) -> str | None:
        """The scene a change ``what`` is for (None, and the reviewer told, if the page
        was still switching)."""
        ...

    def prepared_scene(self) -> Prepared | None:
        """The overlays of the scene shown."""
        ...

    def write(self, sid: str, what: str, fn: Callable[[], object], *, decision: bool) -> bool:
        """Run a write; on failure the page shows it and keeps the scene unsaved."""
        ...

    def not_saved(self, sid: str, what: str, why: str) -> None: ...
    def show_repair(self, text: str, nudges: str) -> None: ...
    def focus(self, key: str, *, zoom: bool | None = None) -> None: ...
    def request_render(self) -> None: ...


class RepairEditor:
    """The repair keys of one page (see the module docstring)."""

    def __init__(self, page: EditorPage) -> None:
        self.page = page
        self.host = page.host
        self._lock = threading.Lock()  # the stacks, the offer, the cycles, the text below
        self.nudge_kind = NudgeKind.MOVE
        self.large = False
        # Per scene, the page's steps: undone ones move from history to future and back.
        self.history: dict[str, list[Step]] = {}
        self.future: dict[str, list[Step]] = {}
        self.repair_text = ""  # what the last repair did, for the panel
        self.offer: Offer | None = None
        self._cycle: dict[tuple[str, str, str], tuple[list, int]] = {}
        self._refining = threading.Lock()
        # One pose change at a time: each is written before the next is made.
        self._editing = threading.RLock()
        # Work for the next key, done once its pixels are out (one job at a time).
        self._ahead_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ahead")
        self._ahead_for: tuple[str, str, str] | None = None
        self._ahead_done = threading.Condition()
        self._ahead_making: str | None = None  # the view the job is making overlays of

    def close(self) -> None:
        """The page has gone: no more work ahead."""
        self._ahead_pool.shutdown(wait=False, cancel_futures=True)

    def say(self, text: str) -> None:
        """Show what a repair did (or is doing) in the panel at once."""
        with self._lock:
            self.repair_text = text
        self.page.show_repair(text, self.nudge_text())

    def nudge_text(self) -> str:
        """The nudges' current kind and size, for the panel."""
        size = (
            (f"{repair.LARGE_MM:g} mm" if self.large else f"{repair.SMALL_MM:g} mm")
            if self.nudge_kind == NudgeKind.MOVE
            else (f"{repair.LARGE_DEG:g}°" if self.large else f"{repair.SMALL_DEG:g}°")
        )
        return f"nudges (1-6): **{self.nudge_kind}** by {size} in the reference camera's axes"

    def _target(self, what: str) -> tuple[str, str] | None:
        """The scene shown and its selected instance, for a repair ``what``."""
        _, key = self.page.cursor()
        if key is None:
            self.say("select an instance first (click it, or I)")
            return None
        sid = self.page.shown_scene(f"{what} {key}")
        if sid is None or self.page.info(sid).pose(key) is None:
            return None
        return sid, key

    def _edit(
        self,
        sid: str,
        key: str,
        T: np.ndarray,
        step: RepairStep,
        *,
        seen: SceneInfo,
        unmark: tuple[str, tuple[float, float]] | None = None,
    ) -> bool:
        """Show a new pose of ``key`` (``step`` added to its edit's steps), then save it.
        ``seen``: the scene as it was when ``T`` was computed; if another page has changed
        that part since, nothing is written and this reviewer is told."""
        state = self.host.state
        before = seen.review.poses.get(key)
        steps = list(before.steps) if before is not None and key in seen.edited else []
        with self._editing:
            after = self._show_then_save(
                sid,
                key,
                f"pose of {key}",
                lambda: state.stage_pose(
                    sid, key, T, [*steps, step], by=self.page.id, unmark=unmark, expect=before
                ),
                self.page.info(sid).view,
            )
            if isinstance(after, Unsaved):
                return False
            with self._lock:
                self.history.setdefault(sid, []).append(Step(key, before, after))
                self.future.pop(sid, None)
            return True

    def _restore(
        self, sid: str, key: str, edit: EditedPose | None, what: str, *, expect: object
    ) -> EditedPose | None | Unsaved:
        """Put ``key``'s edit back to ``edit`` if it is still ``expect``: the edit written
        (None: the auto pose), or why not."""
        state = self.host.state
        with self._editing:
            return self._show_then_save(
                sid,
                key,
                what,
                lambda: state.stage_restore(sid, key, edit, by=self.page.id, expect=expect),
                self.page.info(sid).view,
            )

    def _show_then_save(
        self, sid: str, key: str, what: str, stage: Callable[[], Staged], shown: str
    ) -> EditedPose | None | Unsaved:
        """Make a pose change in memory (``stage``), send its pixels, then write it: the
        reviewer sees it before the disk has it, and it is on disk before this returns (and
        so before the next change is made). A change that cannot be written is said so in
        red, and the page goes back to what the file holds. Returns ``key``'s edit as
        written (None: the auto pose), or why it was not."""
        try:
            staged = stage()
        except SaveError as exc:
            self.page.not_saved(sid, what, str(exc))
            return Unsaved.CONFLICT if isinstance(exc, Conflict) else Unsaved.FAILED
        try:
            self._reposed(sid, key, shown)
        finally:  # whatever showing it did, the change is written
            saved = self.page.write(
                sid, what, lambda: self.host.state.commit(staged), decision=False
            )
        return staged.review.poses.get(key) if saved else Unsaved.FAILED

    def _reposed(self, sid: str, key: str, before: str) -> None:
        """Make the scene's overlays for its new poses from the shown ones (only the
        changed rectangles cast again; ``before``: the version they show), then show them."""
        info = self.page.info(sid)
        prep = self.page.prepared_scene()
        with self._ahead_done:  # being made ahead (A came quickly): sooner done than redone
            self._ahead_done.wait_for(lambda: self._ahead_making != info.view, AHEAD_WAIT)
        if self.host.cache.ready((sid, info.view)):  # poses shown before (undo, redo, A)
            prep = None
        ds = self.host.state.view(sid, info)[0]
        # A sequence's page may show other frames by now (P): then the scene is prepared anew.
        same_cameras = prep is not None and {la.name for la in prep.layers} == {
            c.name for c in ds.rig.cameras
        }
        if (
            prep is not None
            and prep.scene_id == sid
            and same_cameras
            and key in {p.key for p in info.poses}
        ):
            new = repose(ds, prep, list(info.poses), key)
            if new is not None:
                self.host.reposed(sid, info, new, before=before)
        self.page.request_render()

    def refine(self) -> None:
        """R: refine the selected instance in a thread of its own (the page says so)."""
        target = self._target("refine")
        if target is None:
            return
        sid, key = target
        if not self._refining.acquire(blocking=False):
            self.say("a refinement is already running")
            return
        self.say(f"refining {key}: ICP against the depth and its markers…")
        threading.Thread(target=self._refine, args=(sid, key), daemon=True).start()

    def _refine(self, sid: str, key: str) -> None:
        try:
            state = self.host.state
            seen = self.page.info(sid)
            inputs = self.host.repair_inputs(sid, seen)
            result = repair.refine(state.view(sid, seen)[0], seen, key, inputs)
            residuals = f"before: {result.before.text()}; after: {result.after.text()}"
            if result.converged:
                if self._edit(sid, key, result.T, result.step(), seen=seen):
                    self.say(f"✔ {key} refined in {result.seconds:.2f} s — {residuals}")
            else:
                self.say(
                    f"<span style='color:#d00'>⚠ {key}: the refinement did not converge "
                    f"({result.why}); the pose is kept</span> — {residuals}"
                )
        except Exception as exc:  # the page stays usable; the reviewer is told
            self.say(f"⚠ {key}: cannot refine ({type(exc).__name__}: {exc})")
        finally:
            self._refining.release()

    def alternative(self) -> None:
        """A: the selected instance's next candidate pose."""
        with self._editing:  # after the page's previous key is written, from what it left
            self._alternative()

    def _alternative(self) -> None:
        target = self._target("alternative for")
        if target is None:
            return
        sid, key = target
        info = self.page.info(sid)
        auto = info.auto_pose(key)
        ck, found, index = self._candidates(sid, key, info)
        if len(found) < 2:
            self.say(f"{key}: no other candidate pose from its markers")
            return
        index = (index + 1) % len(found)
        with self._lock:
            self._cycle[ck] = (found, index)
        c = found[index]
        if index == 0 and auto is not None:
            before = info.review.poses.get(key)
            done = self._restore(sid, key, None, f"pose of {key}", expect=before)
            saved = not isinstance(done, Unsaved)
            if saved:
                with self._lock:
                    self.history.setdefault(sid, []).append(Step(key, before, None))
                    self.future.pop(sid, None)
        else:
            step = RepairStep(RepairOp.ALTERNATIVE, {"source": c.source, "support": c.support})
            saved = self._edit(sid, key, c.T, step, seen=info)
        if saved:
            self.say(f"{key}: candidate {index + 1} of {len(found)} — {c.text()}")

    def _candidates(
        self, sid: str, key: str, info: SceneInfo
    ) -> tuple[tuple[str, str, str], list, int]:
        """The candidate poses of ``key`` A cycles through (made once per auto pose) and the
        index of the one shown last, with the key they are kept under."""
        auto = info.auto_pose(key)
        ck = (sid, key, "" if auto is None else str(auto.T.tobytes()))
        with self._lock:
            hit = self._cycle.get(ck)
        if hit is None:
            state = self.host.state
            found = repair.candidates(
                state.view(sid, info)[0], info, key, self.host.repair_inputs(sid, info)
            )
            with self._lock:
                hit = self._cycle.setdefault(ck, (found, 0))
        return ck, *hit

    def work_ahead(self, sid: str, key: str, info: SceneInfo) -> None:
        """Once the pixels are out, in the background: what the next A on the selected
        instance needs (the scene's markers read, the instance's candidates, the overlays
        of the next one), so that the key only shows it. Once per poses shown."""
        job = (sid, key, info.view)
        with self._lock:
            if job == self._ahead_for or self.page.closed:
                return
            self._ahead_for = job
        self._ahead_pool.submit(self._prepare_alternative, sid, key, info)

    def _still_on(self, sid: str, key: str) -> bool:
        """Whether the page is still on instance ``key`` of scene ``sid`` (work ahead for it
        is of no use once the reviewer has gone on, and would slow down what they do)."""
        return self.page.cursor() == (sid, key) and not self.page.closed

    def _prepare_alternative(self, sid: str, key: str, info: SceneInfo) -> None:
        try:
            time.sleep(AHEAD_DELAY)
            if not self._still_on(sid, key) or self.page.info(sid).view != info.view:
                return  # another key came meanwhile: its own render asks again
            if info.pose(key) is None or not self.host.cache.ready((sid, info.view)):
                return
            prep = self.host.prepared(sid, info)  # the overlays shown, made already
            if not self._still_on(sid, key):
                return
            _, found, index = self._candidates(sid, key, info)
            if len(found) < 2 or self.page.info(sid).view != info.view:
                return  # nothing to cycle through, or the poses changed meanwhile
            if not self._still_on(sid, key):
                return
            poses, view = info.with_pose(key, found[(index + 1) % len(found)].T)
            if not self.host.cache.ready((sid, view)):
                with self._ahead_done:
                    self._ahead_making = view
                ds = self.host.state.view(sid, info)[0]  # the frames ``prep`` shows
                new = repose(ds, prep, poses, key, parallel=False)
                if new is not None:
                    self.host.ahead(sid, view, new)
        except Exception as exc:  # only a head start: A makes it itself then
            print(f"review: {self.page.id}: could not prepare A ahead: {exc}", file=sys.stderr)
        finally:
            with self._ahead_done:
                self._ahead_making = None
                self._ahead_done.notify_all()

    def nudge(self, axis: int, sign: int) -> None:
        """Move or turn the selected instance by one step along / about a camera axis."""
        target = self._target("nudge")
        if target is None:
            return
        sid, key = target
        step = repair.step_of(self.nudge_kind, axis, sign, self.large)
        with self._editing:  # from the pose the page's previous key left, however soon
            info = self.page.info(sid)
            T = repair.nudge(self.host.state.view(sid, info)[0], info, key, step)
            saved = self._edit(sid, key, T, step.step(), seen=info)
        if saved:
            unit = "mm" if step.kind == "move" else "°"
            self.say(f"{key}: {step.kind} {step.amount:+g} {unit} along {'xyz'[axis]}")

    def gizmo(self, key: str, T) -> None:
        """The gizmo in the 3D view was let go: ``T`` is the part's new pose."""
        sid, _ = self.page.cursor()
        if sid is None:
            return
        with self._editing:
            info = self.page.info(sid)
            if info.pose(key) is None:
                return
            saved = self._edit(sid, key, T, RepairStep(RepairOp.GIZMO), seen=info)
        if saved:
            self.say(f"{key}: moved with the gizmo")

    def toggle_nudge_kind(self) -> None:
        move = self.nudge_kind == NudgeKind.MOVE
        self.nudge_kind = NudgeKind.TURN if move else NudgeKind.MOVE
        self.say(self.repair_text)

    def toggle_nudge_size(self) -> None:
        self.large = not self.large
        self.say(self.repair_text)

    def _step_back(self, back: bool) -> None:
        with self._editing:  # the page's previous key is written and in its history first
            self._step_back_now(back)

    def _step_back_now(self, back: bool) -> None:
        what = "undo" if back else "redo"
        sid, _ = self.page.cursor()
        sid = self.page.shown_scene(what) if sid is not None else None
        if sid is None:
            return
        with self._lock:
            source = (self.history if back else self.future).get(sid, [])
            if not source:
                self.repair_text = f"nothing to {what} in this scene"
                item = None
            else:
                item = source.pop()
        if item is None:
            self.say(self.repair_text)
            return
        # Only this page's own step, while it is still the part's last change: an undo
        # never throws away what another reviewer did to the part since.
        edit, expect = (item.before, item.after) if back else (item.after, item.before)
        done = self._restore(sid, item.key, edit, f"{what} of {item.key}", expect=expect)
        if done is Unsaved.CONFLICT:
            return  # another reviewer's change came after it: the step is gone
        with self._lock:
            if done is Unsaved.FAILED:
                source.append(item)  # the disk refused it: it may be tried again
                return
            (self.future if back else self.history).setdefault(sid, []).append(item)
        self.page.focus(item.key)
        self.say(f"{what}: {item.key} " + ("back to its auto pose" if edit is None else "restored"))

    def undo(self) -> None:
        self._step_back(True)

    def redo(self) -> None:
        self._step_back(False)

    def reset_pose(self) -> None:
        """X: the selected instance back to its auto pose (an added one is removed)."""
        with self._editing:  # after the page's previous key is written, from what it left
            self._reset_pose()

    def _reset_pose(self) -> None:
        target = self._target("reset")
        if target is None:
            return
        sid, key = target
        before = self.page.info(sid).review.poses.get(key)
        if before is None:
            self.say(f"{key} has its auto pose already")
            return
        done = self._restore(sid, key, None, f"reset of {key}", expect=before)
        if not isinstance(done, Unsaved):
            with self._lock:
                self.history.setdefault(sid, []).append(Step(key, before, None))
                self.future.pop(sid, None)
            self.say(f"{key}: reset to the auto-annotation")

    def add_missing(self, key: str) -> None:
        """ "Add here": start instance ``key`` where M was clicked."""
        with self._lock:
            offer = self.offer
        if offer is None or key not in offer.instances:
            return
        sid, camera, pixel = offer.scene, offer.camera, offer.pixel
        if self.page.shown_scene(f"add {key}") != sid:
            return
        state = self.host.state
        info = self.page.info(sid)
        found = repair.start(
            state.view(sid, info)[0], info, key, camera, pixel, self.host.repair_inputs(sid, info)
        )
        if found is None:
            self.say(f"⚠ {key}: no marker and no depth near the click to start it from")
            return
        step = RepairStep(
            RepairOp.ADD, {"camera": camera, "pixel": list(pixel), "source": found.source}
        )
        if self._edit(sid, key, found.T, step, seen=info, unmark=(camera, pixel)):
            with self._lock:
                self.offer = None
            self.page.focus(key, zoom=True)
            self.say(f"{key} added ({found.text()}): R refines it")
