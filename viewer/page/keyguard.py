"""Keys over the pictures are the review's alone: a review key (A, the next candidate pose;
on other keyboard layouts Z, O, ... too) does not also move viser's 3D camera, which listens
to the keys at the places of W A S D Q E and the arrows on the whole page.

Why: the pictures lie over the 3D canvas (:mod:`viewer.page.pictures`), so a camera that moves
under them is not seen, yet it is there when the reviewer presses V, somewhere else. And
every frame of its motion is drawn: on a software renderer (headless Chromium, many
laptops) each WebGL frame is read back for compositing, 25-60 ms of the page's main thread,
and a motion takes a dozen, so the new overlay waited for them. In the 3D view (no picture
shown) those keys move the camera as viser does, and still do what they do in the review.

How: viser 1.1.1 has no option to turn its keyboard camera off. Its command hotkeys
(Mantine's ``useHotkeys``) listen on ``document.documentElement`` and match the character
typed (``KeyboardEvent.key``); its camera listens on ``document`` and matches the key's place
(``KeyboardEvent.code``, :data:`CAMERA_CODES`). A key event bubbles through the first before
the second, so a listener on ``document.documentElement`` that stops the propagation of a
review key typed at a camera key's place, while a picture is on the page, leaves the hotkey
working and the camera still. viser's documented ``add_html`` is the way in:
:func:`guard_html` is an empty image whose ``onload`` attribute installs that listener, once
per page. A picture is known by :data:`PICTURE_MARK` (viser unmounts hidden HTML elements,
so a marked element on the page is a picture shown).
"""

from __future__ import annotations

import html
import json
from collections.abc import Iterable

#: The attribute every picture element carries (:mod:`viewer.page.pictures`).
PICTURE_MARK = "data-review-picture"
#: Where viser's keyboard camera keys are (``KeyboardEvent.code``: the key's place on the
#: keyboard, whatever character it types), as its client's ``CameraControls.tsx`` lists them.
CAMERA_CODES = (
    "KeyW",
    "KeyA",
    "KeyS",
    "KeyD",
    "KeyQ",
    "KeyE",
    "ArrowUp",
    "ArrowDown",
    "ArrowLeft",
    "ArrowRight",
)
_PIXEL = "data:image/gif;base64,R0lGODlhAQABAAAAACH5BAEKAAEALAAAAAABAAEAAAICTAEAOw=="


def guard_html(hotkeys: Iterable[str]) -> str:
    """An empty element for the control panel that installs the guard for ``hotkeys`` (the
    review's keys without modifier, as viser's hotkeys match them: by the character typed)
    when the page shows it.

    >>> html = guard_html(["A", "Z"])
    >>> html.startswith("<img") and html.count("<") == 1  # one element, its script quoted
    True
    """
    keys = sorted({k.lower() for k in hotkeys})
    script = (
        "if(!window.__reviewKeyGuard){window.__reviewKeyGuard=true;"
        f"var keys={json.dumps(keys)},codes={json.dumps(list(CAMERA_CODES))};"
        "document.documentElement.addEventListener('keydown',function(e){"
        "if(keys.includes(e.key.toLowerCase())&&codes.includes(e.code)"
        "&&!e.ctrlKey&&!e.metaKey&&!e.altKey"
        f"&&document.querySelector('[{PICTURE_MARK}]'))e.stopPropagation();"
        "});}"
    )
    return (
        f'<img alt="" width="0" height="0" style="display:none" src="{_PIXEL}" '
        f'onload="{html.escape(script, quote=True)}">'
    )
