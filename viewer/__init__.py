"""The validation viewer: ``annotator review DATASET`` serves it with viser.

- :mod:`viewer.state`: what is decided about each scene (review.json), filters, progress;
- :mod:`viewer.overlays`: pixel-exact silhouettes on the images and depth, rendered on the server;
- :mod:`viewer.app`: the viser page, its buttons and hotkeys, prefetching of the next scene.
"""
