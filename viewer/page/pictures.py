"""The pictures of one page (the mosaic, or the zoom and its blinking rendered part), laid
exactly over the 3D canvas as plain HTML images.

Why HTML and not a texture in the 3D scene: a new image for the canvas costs software WebGL
(headless Chromium, many laptops) several frames of 50-150 ms each before it shows, while
an ``<img>`` is decoded and composited by the browser in a few tens of milliseconds without
drawing the 3D scene at all. The images come through viser's documented ``add_html``
element; CSS places them over the canvas:

- ``position: fixed`` at the canvas's place and size: anchored to the canvas where the
  browser supports CSS anchor positioning, else at the top left with the size the canvas
  reported (the control panel is docked on the right);
- ``pointer-events: none``: clicks go through to the canvas, whose click position (0-1 of
  its size) is the position on the picture;
- ``image-rendering: pixelated``: a picture made to the canvas's size is shown pixel for
  pixel, and zoomed pixels stay square if the browser scales it.

The mosaic is sent as JPEG. The zoom is sent in layers (:func:`zoom_html`): each crop as
a PNG of its camera pixels, magnified by the browser pixel for pixel, and the one-pixel
outline, titles and marks as SVG over them, so that a repair, which changes the outline,
sends a few kilobytes. The blinking rendered part is one PNG (deflated fast with PNG's "up"
filter, see :data:`_PNG`): JPEG would smear its edges.
Blinking is a CSS animation of the rendered part over the zoom: no message per blink.

The HTML elements live in the control panel, so they vanish with it when the reviewer
collapses the panel. The same picture is therefore also sent as the canvas's background
image, which the images cover exactly while they are there. Drawing it is a dozen WebGL
frames, and on a software renderer each is read back for compositing (25-60 ms of the
page's main thread each): a key pressed meanwhile waited for them. So the copy goes
:data:`BACKGROUND_DELAY` after a change while the panel is collapsed, and otherwise, as a
safety net, only once the pictures have been still for :data:`BACKGROUND_QUIET`, longer
than a reviewer takes between keys. viser does not tell the server that its panel
collapsed; the canvas does (:class:`PanelGuess`): it widens by the panel's width at once.
"""

from __future__ import annotations

import base64
import hashlib
import html
import threading
import time
from collections.abc import Callable

import cv2
import numpy as np
import viser

from viewer.drawing.style import MISSING_COLOUR, UNEXPLAINED_COLOUR
from viewer.drawing.zoom import Zoom, ZoomTile, outline_rects, tile_marks
from viewer.page.keyguard import PICTURE_MARK

JPEG_QUALITY = 85
BACKGROUND_DELAY = 0.2  # seconds after a change: the canvas's copy, panel collapsed
BACKGROUND_QUIET = 2.5  # seconds without a change: the canvas's copy, panel open
#: A canvas that widens (narrows) by this share at once, its height kept, is taken for the
#: control panel collapsed (opened): it is docked beside the canvas (about a third of it).
PANEL_SHIFT = 0.2
BLINK_SECONDS = 0.7  # one period: rendered part, then the image, half each
_ANCHOR = "--review-canvas"
_STYLE = (
    f"<style>canvas[data-engine]{{anchor-name:{_ANCHOR}}}"
    "@keyframes review-blink{0%{opacity:1}50%{opacity:0}}</style>"
)
#: Fast and small for the zoom, whose rows come in runs of equal rows (magnified pixels):
#: the "up" filter makes each repeated row zeros, several times quicker to deflate than
#: libpng's adaptive filters, and no bigger; deflate's run-length strategy finds those runs
#: without searching for longer matches, which is quicker again and no bigger either.
_PNG = [
    cv2.IMWRITE_PNG_COMPRESSION,
    1,
    cv2.IMWRITE_PNG_FILTER,
    cv2.IMWRITE_PNG_FILTER_UP,
    cv2.IMWRITE_PNG_STRATEGY,
    cv2.IMWRITE_PNG_STRATEGY_RLE,
]
_ORDER = 1e9  # after everything else in the panel: the images take no room in it
_ZOOM_LAYER = 2  # z-index of the zoom's ground: over the mosaic (1), under blinking


