"""One browser page: its own cursor (:class:`~viewer.page.navigation.Navigator`), control panel,
pictures and 3D canvas, and what its buttons, hotkeys and clicks do.

A :class:`Session` is three layers: what the page shows and when
(:mod:`viewer.page.rendering`), what its keys decide (:mod:`viewer.page.decisions`), and,
here, its parts and the keys and clicks that move its cursor, zoom and repair.

The repair keys (R, A, the nudges, the gizmo, M + click + "Add here", U, X) are the page's
:class:`~viewer.page.editor.RepairEditor`, which needs of the page only what
:class:`~viewer.page.editor.EditorPage` lists; the page needs of its server only what
:class:`~viewer.page.host.ReviewHost` lists. When the page closes, what it held is dropped.
"""

from __future__ import annotations

import sys
import threading

import viser

from annotator.dataset.review import ReviewStatus
from annotator.review import FILTERS, SceneInfo
from viewer.drawing.overlays import Prepared
from viewer.page.decisions import PageDecisions
from viewer.page.editor import RepairEditor
from viewer.page.host import ReviewHost
from viewer.page.navigation import Navigator
from viewer.page.panel import Panel
from viewer.page.pictures import Pictures
from viewer.page.scene3d import Scene3D
from viewer.page.shown import Shown

#: How long a page's closing waits for its render under way (it is dropped after it).
CLOSE_WAIT_SECONDS = 10.0


class Session(PageDecisions):
    """The review page of one browser client."""

    def __init__(self, app: ReviewHost, client: viser.ClientHandle) -> None:
        self.app = app
        self.client = client
        self.id = f"page-{app.tag}-{client.client_id}"
        self.nav = Navigator(app.state, current=app.start_scene)
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

    # ---------------------------------------------------------------- render

    # ------------------------------------------------------------ decisions

    # ---------------------------------------------------------------- sequences

    def pressed(self) -> None:
        """A key or button came (see :meth:`viewer.page.panel.PanelActions.pressed`)."""
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
