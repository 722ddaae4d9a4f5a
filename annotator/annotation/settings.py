"""The thresholds of auto-annotation, in one record."""

from __future__ import annotations

from dataclasses import dataclass, field

from annotator.annotation.completeness import CompletenessSettings
from annotator.occlusion import AGREEMENT_TOLERANCE_MM


@dataclass(frozen=True)
class AnnotateSettings:
    """Thresholds of the annotation (px, mm, ratios).

    Attributes:
        inlier_px: A marker supports a candidate pose within this reprojection error.
        final_inlier_px: The same after refinement (at least 4 sigma of the corner noise).
        high_residual_px: Above this RMS reprojection error an instance is ``high_residual``.
        ambiguity_ratio: A lone marker is ``ambiguous`` when its two pose solutions' errors
            are within this ratio.
        high_uncertainty_fraction: Above this fraction of the diameter the estimated
            uncertainty is ``high_uncertainty``.
        depth_tolerance_mm: Measured and rendered depth agree within
            ``max(depth_tolerance_mm, 1% of the depth)``.
        depth_min_agreement: Below this agreement an instance is ``depth_disagreement``.
        visibility_step: Occlusion and depth agreement from every ``visibility_step``-th pixel
            of every ``visibility_step``-th row; ``annotator occlusion`` gives the exact rates.
        completeness: The completeness checks' own thresholds.
    """

    inlier_px: float = 4.0
    final_inlier_px: float = 2.5
    high_residual_px: float = 1.0
    ambiguity_ratio: float = 3.0
    high_uncertainty_fraction: float = 0.01
    depth_tolerance_mm: float = AGREEMENT_TOLERANCE_MM
    depth_min_agreement: float = 0.6
    visibility_step: int = 2
    completeness: CompletenessSettings = field(default_factory=CompletenessSettings)