def _data_url(image: np.ndarray, exact: bool) -> str:
    bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    if exact:
        ok, data = cv2.imencode(".png", bgr, _PNG)
        mime = "image/png"
    else:
        ok, data = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        mime = "image/jpeg"
    if not ok:
        raise ValueError("could not encode a picture")
    return f"data:{mime};base64,{base64.b64encode(data.tobytes()).decode('ascii')}"


def _over_canvas(w: int, h: int) -> str:
    """CSS that lays an element of ``w`` x ``h`` picture pixels exactly over the canvas."""
    return (
        f"position:fixed;left:0;top:0;width:{w}px;height:{h}px;"
        f"position-anchor:{_ANCHOR};left:anchor(left);top:anchor(top);"
        "width:anchor-size(width);height:anchor-size(height);pointer-events:none;"
    )


def picture_html(image: np.ndarray, *, exact: bool = False, z: int = 0, blink: bool = False) -> str:
    """An ``<img>`` of ``image`` (RGB) covering the 3D canvas (see the module docstring)."""
    h, w = image.shape[:2]
    animation = f"animation:review-blink {BLINK_SECONDS}s steps(1,end) infinite;" if blink else ""
    return (
        f'{_STYLE}<img alt="" {PICTURE_MARK} src="{_data_url(image, exact)}" '
        f'style="{_over_canvas(w, h)}'
        f'image-rendering:pixelated;z-index:{z};{animation}">'
    )


def zoom_html(z: Zoom, *, layer: int = 0) -> str:
    """The zoom ``z`` covering the 3D canvas, in layers (:func:`zoom_layers`, one after
    the other)."""
    return "".join(zoom_layers(z, layer=layer))


def zoom_layers(z: Zoom, *, layer: int = 0) -> list[str]:
    """The zoom ``z`` covering the 3D canvas, as HTML layers: the black ground and the
    "not visible" notes, each crop as a PNG of its own camera pixels (magnified by the
    browser pixel for pixel), and over them one SVG of the outline (the rectangles of
    :func:`viewer.drawing.zoom.outline_rects`), the tiles' titles and marks. Together they show
    :attr:`Zoom.image`. Each goes to the page as an element of its own, so that a repair,
    which changes the outline and seldom a crop, sends the page a few kilobytes and the
    browser decodes no picture again. ``layer``: the z-index of the ground, the crops
    one above, the SVG two above."""
    w, h = z.width, z.height

    def pct(v: int, whole: int) -> str:
        return f"{100.0 * v / whole:.6f}%"

    def over(z_index: int, body: str, ground: str = "") -> str:
        # The style sheet is in the ground only: a page takes a new sheet as a change to
        # everything, and the ground seldom changes.
        return (
            f'{_STYLE if ground else ""}<div {PICTURE_MARK} style="{_over_canvas(w, h)}'
            f"z-index:{z_index};"
            f'{ground}overflow:hidden">{body}</div>'
        )

    def svg(body: str) -> str:
        return (
            f'<svg viewBox="0 0 {w} {h}" preserveAspectRatio="none" '
            'shape-rendering="crispEdges" style="position:absolute;left:0;top:0;'
            f'width:100%;height:100%">{body}</svg>'
        )

    notes = "".join(
        f'<text x="{x}" y="{y}" fill="rgb(200,200,200)" {_FONT} font-size="14">'
        f"{html.escape(text)}</text>"
        for text, x, y in z.notes
    )
    layers = [over(layer, svg(notes) if notes else "", "background:#000;")]
    for part in z.parts:
        t = part.tile
        layers.append(
            over(
                layer + 1,
                f'<img alt="" src="{_png_url(part.shown)}" style="position:absolute;'
                f"left:{pct(t.x0, w)};top:{pct(t.y0, h)};width:{pct(t.width, w)};"
                f'height:{pct(t.height, h)};image-rendering:pixelated">',
            )
        )
    shapes = [_svg_tile(part, z) for part in z.parts]
    if not z.fill:
        d = "".join(
            f"M{part.tile.x0 + x} {part.tile.y0 + y}h{rw}v{rh}h{-rw}z"
            for part in z.parts
            for x, y, rw, rh in outline_rects(part.mask, part.magnification)
        )
        shapes.append(f'<path fill="{_rgb(z.colour)}" d="{d}"/>')
    layers.append(over(layer + 2, svg("".join(shapes))))
    return layers


