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

The mosaic is sent as JPEG; the zoom as PNG, since JPEG would smear its one-pixel outline
(deflated fast with PNG's "up" filter, see :data:`_PNG`).
Blinking is a CSS animation of the rendered part over the zoom: no message per blink.

The HTML elements live in the control panel, so they vanish with it when the reviewer
collapses the panel. The same picture is therefore also sent, a moment after the HTML one
(:data:`BACKGROUND_DELAY`, so that drawing it does not slow the picture down), as the
canvas's background image, which the images cover exactly while they are there.
"""

from __future__ import annotations

import base64
import threading
from collections.abc import Callable

import cv2
import numpy as np
import viser

JPEG_QUALITY = 85
BACKGROUND_DELAY = 0.2  # seconds
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


def picture_html(image: np.ndarray, *, exact: bool = False, z: int = 0, blink: bool = False) -> str:
    """An ``<img>`` of ``image`` (RGB) covering the 3D canvas (see the module docstring)."""
    h, w = image.shape[:2]
    animation = f"animation:review-blink {BLINK_SECONDS}s steps(1,end) infinite;" if blink else ""
    return (
        f'{_STYLE}<img alt="" src="{_data_url(image, exact)}" style="'
        f"position:fixed;left:0;top:0;width:{w}px;height:{h}px;"
        f"position-anchor:{_ANCHOR};left:anchor(left);top:anchor(top);"
        "width:anchor-size(width);height:anchor-size(height);"
        f'pointer-events:none;image-rendering:pixelated;z-index:{z};{animation}">'
    )


class Pictures:
    """The pictures of one page (``gui`` and ``scene`` are that client's)."""

    def __init__(self, gui: viser.GuiApi, scene: viser.SceneApi) -> None:
        self._scene = scene
        self._mosaic = gui.add_html("", order=_ORDER)
        self._zoom = gui.add_html("", order=_ORDER + 1, visible=False)
        self._rendered = gui.add_html("", order=_ORDER + 2, visible=False)
        self._lock = threading.Lock()  # the page's render and its 3D toggle both come here
        self._hidden = False
        self._zoom_open = False
        self._blinking = False
        self._current: np.ndarray | None = None  # the picture on screen
        #: draws the zoom's rendered part, not sent yet
        self._unsent: Callable[[], np.ndarray] | None = None
        self._background_due = False
        self._timer: threading.Timer | None = None
        self._timer_pending = False

    def show_mosaic(self, image: np.ndarray) -> None:
        """Show the mosaic (RGB, made to the canvas's size); the zoom closes."""
        html = picture_html(image, z=1)
        with self._lock:
            self._mosaic.content = html
            self._zoom_open = False
            self._current, self._background_due = image, True
            self._apply()

    def show_zoom(self, image: np.ndarray, rendered: Callable[[], np.ndarray]) -> None:
        """Show the zoom over the mosaic; ``rendered`` draws what blinking shows over it
        (drawn and sent when blinking starts: making it would delay the zoom, and blinking
        is rare)."""
        html = picture_html(image, exact=True, z=2)
        with self._lock:
            self._zoom.content = html
            self._unsent = rendered
            self._zoom_open = True
            self._current, self._background_due = image, True
            if self._blinking:
                self._send_rendered()
            self._apply()

    def _send_rendered(self) -> None:
        if self._unsent is not None:
            self._rendered.content = picture_html(self._unsent(), exact=True, z=3, blink=True)
            self._unsent = None

    def clear(self) -> None:
        """Take every picture off the page (a scene that cannot be shown is named in the
        panel; the pictures of the one before must not stand for it)."""
        with self._lock:
            self._mosaic.content = ""
            self._zoom.content = ""
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

    def send_background_soon(self) -> None:
        """Send the canvas's copy of the picture on screen (or clear it while the pictures
        are hidden) in :data:`BACKGROUND_DELAY`, if it has changed by then."""
        with self._lock:
            if self._timer_pending:
                return  # the pending one will send the latest
            self._timer_pending = True
            self._timer = threading.Timer(BACKGROUND_DELAY, self.send_background)
            self._timer.daemon = True
            self._timer.start()

    def send_background(self) -> None:
        """Send the canvas's copy of the picture on screen now (see
        :meth:`send_background_soon`)."""
        with self._lock:
            self._timer_pending = False
            if not self._background_due:
                return
            self._background_due = False
            image = None if self._hidden else self._current
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
        self._zoom.visible = shown and self._zoom_open
        self._rendered.visible = shown and self._zoom_open and self._blinking
