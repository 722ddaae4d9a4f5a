"""Recorded sequences into a moving rig's dataset (``annotator ingest``, FORMAT.md sequences).

:mod:`.sources` reads a video or a folder of colour and depth images as capture tools name
them and pairs depth with colour; :mod:`.selection` picks every N-th frame and drops those
too blurred to read; :mod:`.write` writes the frames as the dataset stores them and
frames.json; :mod:`.scene` runs the whole (:func:`~.scene.ingest_scene`).
"""