_FONT = 'font-family="Helvetica,Arial,sans-serif"'


def _svg_tile(part: ZoomTile, z: Zoom) -> str:
    """A tile's title and marks (:func:`viewer.drawing.zoom.tile_marks`), clipped to it."""
    t = part.tile
    marks = tile_marks(part.panel, t, z.look)
    inner = []
    d = ""
    for x0, y0, x1, y1 in marks.regions:
        rw, rh = x1 - x0 + 1, y1 - y0 + 1
        d += f"M{x0} {y0}h{rw}v1h{-rw}zM{x0} {y1}h{rw}v1h{-rw}z"
        d += f"M{x0} {y0}h1v{rh}h-1zM{x1} {y0}h1v{rh}h-1z"
    if d:
        inner.append(f'<path fill="{_rgb(UNEXPLAINED_COLOUR)}" d="{d}"/>')
    c = _rgb(MISSING_COLOUR)
    for cx, cy in marks.missing:
        x, y = round(cx), round(cy)
        inner.append(
            f'<g shape-rendering="auto" fill="none"><circle cx="{x}" cy="{y}" r="9" '
            f'stroke="#000" stroke-width="3"/><circle cx="{x}" cy="{y}" r="9" '
            f'stroke="{c}" stroke-width="2"/><path stroke="{c}" '
            f'd="M{x - 5} {y + 0.5}h10M{x + 0.5} {y - 5}v10"/></g>'
        )
    inner.append(
        f'<rect width="{9 + 9 * len(marks.title)}" height="23" fill="#000"/><text x="4" '
        f'y="16" fill="#fff" {_FONT} font-size="13">{html.escape(marks.title)}</text>'
    )
    return (
        f'<svg x="{t.x0}" y="{t.y0}" width="{t.width}" height="{t.height}" overflow="hidden">'
        f"{''.join(inner)}</svg>"
    )


def _rgb(bgr: tuple[int, int, int]) -> str:
    return f"rgb({bgr[2]},{bgr[1]},{bgr[0]})"


#: The data URLs of the zoom's last crops, by content: a repair changes the outline, and
#: seldom the crops under it (see :func:`viewer.drawing.zoom.zoom`'s ``keep``).
_CROP_URLS: dict[tuple[tuple[int, ...], bytes], str] = {}
_CROP_URLS_KEPT = 32


def _png_url(bgr: np.ndarray) -> str:
    """A data URL of a crop (BGR) as PNG: one channel if it is grey (a third of the bytes),
    the crop's natural pixels deflated as libpng does by default."""
    digest = (bgr.shape, hashlib.blake2b(bgr.tobytes(), digest_size=16).digest())
    url = _CROP_URLS.get(digest)
    if url is not None:
        return url
    grey = (
        bgr.ndim == 3
        and np.array_equal(bgr[..., 0], bgr[..., 1])
        and np.array_equal(bgr[..., 0], bgr[..., 2])
    )
    ok, data = cv2.imencode(".png", np.ascontiguousarray(bgr[..., 0]) if grey else bgr)
    if not ok:
        raise ValueError("could not encode a picture")
    url = f"data:image/png;base64,{base64.b64encode(data.tobytes()).decode('ascii')}"
    if len(_CROP_URLS) >= _CROP_URLS_KEPT:
        _CROP_URLS.pop(next(iter(_CROP_URLS)))
    _CROP_URLS[digest] = url
    return url


