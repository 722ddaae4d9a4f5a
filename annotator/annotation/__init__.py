"""Auto-annotation of a scene: markers -> robust multi-view pose per instance -> trust, and the
scene's completeness.

Modules, in the order a scene goes through them: :mod:`.scene` (the orchestration),
:mod:`.consensus` (one instance's pose and trust), :mod:`.recovery` (markers read with the
pose's help), :mod:`.visibility` (occlusion, depth agreement), :mod:`.refine` (poses on few
markers refined against the depth), :mod:`.unexplained` and :mod:`.completeness` (depth no
pose explains, image quality), :mod:`.settings` (thresholds), :mod:`.batch` (a whole dataset).

``annotation.json`` (docs/FORMAT.md) is read and written through the records of
:mod:`annotator.dataset.records`; per instance, besides the pose:

- ``uncertainty_mm``: estimated 1-sigma pose error as RMS surface displacement (mm), from the
  joint refinement's covariance (the paper's distance, section 4.1; for a pose refined against
  the depth, both terms' with the depth's offset and the markers' site errors);
- ``reprojection_px``: ``{"rms", "max", "per_camera": {camera: rms}}`` over the markers used;
- ``markers``: ``{camera: {"used": [ids], "rejected": [ids], "recovered": [ids]}}``
  (``recovered``: read through the blur model, with the support of the others);
- ``views``: number of cameras whose markers were used;
- ``depth``: ``{"agreement", "median_abs_mm", "pixels"}`` or null: the fraction of the
  instance's visible pixels (depth camera) where the measured depth is within
  ``max(3 mm, 1% of z)`` of the depth rendered at the pose, and the median absolute difference;
- ``occlusion``: ``{"rate", "per_camera": {camera: rate}}``: 1 - visible/full silhouette pixels,
  posed instances as occluders, plus the depth test in the depth camera;
- ``flags``: reasons a reviewer should look (:class:`annotator.dataset.flags.Flag`).

Top level: ``format``, ``created_at``, ``description_digest``, ``unknown_markers``
(``{camera: [ids]}``, ids that belong to no instance), ``duplicates`` (``{camera: [ids]}`` seen
twice in one image), ``image_quality``, ``warnings`` (``{"kind", "message", ...}``, see
:class:`annotator.dataset.figures.SceneWarning`), ``unexplained_mask`` and ``errors``.
"""
