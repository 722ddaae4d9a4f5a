"""Refining one instance's pose against the measured depth jointly with its markers
(:mod:`.depth`): the review viewer's "R" (through :mod:`annotator.repair`) and
``annotate``'s refinement of poses on few markers (:mod:`annotator.annotation`) share it.

Below :mod:`annotator.annotation` and :mod:`annotator.repair` in the layers: it knows the
cameras, the meshes, the markers' reprojection (:mod:`annotator.pnp`) and the ray caster, not
the annotation's records.
"""

from annotator.refinement.depth import (
    DepthTerm,
    Refinement,
    RefineSettings,
    Residuals,
    measured_points,
    refine_instance,
)

__all__ = [
    "DepthTerm",
    "RefineSettings",
    "Refinement",
    "Residuals",
    "measured_points",
    "refine_instance",
]