class PanelGuess:
    """Whether a page's control panel is collapsed, as its canvas's sizes (in the order the
    page reports them) tell: collapsing the docked panel widens the canvas by the panel's
    width, and its height stays. A window resized only in width by as much is taken for the
    same; the worst that follows is a canvas copy sent sooner, or later, than needed.

    >>> guess = PanelGuess()
    >>> guess.canvas(916, 1000), guess.canvas(1360, 1000), guess.canvas(916, 1000)
    (False, True, False)
    >>> guess.canvas(687, 750)  # viser's lower pixel ratio: the same canvas, no panel change
    False
    >>> guess.canvas(0, 0), guess.canvas(916, 1000)  # no canvas (yet): nothing to go by
    (False, False)
    """

    def __init__(self) -> None:
        self.collapsed = False  # a page starts with its panel open
        self._size: tuple[int, int] | None = None

    def canvas(self, width: int, height: int) -> bool:
        """Take the canvas's size now; whether the panel is collapsed."""
        if width < 64 or height < 64:  # no canvas to speak of (see memory.picture_size)
            return self.collapsed
        if self._size is not None:
            w0, h0 = self._size
            if abs(height - h0) <= 0.01 * h0:
                if width >= (1 + PANEL_SHIFT) * w0:
                    self.collapsed = True
                elif width <= (1 - PANEL_SHIFT) * w0:
                    self.collapsed = False
        self._size = (width, height)
        return self.collapsed


