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

The repair keys (R, A, the nudges, the gizmo, M + click + "Add here", U, X) are the page's
:class:`~viewer.editor.RepairEditor`, which needs of the page only what
:class:`~viewer.editor.EditorPage` lists; the page needs of its server only what
:class:`~viewer.host.ReviewHost` lists.

The pictures are made for the page's canvas, within an 8K screen
(:func:`viewer.memory.clamp_viewport`); when the page closes, what it held is dropped.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import viser

from annotator.dataset.review import ReviewStatus
from viewer import repair
from viewer.editor import Offer, RepairEditor
from viewer.host import ReviewHost
from viewer.memory import picture_size
from viewer.mosaic import compose
from viewer.navigation import Navigator
from viewer.overlays import Prepared
from viewer.panel import Panel
from viewer.panel_text import PanelView, panel_view
from viewer.pictures import Pictures
from viewer.scene3d import Scene3D
from viewer.shown import Shown
from viewer.state import FILTERS, SaveError, SceneInfo
from viewer.style import Look
from viewer.zoom import zoom

DEFAULT_VIEWPORT = (1280, 960)
#: How long a page's closing waits for its render under way (it is dropped after it).
CLOSE_WAIT_SECONDS = 10.0
_MAX_ALERTS = 3
ALERT_SECONDS = 60.0  # how long the panel repeats another reviewer's overriding decision


