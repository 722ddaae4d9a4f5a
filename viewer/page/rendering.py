"""What one page shows, and when: the pictures made for its canvas, its panel and its 3D
view, for the scene its cursor is on.

Showing a scene is coalesced: actions only move the cursor and ask for a render
(:meth:`PageRendering.request_render`); one render runs at a time and always shows the
latest state, so a held key skips scenes instead of queueing them. The pictures and the
panel go out first; the 3D view follows (and only while it is shown). A scene that cannot be
shown (its folder gone, an unexpected failure) is named in the page, without the pictures of
the scene shown before it, and its failure is one line in the server's log.

The pictures are made for the page's canvas, within an 8K screen
(:func:`viewer.drawing.memory.clamp_viewport`).

:class:`PageRendering` is the first layer of :class:`viewer.page.session.Session` (then
:class:`viewer.page.decisions.PageDecisions`): the attributes it declares are the session's.
"""

from __future__ import annotations

import sys
import threading
import time

import viser

from annotator.review import SceneInfo
from viewer.drawing.memory import picture_size
from viewer.drawing.mosaic import compose
from viewer.drawing.overlays import Prepared
from viewer.drawing.style import Look
from viewer.drawing.zoom import zoom
from viewer.page.editor import RepairEditor
from viewer.page.host import ReviewHost
from viewer.page.navigation import Navigator
from viewer.page.panel import Panel
from viewer.page.panel_text import PanelView, panel_view
from viewer.page.pictures import Pictures
from viewer.page.scene3d import Scene3D
from viewer.page.shown import Shown

__all__ = ["ALERT_SECONDS", "DEFAULT_VIEWPORT", "PageRendering"]

DEFAULT_VIEWPORT = (1280, 960)
ALERT_SECONDS = 60.0  # how long the panel repeats another reviewer's overriding decision


class PageRendering:
    """The rendering part of a page (see the module docstring)."""

    app: ReviewHost
    client: viser.ClientHandle
    id: str
    nav: Navigator
    shown: Shown
    pictures: Pictures
    panel: Panel
    scene: Scene3D
    editor: RepairEditor
    viewport: tuple[int, int]
    fill: bool
    blinking: bool
    armed: bool
    unsaved: dict[str, str]
    alerts: list[tuple[float, str]]
    displayed_info: SceneInfo | None
    frames_at: dict[str, int]
    _lock: threading.RLock
    _render_lock: threading.Condition
    _dirty: bool
    _rendering: bool
    _closed: bool

    def _canvas(self) -> tuple[int, int] | None:
        """The page's canvas size as it says (None: it has not said, or nonsense)."""
        try:
            return int(self.client.camera.image_width), int(self.client.camera.image_height)
        except (AssertionError, AttributeError, TypeError, ValueError, OverflowError):
            return None

    def _viewport(self, shown: tuple[int, int] | None) -> tuple[int, int]:
        """The size to make the pictures: the page's canvas, as it says, the pictures being
        ``shown`` at that size (see :func:`viewer.drawing.memory.picture_size`)."""
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

    def _at(self, sid: str) -> int:
        with self._lock:
            return self.frames_at.get(sid, 0)

    def info(self, sid: str) -> SceneInfo:
        """Scene ``sid`` as this page shows it now (a sequence: with this page's frames)."""
        return self.app.state.info(sid, self._at(sid))
