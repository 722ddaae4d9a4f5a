"""One browser page: its own cursor (:class:`~viewer.navigation.Navigator`), control panel,
pictures and 3D canvas, and what its buttons, hotkeys and clicks do.

Decisions go to the shared :class:`~viewer.state.ReviewState` (review.json, atomically).
A decision that cannot be written is shown in this page at once, in red, and the page stays
on the scene, whose status remains the one on disk. When another page (or another server)
decides a scene this page decided, the later decision is kept and this page is told.

Showing a scene is coalesced: actions only move the cursor and ask for a render; one render
runs at a time and always shows the latest state, so a held key skips scenes instead of
queueing them. The pictures and the panel go out first; the 3D view follows (and only
while it is shown).

A decision is for the scene the page shows (:attr:`Session.displayed`: the last one whose
panel and pictures were sent), never merely the one the cursor is on: a key pressed while
the page is still switching (the cursor has moved, the new scene is not sent yet) is refused
and said so in red, as is a decision for a scene whose folder has gone. A scene that cannot
be shown (its folder gone, an unexpected failure) is named in the page, without the
pictures of the scene shown before it, and its failure is one line in the server's log.

Repairing a pose (R, A, the nudges, the gizmo, M + click + "Add here", U, X) shows the new
pose re-rendered only where it changed (:func:`viewer.overlays.repose`), then saves it in
review.json (staged in memory first: :meth:`ReviewState.stage_pose`), before the key is done
with and the next change is made; one that cannot be written is said so in red and taken
back. Each change names the edit it was computed from, so one made on a pose that another
page or server has changed since is refused and said (:class:`viewer.state.Conflict`),
never written over theirs. Undo and redo are per page and scene, and undo only the page's
own steps, while each is still its part's last change. A
refinement runs in its own thread, the page saying so meanwhile. Once the pixels of a
selected instance are out, what the next A needs is made in the background (the scene's
markers read, the candidates, the overlays of the next one): A then only shows it, as U does.

The pictures are made for the page's canvas, within an 8K screen
(:func:`viewer.memory.clamp_viewport`); when the page closes, what it held is dropped.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING

import numpy as np
import viser

from annotator.dataset.review import EditedPose, RepairOp, RepairStep, ReviewStatus
from annotator.repair import NudgeKind
from viewer import repair
from viewer.memory import picture_size
from viewer.mosaic import Picture, compose
from viewer.navigation import Navigator
from viewer.overlays import Prepared, repose
from viewer.panel import Panel, PanelView, instance_table, warnings_text
from viewer.pictures import Pictures
from viewer.scene3d import Scene3D
from viewer.state import FILTERS, Conflict, SaveError, SceneInfo, Staged
from viewer.style import Look
from viewer.zoom import Zoom, zoom

if TYPE_CHECKING:
    from viewer.app import ReviewApp

DEFAULT_VIEWPORT = (1280, 960)
#: How long a page's closing waits for its render under way (it is dropped after it).
CLOSE_WAIT_SECONDS = 10.0
_MAX_ALERTS = 3
ALERT_SECONDS = 60.0  # how long the panel repeats another reviewer's overriding decision
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
    CONFLICT = "conflict"  # another reviewer changed the part first (viewer.state.Conflict)


class Session:
    """The review page of one browser client."""

    def __init__(self, app: ReviewApp, client: viser.ClientHandle) -> None:
        self.app = app
        self.client = client
        self.id = f"page-{app.tag}-{client.client_id}"
        self.nav = Navigator(app.state)
        self._lock = threading.RLock()  # the cursor and the flags below
        self.fill = False
        self.armed = False
        self.unsaved: dict[str, str] = {}  # scene -> why its decision is not saved
        self._unsaved_notes: dict[str, viser.NotificationHandle] = {}
        self.alerts: list[tuple[float, str]] = []  # other reviewers' decisions over ours
        self.mine: dict[str, ReviewStatus] = {}  # scenes this page decided last
        self.viewport = self._viewport(None)
        self.displayed: str | None = None  # the scene whose panel and pictures were sent last
        self._render_lock = threading.Condition()
        self._dirty = False
        self._rendering = False
        self._closed = False
        self._shown: tuple | None = None  # what the mosaic was made for
        self._shown_zoom: tuple | None = None  # what the zoom was made for
        self._on_canvas: tuple | None = None  # which picture is shown: ("mosaic" | "zoom", ...)
        self._picture: tuple[str, Picture] | None = None
        self._zoom: tuple[str, Zoom] | None = None
        self._prep: Prepared | None = None
        self.blinking = False
        # Repairs: nudge settings, per scene undo / redo stacks of the page's steps (instance,
        # its edit before, its edit after; None: the auto pose), what the last repair did, the
        # instances offered after M + click.
        self.nudge_kind = NudgeKind.MOVE
        self.large = False
        self.history: dict[str, list[Step]] = {}
        self.future: dict[str, list[Step]] = {}
        self.repair_text = ""
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
        self.panel = Panel(client.gui, self)
        self.pictures = Pictures(client.gui, client.scene)
        self.scene = Scene3D(
            client.scene,
            app.state.ds,
            on_part=self.select,
            on_canvas=self.clicked_canvas,
            on_gizmo=self.moved_by_gizmo,
        )
        client.camera.on_update(self._camera_moved)
        # The first render is the app's to ask for, once this page is listed among its pages.

    # --------------------------------------------------------------- viewport
    def _canvas(self) -> tuple[int, int] | None:
        """The page's canvas size as it says (None: it has not said, or nonsense)."""
        try:
            return int(self.client.camera.image_width), int(self.client.camera.image_height)
        except (AssertionError, AttributeError, TypeError, ValueError, OverflowError):
            return None

    def _viewport(self, shown: tuple[int, int] | None) -> tuple[int, int]:
        """The size to make the pictures: the page's canvas, as it says, the pictures being
        ``shown`` at that size (see :func:`viewer.memory.picture_size`)."""
        canvas = self._canvas()
        if canvas is None:
            return DEFAULT_VIEWPORT
        return picture_size(*canvas, shown) or DEFAULT_VIEWPORT

    def _camera_moved(self, _camera: viser.CameraHandle) -> None:
        canvas = self._canvas()
        if canvas is not None:
            self.pictures.canvas_resized(*canvas)
        size = self._viewport(self.viewport)
        if size != self.viewport:  # a pixel off would be a picture scaled, no longer exact
            self.viewport = size
            self.request_render()

    # ---------------------------------------------------------------- render
    def request_render(self) -> None:
        """Show the latest state (now, or right after the render under way)."""
        with self._render_lock:
            self._dirty = True
            if self._rendering or self._closed:
                return
            self._rendering = True
        try:
            while True:
                with self._render_lock:
                    if not self._dirty or self._closed:
                        return
                    self._dirty = False
                try:
                    self._render()
                except Exception as exc:  # the page stays usable; the log gets one line
                    self._failed(exc)
        finally:
            with self._render_lock:
                self._rendering = False
                self._render_lock.notify_all()

    def _failed(self, exc: Exception) -> None:
        if self._closed:  # the page went during the render: nobody to show it to
            return
        with self._lock:
            sid = self.nav.current
        why = f"{type(exc).__name__}: {exc}".splitlines()[0]
        print(f"review: {self.id}: cannot show scene {sid}: {why}", file=sys.stderr)
        if sid is None:
            return
        try:
            self._show_without_pictures(sid, self.app.state.info(sid), f"cannot show it: {why}")
        except Exception:  # the page is gone meanwhile: nothing to tell it
            pass

    def _show_without_pictures(self, sid: str, info: SceneInfo, why: str) -> None:
        """Name scene ``sid`` in the page with ``why`` it is not shown; the pictures of the
        scene shown before are taken off the page, so that none is mistaken for it."""
        with self._lock:
            flt, selected = self.nav.filter, self.nav.selected
            self._picture = self._zoom = self._prep = None
            self._shown = self._shown_zoom = None
            self._on_canvas = ("none", sid)
            self.blinking = False
        self.pictures.clear()
        view = self._panel_view(info, None, flt, selected)
        red = f"<span style='color:#d00'>⛔ {why}</span>"
        view.alert = f"{red}\n\n{view.alert}" if view.alert else red
        self.panel.show(view, [])
        with self._lock:
            self.displayed = sid
        self.client.flush()
        self.pictures.send_background_soon()
        self.scene.show_3d_scene((), Look(), None, (sid, "none"))

    def _render(self) -> None:
        with self._lock:
            sid = self.nav.current
            selected, zoom_open, fill = self.nav.selected, self.nav.zoom, self.fill
            blinking = self.blinking
            flt = self.nav.filter
        if sid is None:
            self.panel.show(PanelView("## No scene in this dataset"), [])
            return
        state = self.app.state
        info = state.info(sid)
        if info.gone:
            self._show_without_pictures(sid, info, f"{info.error}: nothing to decide")
            return
        prep = self.app.prepared(sid, info)  # a failure is shown by request_render
        self._prep = prep
        look = Look.of(info, selected)
        self.viewport = self._viewport(self.viewport)  # the canvas may have changed since
        w, h = self.viewport
        base = (sid, info.view, look, (w, h))
        zkey = (*base, fill) if zoom_open and selected else None
        if selected is not None and zkey is not None and zkey != self._shown_zoom:
            shown = self._zoom[1] if self._zoom is not None and self._zoom[0] == sid else None
            z = zoom(prep, selected, look, w, h, fill=fill, keep=shown)
            self._zoom = (sid, z) if z is not None else None
            self._shown_zoom = zkey if z is not None else None
        if zkey is None or self._zoom is None:
            picture = self._picture
            if base != self._shown or picture is None:
                picture = self._picture = (sid, compose(prep, look, w, h))
                self._shown = base
                self.app.drew()
            if ("mosaic", base) != self._on_canvas:
                self.pictures.show_mosaic(picture[1].image)
                self._on_canvas = ("mosaic", base)
            with self._lock:
                self.blinking = False  # blinking belongs to a zoom
        elif ("zoom", zkey) != self._on_canvas:
            z = self._zoom[1]
            self.pictures.show_zoom(z)
            self._on_canvas = ("zoom", zkey)
        self.pictures.blink(blinking and self._on_canvas[0] == "zoom")
        self.panel.show(self._panel_view(info, prep, flt, selected), [p.key for p in info.poses])
        with self._lock:
            self.displayed = sid
        self.client.flush()  # the new picture is on its way before anything else is done
        self.pictures.send_background_soon()
        self.scene.show_3d_scene(info.poses, look, prep.cloud, (sid, info.fingerprint))
        self.scene.show_gizmo(info.pose(selected) if selected else None)
        if selected and prep.scene_id == sid and info.pose(selected) is not None:
            self._ahead(sid, selected, info)
        with self._lock:
            upcoming = self.nav.upcoming()
        for other in reversed(upcoming):  # the cache starts with the last asked for
            self.app.prefetch(other)

    def _panel_view(
        self, info: SceneInfo, prep: Prepared | None, flt: str, selected: str | None
    ) -> PanelView:
        state = self.app.state
        sid = info.id
        status = "**gone**" if info.gone else f"**{info.status}**"
        status += " (stale: the annotation changed since)" if info.stale else ""
        if info.review.reason:
            status += f" — {info.review.reason}"
        title = f"## Scene {sid}\n{status} · {state.ids.index(sid) + 1} of {len(state.ids)} · filter: {flt}"
        alerts = []
        if sid in self.unsaved:
            alerts.append(f"⛔ {self.unsaved[sid]}")
        now = time.monotonic()
        alerts += [f"⚠ {a}" for t, a in self.alerts if now - t < ALERT_SECONDS]
        messages = list(prep.messages) if prep is not None else []
        if not info.annotated and not info.gone:
            messages.append(f"scene {sid} has no annotation.json: run `annotator annotate` first")
        if info.error and not info.gone:  # a gone scene's is the page's alert
            messages.append(info.error)
        notice = "\n\n".join(f"⚠ {m}" for m in messages)
        if self.armed:
            notice = (
                "**Click on a picture where a part without a pose lies** (M again to cancel)"
                + (f"\n\n{notice}" if notice else "")
            )
        offer = self.offer if self.offer is not None and self.offer.scene == sid else None
        if offer is not None:
            x, y = offer.pixel
            notice = (
                f"**Add a part at {offer.camera} ({x:.0f}, {y:.0f})**: pick "
                "the instance below (then R to refine it)" + (f"\n\n{notice}" if notice else "")
            )
        done, total = state.progress()
        pace = state.pace()
        eta = f", about {(total - done) / pace:.0f} min left" if pace > 0 else ""
        return PanelView(
            title=title,
            alert="\n\n".join(f"<span style='color:#d00'>{a}</span>" for a in alerts),
            notice=notice,
            progress=100.0 * done / max(total, 1),
            progress_text=f"reviewed {done} / {total} · {pace:.1f} scenes/min{eta}",
            table=instance_table(info, selected),
            warnings=warnings_text(info),
            repair=self.repair_text,
            offer=offer.instances if offer is not None else (),
        )

    # ------------------------------------------------------------ decisions
    def _not_saved(self, sid: str, what: str, why: str) -> None:
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

    def _shown_scene(self, what: str) -> str | None:
        """The scene a decision ``what`` is for: the one the page shows, if the cursor is
        on it. Else None, and the reviewer is told: the page was still switching, and the
        decision was made looking at another scene."""
        with self._lock:
            sid, shown = self.nav.current, self.displayed
        if sid is None or sid == shown:
            return sid
        showing = "no scene yet" if shown is None else f"scene {shown}"
        self._not_saved(
            sid,
            what,
            f"the page was still showing {showing} when you decided; "
            "look at this one, then decide again",
        )
        return None

    def _write(self, sid: str, what: str, fn, *, decision: bool = True) -> bool:
        """Run a write; on failure show it in this page and keep the scene unsaved."""
        try:
            review = fn()
        except SaveError as exc:
            self._not_saved(sid, what, str(exc))
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
        sid = self._shown_scene(str(status))
        if sid is None:
            return
        if self._write(sid, str(status), lambda: self.app.state.set_scene(sid, status, by=self.id)):
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
        sid = self._shown_scene(f"{key} {status}")
        if sid is None:
            return
        self._write(
            sid,
            f"{key} {status}",
            lambda: self.app.state.set_instance(sid, key, status, by=self.id),
        )
        self.request_render()

    def toggle_instance(self) -> None:
        with self._lock:
            sid, key = self.nav.current, self.nav.selected
        if sid is None or key is None:
            return
        new = (
            ReviewStatus.ACCEPTED
            if self.app.state.info(sid).instance_status(key) == ReviewStatus.REJECTED
            else ReviewStatus.REJECTED
        )
        self.set_instance(new)

    def arm_missing(self) -> None:
        with self._lock:
            self.armed = not self.armed
        self.request_render()

    def _mark_missing(self, camera: str, x: float, y: float) -> None:
        with self._lock:
            self.armed = False
        sid = self._shown_scene(f"no pose at {camera} ({x:.0f}, {y:.0f})")
        if sid is None:
            return
        saved = self._write(
            sid,
            f"no pose at {camera} ({x:.0f}, {y:.0f})",
            lambda: self.app.state.mark_missing(sid, camera, (x, y), by=self.id),
        )
        keys = repair.unposed(self.app.state.ds, self.app.state.info(sid))
        if saved and keys:
            mark = self.app.state.info(sid).review.missing[-1]
            with self._lock:
                self.offer = Offer(sid, mark.camera, mark.pixel, tuple(keys))
        self.request_render()

    # ---------------------------------------------------------------- repairs
    def _say(self, text: str) -> None:
        """Show what a repair did (or is doing) in the panel at once."""
        with self._lock:
            self.repair_text = text
        self.panel.show_repair(text, self._nudge_text())
        self.client.flush()

    def _nudge_text(self) -> str:
        size = (
            (f"{repair.LARGE_MM:g} mm" if self.large else f"{repair.SMALL_MM:g} mm")
            if self.nudge_kind == NudgeKind.MOVE
            else (f"{repair.LARGE_DEG:g}°" if self.large else f"{repair.SMALL_DEG:g}°")
        )
        return f"nudges (1-6): **{self.nudge_kind}** by {size} in the reference camera's axes"

    def _target(self, what: str) -> tuple[str, str] | None:
        """The scene shown and its selected instance, for a repair ``what``."""
        with self._lock:
            key = self.nav.selected
        if key is None:
            self._say("select an instance first (click it, or I)")
            return None
        sid = self._shown_scene(f"{what} {key}")
        if sid is None or self.app.state.info(sid).pose(key) is None:
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
        state = self.app.state
        before = seen.review.poses.get(key)
        steps = list(before.steps) if before is not None and key in seen.edited else []
        with self._editing:
            after = self._show_then_save(
                sid,
                key,
                f"pose of {key}",
                lambda: state.stage_pose(
                    sid, key, T, [*steps, step], by=self.id, unmark=unmark, expect=before
                ),
                state.info(sid).view,
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
        state = self.app.state
        with self._editing:
            return self._show_then_save(
                sid,
                key,
                what,
                lambda: state.stage_restore(sid, key, edit, by=self.id, expect=expect),
                state.info(sid).view,
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
            self._not_saved(sid, what, str(exc))
            return Unsaved.CONFLICT if isinstance(exc, Conflict) else Unsaved.FAILED
        try:
            self._reposed(sid, key, shown)
        finally:  # whatever showing it did, the change is written
            saved = self._write(sid, what, lambda: self.app.state.commit(staged), decision=False)
        return staged.review.poses.get(key) if saved else Unsaved.FAILED

    def _reposed(self, sid: str, key: str, before: str) -> None:
        """Make the scene's overlays for its new poses from the shown ones (only the
        changed rectangles cast again; ``before``: the version they show), then show them."""
        info = self.app.state.info(sid)
        prep = self._prep
        with self._ahead_done:  # being made ahead (A came quickly): sooner done than redone
            self._ahead_done.wait_for(lambda: self._ahead_making != info.view, AHEAD_WAIT)
        if self.app.cache.ready((sid, info.view)):  # poses shown before (undo, redo, A)
            prep = None
        if prep is not None and prep.scene_id == sid and key in {p.key for p in info.poses}:
            new = repose(self.app.state.ds, prep, list(info.poses), key)
            if new is not None:
                self.app.reposed(sid, info, new, before=before)
        self.request_render()

    def refine(self) -> None:
        """R: refine the selected instance in a thread of its own (the page says so)."""
        target = self._target("refine")
        if target is None:
            return
        sid, key = target
        if not self._refining.acquire(blocking=False):
            self._say("a refinement is already running")
            return
        self._say(f"refining {key}: ICP against the depth and its markers…")
        threading.Thread(target=self._refine, args=(sid, key), daemon=True).start()

    def _refine(self, sid: str, key: str) -> None:
        try:
            state = self.app.state
            inputs = self.app.repair_inputs(sid)
            seen = state.info(sid)
            result = repair.refine(state.ds, seen, key, inputs)
            residuals = f"before: {result.before.text()}; after: {result.after.text()}"
            if result.converged:
                if self._edit(sid, key, result.T, result.step(), seen=seen):
                    self._say(f"✔ {key} refined in {result.seconds:.2f} s — {residuals}")
            else:
                self._say(
                    f"<span style='color:#d00'>⚠ {key}: the refinement did not converge "
                    f"({result.why}); the pose is kept</span> — {residuals}"
                )
        except Exception as exc:  # the page stays usable; the reviewer is told
            self._say(f"⚠ {key}: cannot refine ({type(exc).__name__}: {exc})")
        finally:
            self._refining.release()

    def pressed(self) -> None:
        """A key or button came (see :meth:`viewer.panel.PanelActions.pressed`)."""
        self.pictures.postpone()

    def alternative(self) -> None:
        """A: the selected instance's next candidate pose."""
        target = self._target("alternative for")
        if target is None:
            return
        sid, key = target
        info = self.app.state.info(sid)
        auto = info.auto_pose(key)
        ck, found, index = self._candidates(sid, key, info)
        if len(found) < 2:
            self._say(f"{key}: no other candidate pose from its markers")
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
            self._say(f"{key}: candidate {index + 1} of {len(found)} — {c.text()}")

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
            state = self.app.state
            found = repair.candidates(state.ds, info, key, self.app.repair_inputs(sid))
            with self._lock:
                hit = self._cycle.setdefault(ck, (found, 0))
        return ck, *hit

    def _ahead(self, sid: str, key: str, info: SceneInfo) -> None:
        """Once the pixels are out, in the background: what the next A on the selected
        instance needs (the scene's markers read, the instance's candidates, the overlays
        of the next one), so that the key only shows it. Once per poses shown."""
        job = (sid, key, info.view)
        with self._lock:
            if job == self._ahead_for or self._closed:
                return
            self._ahead_for = job
        self._ahead_pool.submit(self._prepare_alternative, sid, key, info)

    def _still_on(self, sid: str, key: str) -> bool:
        """Whether the page is still on instance ``key`` of scene ``sid`` (work ahead for it
        is of no use once the reviewer has gone on, and would slow down what they do)."""
        with self._lock:
            return self.nav.current == sid and self.nav.selected == key and not self._closed

    def _prepare_alternative(self, sid: str, key: str, info: SceneInfo) -> None:
        try:
            time.sleep(AHEAD_DELAY)
            if not self._still_on(sid, key) or self.app.state.info(sid).view != info.view:
                return  # another key came meanwhile: its own render asks again
            if info.pose(key) is None or not self.app.cache.ready((sid, info.view)):
                return
            prep = self.app.prepared(sid, info)  # the overlays shown, made already
            if not self._still_on(sid, key):
                return
            _, found, index = self._candidates(sid, key, info)
            if len(found) < 2 or self.app.state.info(sid).view != info.view:
                return  # nothing to cycle through, or the poses changed meanwhile
            if not self._still_on(sid, key):
                return
            poses, view = info.with_pose(key, found[(index + 1) % len(found)].T)
            if not self.app.cache.ready((sid, view)):
                with self._ahead_done:
                    self._ahead_making = view
                new = repose(self.app.state.ds, prep, poses, key, parallel=False)
                if new is not None:
                    self.app.ahead(sid, view, new)
        except Exception as exc:  # only a head start: A makes it itself then
            print(f"review: {self.id}: could not prepare A ahead: {exc}", file=sys.stderr)
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
        info = self.app.state.info(sid)
        T = repair.nudge(self.app.state.ds, info, key, step)
        if self._edit(sid, key, T, step.step(), seen=info):
            unit = "mm" if step.kind == "move" else "°"
            self._say(f"{key}: {step.kind} {step.amount:+g} {unit} along {'xyz'[axis]}")

    def moved_by_gizmo(self, key: str, T) -> None:
        """The gizmo in the 3D view was let go: ``T`` is the part's new pose."""
        with self._lock:
            sid = self.nav.current
        info = self.app.state.info(sid) if sid is not None else None
        if sid is not None and info is not None and info.pose(key) is not None:
            if self._edit(sid, key, T, RepairStep(RepairOp.GIZMO), seen=info):
                self._say(f"{key}: moved with the gizmo")

    def toggle_nudge_kind(self) -> None:
        move = self.nudge_kind == NudgeKind.MOVE
        self.nudge_kind = NudgeKind.TURN if move else NudgeKind.MOVE
        self._say(self.repair_text)

    def toggle_nudge_size(self) -> None:
        self.large = not self.large
        self._say(self.repair_text)

    def _step_back(self, back: bool) -> None:
        what = "undo" if back else "redo"
        with self._lock:
            sid = self.nav.current
        sid = self._shown_scene(what) if sid is not None else None
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
            self._say(self.repair_text)
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
            self.nav.select(item.key, zoom=self.nav.zoom)
        self._say(
            f"{what}: {item.key} " + ("back to its auto pose" if edit is None else "restored")
        )

    def undo(self) -> None:
        self._step_back(True)

    def redo(self) -> None:
        self._step_back(False)

    def reset_pose(self) -> None:
        """X: the selected instance back to its auto pose (an added one is removed)."""
        target = self._target("reset")
        if target is None:
            return
        sid, key = target
        before = self.app.state.info(sid).review.poses.get(key)
        if before is None:
            self._say(f"{key} has its auto pose already")
            return
        done = self._restore(sid, key, None, f"reset of {key}", expect=before)
        if not isinstance(done, Unsaved):
            with self._lock:
                self.history.setdefault(sid, []).append(Step(key, before, None))
                self.future.pop(sid, None)
            self._say(f"{key}: reset to the auto-annotation")

    def add_missing(self, key: str) -> None:
        """ "Add here": start instance ``key`` where M was clicked."""
        with self._lock:
            offer = self.offer
        if offer is None or key not in offer.instances:
            return
        sid, camera, pixel = offer.scene, offer.camera, offer.pixel
        if self._shown_scene(f"add {key}") != sid:
            return
        state = self.app.state
        info = state.info(sid)
        found = repair.start(state.ds, info, key, camera, pixel, self.app.repair_inputs(sid))
        if found is None:
            self._say(f"⚠ {key}: no marker and no depth near the click to start it from")
            return
        step = RepairStep(
            RepairOp.ADD, {"camera": camera, "pixel": list(pixel), "source": found.source}
        )
        if self._edit(sid, key, found.T, step, seen=info, unmark=(camera, pixel)):
            with self._lock:
                self.offer = None
                self.nav.select(key)
            self._say(f"{key} added ({found.text()}): R refines it")

    # ------------------------------------------------------------ navigation
    def _move(self, fn) -> None:
        with self._lock:
            fn()
        self.request_render()

    def next(self) -> None:
        self._move(lambda: self.nav.step(+1))

    def previous(self) -> None:
        self._move(lambda: self.nav.step(-1))

    def next_flagged(self) -> None:
        self._move(self.nav.next_flagged)

    def set_filter(self, flt: str) -> None:
        if flt not in FILTERS:  # only a page that is not viser's own sends another
            print(
                f"review: {self.id}: ignored an unknown filter {str(flt)[:40]!r}", file=sys.stderr
            )
            return
        self._move(lambda: self.nav.set_filter(flt))

    def select(self, key: str) -> None:
        self._move(lambda: self.nav.select(key))

    def select_next(self) -> None:
        self._move(self.nav.select_next)

    def toggle_zoom(self) -> None:
        self._move(self.nav.toggle_zoom)

    def toggle_fill(self) -> None:
        def flip() -> None:
            self.fill = not self.fill

        self._move(flip)

    def toggle_3d(self) -> None:
        on = not self.scene.showing_3d
        self.pictures.hide(on)
        if on:  # the canvas is in view at once: no picture may linger on it
            self.pictures.send_background()
        else:
            self.pictures.send_background_soon()
        self.scene.show_3d(on, self.client.camera)

    # ----------------------------------------------------------------- clicks
    def clicked_canvas(self, x: float, y: float) -> None:
        """A click on the canvas at (x, y) in 0-1 of its size: on the picture shown."""
        with self._lock:
            shown = self._on_canvas
        picture = self._zoom if shown and shown[0] == "zoom" else self._picture
        if picture is not None:
            h, w = picture[1].image.shape[:2]
            self.clicked(x * w - 0.5, y * h - 0.5)

    def clicked(self, u: float, v: float) -> None:
        """A click at (u, v) of the picture shown (the mosaic or the zoom)."""
        with self._lock:
            sid = self.nav.current
            zoomed = self._on_canvas is not None and self._on_canvas[0] == "zoom"
            shown = self._zoom if zoomed else self._picture
            armed = self.armed
        prep = self._prep
        if shown is None or shown[0] != sid or prep is None or prep.scene_id != sid:
            return
        located = shown[1].locate(u, v)
        if located is None:
            return
        tile, x, y = located
        if armed:
            self._mark_missing(tile.camera, x, y)
            return
        key = prep.instance_at(tile.camera, x, y, radius=4.0 / tile.scale)
        if key is not None:
            self.select(key)

    # ------------------------------------------------------------------ blink
    def toggle_blink(self) -> None:
        """Blink the rendered part over the zoom (opening the zoom if needed), or stop. The
        browser blinks it (a CSS animation): nothing is sent per blink."""
        with self._lock:
            self.blinking = not self.blinking
            if self.blinking and not (self.nav.zoom and self.nav.selected):
                self.nav.toggle_zoom()
        self.request_render()

    # ------------------------------------------------------ other reviewers
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

    def close(self) -> None:
        """The page has gone: stop rendering (waiting for the render under way, within
        :data:`CLOSE_WAIT_SECONDS`) and drop what it held."""
        with self._render_lock:
            self._closed = True
            self._dirty = False
            self._render_lock.wait_for(lambda: not self._rendering, CLOSE_WAIT_SECONDS)
        self.pictures.close()
        self._ahead_pool.shutdown(wait=False, cancel_futures=True)
        with self._lock:
            self._picture = self._zoom = self._prep = None
            self._shown = self._shown_zoom = self._on_canvas = None