class Session:
    """The review page of one browser client."""

    def __init__(self, app: ReviewHost, client: viser.ClientHandle) -> None:
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
        #: The scene whose panel and pictures were sent last, as they showed it.
        self.displayed_info: SceneInfo | None = None
        self.frames_at: dict[str, int] = {}  # a sequence -> this page's window, frames on
        self._render_lock = threading.Condition()
        self._dirty = False
        self._rendering = False
        self._closed = False
        self.shown = Shown()
        self.blinking = False
        self.editor = RepairEditor(self)
        self.panel = Panel(client.gui, self)
        self.pictures = Pictures(client.gui, client.scene)
        self.scene = Scene3D(
            client.scene,
            app.state.ds,
            on_part=self.select,
            on_canvas=self.clicked_canvas,
            on_gizmo=self.editor.gizmo,
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
            self._show_without_pictures(sid, self.info(sid), f"cannot show it: {why}")
        except Exception:  # the page is gone meanwhile: nothing to tell it
            pass

    def _show_without_pictures(self, sid: str, info: SceneInfo, why: str) -> None:
        """Name scene ``sid`` in the page with ``why`` it is not shown; the pictures of the
        scene shown before are taken off the page, so that none is mistaken for it."""
        with self._lock:
            flt, selected = self.nav.filter, self.nav.selected
            self.shown.clear(on_canvas=("none", sid))
            self.blinking = False
        self.pictures.clear()
        view = self._panel_view(info, None, flt, selected)
        red = f"<span style='color:#d00'>⛔ {why}</span>"
        view.alert = f"{red}\n\n{view.alert}" if view.alert else red
        self.panel.show(view, [])
        with self._lock:
            self.displayed_info = info
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
        info = self.info(sid)
        if info.gone:
            self._show_without_pictures(sid, info, f"{info.error}: nothing to decide")
            return
        prep = self.app.prepared(sid, info)  # a failure is shown by request_render
        self.shown.prep = prep
        look = Look.of(info, selected)
        self.viewport = self._viewport(self.viewport)  # the canvas may have changed since
        w, h = self.viewport
        base = (sid, info.view, look, (w, h))
        zkey = (*base, fill) if zoom_open and selected else None
        if selected is not None and zkey is not None and zkey != self.shown.zoom_for:
            shown = (
                self.shown.zoom[1]
                if self.shown.zoom is not None and self.shown.zoom[0] == sid
                else None
            )
            z = zoom(prep, selected, look, w, h, fill=fill, keep=shown)
            self.shown.zoom = (sid, z) if z is not None else None
            self.shown.zoom_for = zkey if z is not None else None
        if zkey is None or self.shown.zoom is None:
            picture = self.shown.mosaic
            if base != self.shown.mosaic_for or picture is None:
                picture = self.shown.mosaic = (sid, compose(prep, look, w, h))
                self.shown.mosaic_for = base
                self.app.drew()
            if ("mosaic", base) != self.shown.on_canvas:
                self.pictures.show_mosaic(picture[1].image)
                self.shown.on_canvas = ("mosaic", base)
            with self._lock:
                self.blinking = False  # blinking belongs to a zoom
        elif ("zoom", zkey) != self.shown.on_canvas:
            z = self.shown.zoom[1]
            self.pictures.show_zoom(z)
            self.shown.on_canvas = ("zoom", zkey)
        self.pictures.blink(blinking and self.shown.on_canvas[0] == "zoom")
        self.panel.show(self._panel_view(info, prep, flt, selected), [p.key for p in info.poses])
        with self._lock:
            self.displayed_info = info
        self.client.flush()  # the new picture is on its way before anything else is done
        self.pictures.send_background_soon()
        # A sequence's cloud is the first shown frame's depth, its frustums the shown frames'
        # cameras: sent again when P shows others.
        cameras = self.app.state.view(sid, info)[0].rig.cameras if info.shown else None
        self.scene.show_3d_scene(
            info.poses, look, prep.cloud, (sid, info.fingerprint, info.shown), cameras
        )
        self.scene.show_gizmo(info.pose(selected) if selected else None)
        if selected and prep.scene_id == sid and info.pose(selected) is not None:
            self.editor.work_ahead(sid, selected, info)
        with self._lock:
            upcoming = self.nav.upcoming()
        for other in reversed(upcoming):  # the cache starts with the last asked for
            self.app.prefetch(other)
        if info.shown:  # a sequence: P's frames first, as J's scenes are for a fixed rig
            self.app.prefetch_frames(sid, self._at(sid), +1)

    def _panel_view(
        self, info: SceneInfo, prep: Prepared | None, flt: str, selected: str | None
    ) -> PanelView:
        state = self.app.state
        now = time.monotonic()
        with self._lock:
            unsaved = self.unsaved.get(info.id)
            alerts = [a for t, a in self.alerts if now - t < ALERT_SECONDS]
            armed = self.armed
        return panel_view(
            info,
            position=(state.ids.index(info.id) + 1, len(state.ids)),
            filter=flt,
            selected=selected,
            messages=prep.messages if prep is not None else (),
            unsaved=unsaved,
            alerts=alerts,
            armed=armed,
            offer=self.editor.offer,
            progress=state.progress(),
            pace=state.pace(),
            repair=self.editor.repair_text,
        )

    # ------------------------------------------------------------ decisions
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

    def _at(self, sid: str) -> int:
        with self._lock:
            return self.frames_at.get(sid, 0)

    def info(self, sid: str) -> SceneInfo:
        """Scene ``sid`` as this page shows it now (a sequence: with this page's frames)."""
        return self.app.state.info(sid, self._at(sid))

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

    # ---------------------------------------------------------------- sequences
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

    def pressed(self) -> None:
        """A key or button came (see :meth:`viewer.panel.PanelActions.pressed`)."""
        self.pictures.postpone()

    # ------------------------------------------------- what the repair editor needs
    @property
    def host(self) -> ReviewHost:
        return self.app

    @property
    def closed(self) -> bool:
        return self._closed

    def cursor(self) -> tuple[str | None, str | None]:
        with self._lock:
            return self.nav.current, self.nav.selected

    def prepared_scene(self) -> Prepared | None:
        return self.shown.prep

    def show_repair(self, text: str, nudges: str) -> None:
        self.panel.show_repair(text, nudges)
        self.client.flush()

    def focus(self, key: str, *, zoom: bool | None = None) -> None:
        with self._lock:
            self.nav.select(key, zoom=self.nav.zoom if zoom is None else zoom)

    # ------------------------------------------------------------- repair keys
    def refine(self) -> None:
        self.editor.refine()

    def alternative(self) -> None:
        self.editor.alternative()

    def nudge(self, axis: int, sign: int) -> None:
        self.editor.nudge(axis, sign)

    def toggle_nudge_kind(self) -> None:
        self.editor.toggle_nudge_kind()

    def toggle_nudge_size(self) -> None:
        self.editor.toggle_nudge_size()

    def undo(self) -> None:
        self.editor.undo()

    def redo(self) -> None:
        self.editor.redo()

    def reset_pose(self) -> None:
        self.editor.reset_pose()

    def add_missing(self, key: str) -> None:
        self.editor.add_missing(key)

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
            picture = self.shown.on_screen()
        if picture is not None:
            h, w = picture[1].image.shape[:2]
            self.clicked(x * w - 0.5, y * h - 0.5)

    def clicked(self, u: float, v: float) -> None:
        """A click at (u, v) of the picture shown (the mosaic or the zoom)."""
        with self._lock:
            sid = self.nav.current
            shown = self.shown.on_screen()
            armed = self.armed
        prep = self.shown.prep
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
        self.editor.close()
        with self._lock:
            self.shown.clear()
