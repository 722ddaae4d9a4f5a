"""Auto-annotation of a scene: markers -> robust multi-view pose per instance -> trust, and the
scene's completeness.

``annotation.json`` (docs/FORMAT.md) is read and written through the records of
:mod:`annotator.dataset.annotation`; per instance, besides the pose:

- ``uncertainty_mm``: estimated 1-sigma pose error as RMS surface displacement (mm), from the
  joint refinement's covariance (the paper's distance, section 4.1);
- ``reprojection_px``: ``{"rms", "max", "per_camera": {camera: rms}}`` over the markers used;
- ``markers``: ``{camera: {"used": [ids], "rejected": [ids], "recovered": [ids]}}``
  (``recovered``: read through the blur model, with the support of the others);
- ``views``: number of cameras whose markers were used;
- ``depth``: ``{"agreement", "median_abs_mm", "pixels"}`` or null: the fraction of the
  instance's visible pixels (depth camera) where the measured depth is within
  ``max(3 mm, 1% of z)`` of the depth rendered at the pose, and the median absolute difference;
- ``occlusion``: ``{"rate", "per_camera": {camera: rate}}``: 1 - visible/full silhouette pixels,
  posed instances as occluders, plus the depth test in the depth camera;
- ``flags``: reasons a reviewer should look, from :data:`FLAGS`.

Top level: ``format``, ``created_at``, ``description_digest``, ``unknown_markers``
(``{camera: [ids]}``, ids that belong to no instance), ``duplicates`` (``{camera: [ids]}`` seen
twice in one image), ``image_quality``, ``warnings`` (``{"kind", "message", ...}``, see
:mod:`annotator.annotation.completeness`), ``unexplained_mask`` and ``errors``.
"""

FLAGS: tuple[str, ...] = (
    "ambiguous",  # a lone marker / single view whose two pose solutions fit about equally well
    "single_view",  # only one camera's markers were usable
    "high_residual",  # reprojection error well above the corner noise
    "rejected_markers",  # some of the instance's markers disagreed with the others and were dropped
    "depth_disagreement",  # the depth rendered at the pose disagrees with the measured depth
    "high_uncertainty",  # estimated uncertainty above 1% of the part's diameter
    "overlap",  # another copy of the part is posed in the same place (a marker on the wrong copy)
)

__all__ = ["FLAGS"]
