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
        refine_max_markers: Poses on at most this many marker ids are refined against the
            measured depth (:mod:`annotator.annotation.refine`); 0: none.
        refine_inner_px: A refined pose fits the measured points of its visible region
            shrunk by this many pixels.
        refine_marker_px: A refined pose is kept only if its markers' RMS reprojection error
            grew by at most this (and is not ``high_residual``).
        measured_site_mm, measured_site_deg: 1-sigma of a site ``annotator sites`` measured
            (each shift in its plane, the turn about its normal), in a refined pose's
            uncertainty.
        depth_correlation: In a refined pose's uncertainty, the measured points count as
            this many times fewer independent ones (stereo depth is matched over windows).
        depth_bias_mm: 1-sigma of an offset shared by all of a part's measured points along
            their rays: the refinement solves for it (with this prior) and a refined pose's
            uncertainty counts it.
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
    refine_max_markers: int = 2
    refine_inner_px: int = 2
    refine_marker_px: float = 0.5
    measured_site_mm: float = 0.1
    measured_site_deg: float = 0.5
    depth_correlation: float = 30.0
    depth_bias_mm: float = 0.2
    completeness: CompletenessSettings = field(default_factory=CompletenessSettings)
