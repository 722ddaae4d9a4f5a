"""The validation viewer: ``annotator review DATASET`` serves it with viser.

Three groups, each above the next:

- :mod:`viewer.server`: the one viser server of a dataset and what it shares between pages:
  :mod:`~viewer.server.app` (the server, one session per browser page),
  :mod:`~viewer.server.access` (who may connect: Origin, token),
  :mod:`~viewer.server.messages` (what a connection may send) and
  :mod:`~viewer.server.startup` (starting viser without waiting forever).
- :mod:`viewer.page`: one browser page: :mod:`~viewer.page.session` (what its keys and clicks
  do), :mod:`~viewer.page.navigation` (its cursor, filter, selection and zoom),
  :mod:`~viewer.page.panel` and :mod:`~viewer.page.panel_text` (the control panel),
  :mod:`~viewer.page.pictures` (the pictures laid over the 3D canvas),
  :mod:`~viewer.page.scene3d` (the 3D canvas), :mod:`~viewer.page.keyguard` (keys kept from
  viser's 3D camera), :mod:`~viewer.page.host` (what a page may ask of its server),
  :mod:`~viewer.page.editor` and :mod:`~viewer.page.repair` (repairs,
  undo) and :mod:`~viewer.page.shown` (what is on the canvas).
- :mod:`viewer.drawing`: the pictures, pixel-exact, made on the server:
  :mod:`~viewer.drawing.overlays` (what they are drawn from), :mod:`~viewer.drawing.mosaic`,
  :mod:`~viewer.drawing.zoom` (and the way back to camera pixels), :mod:`~viewer.drawing.style`
  (colours, what each outline shows), :mod:`~viewer.drawing.memory` (what bounds the
  pictures' memory, whatever the pages announce), :mod:`~viewer.drawing.cache` (scenes
  prepared in the background, before a reviewer gets there).

What is decided about each scene (review.json, repaired poses included) is
:mod:`annotator.review`'s, shared by every page of every server on the dataset. What the
tests and benchmarks drive the viewer with (a bare client of viser's protocol, a server in a
child process, headless Chromium) is in ``devkit/``, which is not installed.
"""