class Pictures:
    """The pictures of one page (``gui`` and ``scene`` are that client's)."""

    def __init__(self, gui: viser.GuiApi, scene: viser.SceneApi) -> None:
        self._scene = scene
        self._gui = gui
        self._mosaic = gui.add_html("", order=_ORDER)
        self._rendered = gui.add_html("", order=_ORDER + 1, visible=False)
        self._zoom: list[viser.GuiHtmlHandle] = []  # the zoom's layers (zoom_layers)
        self._zoom_used = 0  # how many of them the zoom shown has
        self._lock = threading.Lock()  # the page's render and its 3D toggle both come here
        self._hidden = False
        self._zoom_open = False
        self._blinking = False
        self._current: Callable[[], np.ndarray] | None = None  # draws the picture on screen
        #: draws the zoom's rendered part, not sent yet
        self._unsent: Callable[[], np.ndarray] | None = None
        self._background_due = False
        self._changed_at = 0.0  # time.monotonic() of the last change the canvas should copy
        self._panel = PanelGuess()
        self._timer: threading.Timer | None = None
        self._timer_pending = False
        self._timer_at = 0.0  # time.monotonic() when the pending timer fires

    def show_mosaic(self, image: np.ndarray) -> None:
        """Show the mosaic (RGB, made to the canvas's size); the zoom closes."""
        html = picture_html(image, z=1)
        with self._lock:
            self._mosaic.content = html
            self._zoom_open = False
            self._current, self._background_due = lambda: image, True
            self._apply()

    def show_zoom(self, z: Zoom) -> None:
        """Show the zoom over the mosaic; what blinking shows over it is drawn and sent when
        blinking starts (making it would delay the zoom, and blinking is rare)."""
        layers = zoom_layers(z, layer=_ZOOM_LAYER)
        with self._lock:
            while len(self._zoom) < len(layers):
                self._zoom.append(self._gui.add_html("", order=_ORDER + 2, visible=False))
            for handle, content in zip(self._zoom, layers):
                handle.content = content  # viser sends only what changed: seldom a crop
            self._zoom_used = len(layers)
            self._unsent = lambda: z.rendered
            self._zoom_open = True
            self._current, self._background_due = lambda: z.image, True
            if self._blinking:
                self._send_rendered()
            self._apply()

    def _send_rendered(self) -> None:
        if self._unsent is not None:
            self._rendered.content = picture_html(
                self._unsent(), exact=True, z=_ZOOM_LAYER + 3, blink=True
            )
            self._unsent = None

    def clear(self) -> None:
        """Take every picture off the page (a scene that cannot be shown is named in the
        panel; the pictures of the one before must not stand for it)."""
        with self._lock:
            self._mosaic.content = ""
            for handle in self._zoom:
                handle.content = ""
            self._rendered.content = ""
            self._unsent = None
            self._zoom_open = False
            self._current, self._background_due = None, True
            self._apply()

    def blink(self, on: bool) -> None:
        """Blink the rendered part over the zoom (if it is open), or stop."""
        with self._lock:
            self._blinking = on
            if on:
                self._send_rendered()
            self._apply()

    def hide(self, hidden: bool) -> None:
        """Hide every picture (while the 3D view is shown), or show them again."""
        with self._lock:
            self._hidden = hidden
            self._background_due = True
            self._apply()

    def canvas_resized(self, width: int, height: int) -> None:
        """The page's canvas is now ``width`` x ``height`` (see :class:`PanelGuess`)."""
        with self._lock:
            self._panel.canvas(width, height)
            if self._timer_pending:  # a panel just collapsed wants its copy sooner
                self._schedule()

    def send_background_soon(self) -> None:
        """Send the canvas's copy of the picture on screen (or clear it while the pictures
        are hidden) once the pictures have been still for :meth:`_wait` (every call starts
        that wait again)."""
        with self._lock:
            self._changed_at = time.monotonic()
            self._schedule()

    def postpone(self) -> None:
        """A key came: the canvas's copy waits again as if the pictures had just changed
        (the key's answer is likely to change them, and must not wait for the copy)."""
        with self._lock:
            if self._timer_pending:
                self._changed_at = time.monotonic()

    def _wait(self) -> float:
        return BACKGROUND_DELAY if self._panel.collapsed else BACKGROUND_QUIET

    def _schedule(self) -> None:
        """(The lock held.) A timer for when the copy is due, unless one fires no later:
        a timer that finds the pictures changed since it was set waits on."""
        due = self._changed_at + self._wait()
        if self._timer_pending and self._timer_at <= due:
            return
        if self._timer is not None:
            self._timer.cancel()
        self._timer_pending, self._timer_at = True, due
        self._timer = threading.Timer(max(0.0, due - time.monotonic()), self._still)
        self._timer.daemon = True
        self._timer.start()

    def _still(self) -> None:
        """The timer: send the copy, or wait on if the pictures changed meanwhile."""
        with self._lock:
            if self._background_due and self._changed_at + self._wait() > time.monotonic():
                self._timer_pending = False
                self._schedule()
                return
        self.send_background()

    def send_background(self) -> None:
        """Send the canvas's copy of the picture on screen now, if it has changed since the
        last one sent (see :meth:`send_background_soon`)."""
        with self._lock:
            self._timer_pending = False
            if not self._background_due:
                return
            self._background_due = False
            image = None if self._hidden or self._current is None else self._current()
            try:
                if image is None:
                    self._scene.set_background_image(None)
                else:
                    self._scene.set_background_image(
                        image, format="jpeg", jpeg_quality=JPEG_QUALITY
                    )
            except Exception:  # the page has gone meanwhile: nothing to show it to
                pass

    def close(self) -> None:
        """The page has gone: send nothing more, and let go of the picture."""
        with self._lock:
            if self._timer is not None:
                self._timer.cancel()
            self._current = self._unsent = None
            self._background_due = False

    def _apply(self) -> None:
        shown = not self._hidden
        self._mosaic.visible = shown and not self._zoom_open
        for i, handle in enumerate(self._zoom):
            handle.visible = shown and self._zoom_open and i < self._zoom_used
        self._rendered.visible = shown and self._zoom_open and self._blinking
