"""The validation viewer: ``annotator review DATASET`` serves it with viser.

- :mod:`viewer.app`: the server: shared state and cache, one session per browser page;
- :mod:`viewer.session`: one page: its cursor, panel and canvas, and what its keys and
  clicks do;
- :mod:`viewer.navigation`: one reviewer's cursor, filter, selection and zoom (no viser);
- :mod:`viewer.state`: what is decided about each scene (review.json, repaired poses
  included), progress, polling;
- :mod:`viewer.cache`: scenes prepared in the background before they are shown;
- :mod:`viewer.overlays`: what the pictures are drawn from, rendered pixel-exact on the server;
- :mod:`viewer.mosaic`, :mod:`viewer.zoom`: the pictures, and the way back to camera pixels;
- :mod:`viewer.pictures`: the pictures on the page, laid over the 3D canvas as HTML images;
- :mod:`viewer.style`: colours and what each instance's outline shows;
- :mod:`viewer.panel`: the control panel and hotkeys;
- :mod:`viewer.keyguard`: keys over the pictures kept from viser's 3D camera (A);
- :mod:`viewer.scene3d`: the 3D canvas (clicks on the pictures, the 3D view, the gizmo) and
  its handles;
- :mod:`viewer.repair`: what the repair keys compute (over :mod:`annotator.repair`);
- :mod:`viewer.access`: who may connect (Origin, token);
- :mod:`viewer.frames`: what a connection may send (malformed frames dropped, one log line);
- :mod:`viewer.memory`: what bounds the server's memory (canvas sizes, cache bytes, closed
  pages' memory given back);
- :mod:`viewer.startup`: starting viser's server without waiting forever (the port checked).

What the tests and benchmarks drive it with (a bare client of viser's protocol, a server in
a child process, headless Chromium) is in ``devkit/``, which is not installed.
"""
