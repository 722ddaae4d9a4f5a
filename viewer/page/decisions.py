"""What one page's keys decide: accept or reject the scene shown, or one of its parts
(Y, N, T), a sequence's frames (P, H), a place where a part has no pose (M and a click), and
what the page is told when another reviewer decided over it.

Decisions go to the shared :class:`~annotator.review.state.ReviewState` (review.json,
atomically). A decision that cannot be written is shown in this page at once, in red, and
the page stays on the scene, whose status remains the one on disk. When another page (or
another server) decides a scene this page decided, the later decision is kept and this page
is told.

A decision is for the scene the page shows (:attr:`PageDecisions.displayed`: the last one
whose panel and pictures were sent), never merely the one the cursor is on: a key pressed
while the page is still switching (the cursor has moved, the new scene is not sent yet) is
refused and said so in red, as is a decision for a scene whose folder has gone.

:class:`PageDecisions` is the second layer of :class:`viewer.page.session.Session`, over
:class:`viewer.page.rendering.PageRendering`: the attributes it declares are the session's.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import viser

from annotator.dataset.review import ReviewStatus
from annotator.review import SaveError, SceneInfo
from viewer.page import repair
from viewer.page.editor import Offer, RepairEditor
from viewer.page.host import ReviewHost
from viewer.page.navigation import Navigator
from viewer.page.rendering import PageRendering

__all__ = ["PageDecisions"]

_MAX_ALERTS = 3


class PageDecisions(PageRendering):
    """The decisions part of a page (see the module docstring)."""

    app: ReviewHost
    client: viser.ClientHandle
    id: str
    nav: Navigator
    editor: RepairEditor
    armed: bool
    unsaved: dict[str, str]
    _unsaved_notes: dict[str, viser.NotificationHandle]
    alerts: list[tuple[float, str]]
    mine: dict[str, ReviewStatus]
    displayed_info: SceneInfo | None
    frames_at: dict[str, int]
    _lock: threading.RLock

    def not_saved(self, sid: str, what: str, why: str) -> None:
        """Tell this reviewer, in red, that their decision about ``sid`` is not saved."""
        msg = f"scene {sid}: your decision ({what}) is NOT saved: {why}"
        note = self.client.add_notification(
            "Decision not saved", msg, color="red", with_close_button=True
        )
        with self._lock:
            self.unsaved[sid] = msg
            old = self._unsaved_notes.pop(sid, None)
            self._unsaved_notes[sid] = note
        if old is not None:
            old.remove()
        self.request_render()

    def shown_scene(self, what: str) -> str | None:
        """The scene a decision ``what`` is for: the one the page shows, if the cursor is
        on it. Else None, and the reviewer is told: the page was still switching, and the
        decision was made looking at another scene."""
        with self._lock:
            sid, shown = self.nav.current, self.displayed
        if sid is None or sid == shown:
            return sid
        showing = "no scene yet" if shown is None else f"scene {shown}"
        self.not_saved(
            sid,
            what,
            f"the page was still showing {showing} when you decided; "
            "look at this one, then decide again",
        )
        return None

    @property
    def displayed(self) -> str | None:
        """The scene whose panel and pictures were sent last."""
        with self._lock:
            return None if self.displayed_info is None else self.displayed_info.id

    def seen(self, sid: str) -> SceneInfo | None:
        """Scene ``sid`` as this page's panel and pictures last showed it (what a decision
        about it is a decision about), or None if they show another."""
        with self._lock:
            info = self.displayed_info
        return info if info is not None and info.id == sid else None

    def write(self, sid: str, what: str, fn: Callable[[], Any], *, decision: bool = True) -> bool:
        """Run a write; on failure show it in this page and keep the scene unsaved."""
        try:
            review = fn()
        except SaveError as exc:
            self.not_saved(sid, what, str(exc))
            return False
        with self._lock:
            self.unsaved.pop(sid, None)
            note = self._unsaved_notes.pop(sid, None)
            if decision:
                self.mine[sid] = review.status
        if note is not None:  # saved now: the red notice would only mislead
            note.remove()
        self.app.changed(self, {sid})
        return True

    def _decide(self, status: ReviewStatus) -> None:
        sid = self.shown_scene(str(status))
        if sid is None:
            return
        seen = self.seen(sid)
        if self.write(
            sid,
            str(status),
            lambda: self.app.state.set_scene(sid, status, by=self.id, seen=seen),
        ):
            with self._lock:
                if self.nav.current == sid:
                    self.nav.after_decision()
        self.request_render()

    def accept(self) -> None:
        self._decide(ReviewStatus.ACCEPTED)

    def reject(self) -> None:
        self._decide(ReviewStatus.REJECTED)

    def set_instance(self, status: ReviewStatus) -> None:
        with self._lock:
            key = self.nav.selected
        if key is None:
            return
        sid = self.shown_scene(f"{key} {status}")
        if sid is None:
            return
        seen = self.seen(sid)
        self.write(
            sid,
            f"{key} {status}",
            lambda: self.app.state.set_instance(sid, key, status, by=self.id, seen=seen),
        )
        self.request_render()

    def toggle_instance(self) -> None:
        with self._lock:
            sid, key = self.nav.current, self.nav.selected
        if sid is None or key is None:
            return
        new = (
            ReviewStatus.ACCEPTED
            if self.info(sid).instance_status(key) == ReviewStatus.REJECTED
            else ReviewStatus.REJECTED
        )
        self.set_instance(new)

    def next_frames(self) -> None:
        self._shift_frames(+1)

    def previous_frames(self) -> None:
        self._shift_frames(-1)

    def _shift_frames(self, step: int) -> None:
        """This page shows the sequence's frames ``step`` on (the pictures of every frame
        shown are made again; a repair made meanwhile is in the scene frame, so in all).
        Other pages keep their own frames."""
        with self._lock:
            sid = self.nav.current
        if sid is None or not self.info(sid).shown:
            return
        with self._lock:
            self.frames_at[sid] = self.frames_at.get(sid, 0) + step
        self.request_render()

    def toggle_frame(self) -> None:
        """Reject the first frame this page shows on its own, or take the rejection back."""
        sid = self.shown_scene("frame")
        seen = self.seen(sid) if sid is not None else None
        if sid is None or seen is None or not seen.shown:
            return
        frame = seen.shown[0]
        self.write(
            sid,
            f"frame {frame}",
            lambda: self._toggle_frame(sid, frame, seen),
            decision=False,
        )
        self.request_render()

    def _toggle_frame(self, sid: str, frame: str, seen: SceneInfo) -> Any:
        self.app.state.toggle_frame(sid, frame, by=self.id, seen=seen)
        return self.app.state.info(sid).review

    def arm_missing(self) -> None:
        with self._lock:
            self.armed = not self.armed
        self.request_render()

    def _mark_missing(self, camera: str, x: float, y: float) -> None:
        with self._lock:
            self.armed = False
        sid = self.shown_scene(f"no pose at {camera} ({x:.0f}, {y:.0f})")
        if sid is None:
            return
        seen = self.seen(sid)
        saved = self.write(
            sid,
            f"no pose at {camera} ({x:.0f}, {y:.0f})",
            lambda: self.app.state.mark_missing(sid, camera, (x, y), by=self.id, seen=seen),
        )
        info = self.info(sid)
        keys = repair.unposed(self.app.state.view(sid, info)[0], info)
        if saved and keys:
            mark = info.review.missing[-1]
            with self._lock:
                self.editor.offer = Offer(sid, mark.camera, mark.pixel, tuple(keys))
        self.request_render()

    def on_changed(self, sids: set[str]) -> None:
        """Scenes decided elsewhere (another page, another server): tell this reviewer if
        one of them was theirs, and show the shared progress."""
        told = []
        for sid in sorted(sids):
            with self._lock:
                mine = self.mine.get(sid)
            if mine is None:
                continue
            review = self.app.state.info(sid).review
            if review.decided_by == self.id:
                continue
            with self._lock:
                self.mine.pop(sid, None)
                msg = (
                    f"scene {sid} was decided after you by another reviewer: now "
                    f"{review.status} (yours: {mine}); the later decision is kept"
                )
                self.alerts = (self.alerts + [(time.monotonic(), msg)])[-_MAX_ALERTS:]
            told.append(msg)
        for msg in told:
            self.client.add_notification(
                "Scene decided by another reviewer", msg, color="orange", auto_close_seconds=20.0
            )
        self.request_render()
