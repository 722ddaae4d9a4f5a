"""Keys over the pictures are the review's alone: **A** (the next candidate pose) does not
also move viser's 3D camera, which listens to W A S D Q E and the arrows on the whole page.

Why: the pictures lie over the 3D canvas (:mod:`viewer.pictures`), so a camera that moves
under them is not seen, yet it is there when the reviewer presses V, somewhere else. And
every frame of its motion is drawn: on a software renderer (headless Chromium, many
laptops) each WebGL frame is read back for compositing, 25-60 ms of the page's main thread,
and a motion takes a dozen, so the new overlay waited for them. In the 3D view (no picture
shown) A moves the camera as viser does, and still cycles the candidates.

How: viser 1.1.1 has no option to turn its keyboard camera off. Its command hotkeys
(Mantine's ``useHotkeys``) listen on ``document.documentElement`` and its camera on
``document``, so a key event bubbles through the first before the second. A listener on
``document.documentElement`` that stops A's propagation while a picture is on the page
leaves the hotkey working and the camera still. viser's documented ``add_html`` is the way
in: :data:`GUARD_HTML` is an empty image whose ``onload`` attribute installs that listener,
once per page. A picture is known by :data:`PICTURE_MARK` (viser unmounts hidden HTML
elements, so a marked element on the page is a picture shown).
"""

from __future__ import annotations

import html
import json

#: The attribute every picture element carries (:mod:`viewer.pictures`).
PICTURE_MARK = "data-review-picture"
#: Keys kept from viser's camera while a picture is shown (``KeyboardEvent.code``, with no
#: modifier): those among the review's hotkeys that viser's camera also takes.
GUARDED_KEYS = ("KeyA",)

_SCRIPT = (
    "if(!window.__reviewKeyGuard){window.__reviewKeyGuard=true;"
    "document.documentElement.addEventListener('keydown',function(e){"
    f"if({json.dumps(list(GUARDED_KEYS))}.includes(e.code)&&!e.ctrlKey&&!e.metaKey&&!e.altKey"
    f"&&document.querySelector('[{PICTURE_MARK}]'))e.stopPropagation();"
    "});}"
)
_PIXEL = "data:image/gif;base64,R0lGODlhAQABAAAAACH5BAEKAAEALAAAAAABAAEAAAICTAEAOw=="
#: An empty element for the control panel that installs the guard when the page shows it.
GUARD_HTML = (
    f'<img alt="" width="0" height="0" style="display:none" src="{_PIXEL}" '
    f'onload="{html.escape(_SCRIPT, quote=True)}">'
)
