"""The thresholds of auto-annotation, in one record."""

from __future__ import annotations

from dataclasses import dataclass, field

from annotator.annotation.completeness import CompletenessSettings
from annotator.noise import NOISE
from annotator.occlusion import AGREEMENT_TOLERANCE_MM


@dataclass(frozen=True)
class SequenceSettings:
    """Thresholds of a sequence's solve (one moving rig; :mod:`annotator.annotation.sequence`).

    Attributes:
        high_reprojection_px: A frame whose corners reproject worse than this (RMS) after the
            solve is flagged ``high_reprojection``.
        few_markers: A frame posed on fewer marker observations is flagged ``few_markers``.
        moved_share: An instance whose markers disagree with its pose in at least this share
            of the frames that see it (and in two frames or more) moved during the sequence.
        frame_max_uncertainty_mm, frame_max_uncertainty_deg: A frame whose pose is more
            uncertain than this (1-sigma) is not posed: a guess is not written.
        visibility_step: Each frame's occlusion rates from every this-many-th pixel at most
            (``annotator occlusion`` gives every frame's exact rates).
        solve_rounds: Rounds of bundle adjustment, each leaving out what the previous one
            found disagreeing.
        scale_rounds: Rounds of taking the scale from the measured depth and adjusting again.
        scale_sigma: How well the scene's scale is known (1-sigma, relative) when no depth
            measures it: the markers' printed size alone, read by corners a tenth of a pixel
            off on 30 px markers.
        depth_scale_sigma: ... and when the depth measures it: never better than the depth
            map's own scale (its calibration, the surface under a marker's centre).
        joint_share: A frame is placed from the markers of all its placed instances at once
            when this share of them agree with that pose; else from its instances' poses.
        max_candidates: At most this many candidate poses are scored when an instance is
            started from all frames.
        start_frames: At most this many frames' observations start an instance.
        site_sigma_mm: How well each corner of a marker is known on its part (1-sigma, each
            on its own: printing, gluing flat, the corner fit's bias); it does not average out
            over frames.
        glued_share: When at least this share of a sequence's parts (seen in two frames or
            more) reproject worse than ``high_residual_px``, the user is told that
            ``annotator sites`` measures their markers.
        phantom_frames: A pose on one reading whose part this many other frames should see,
            and read no marker of, is a misread or stray marker.
        weak_markers: A frame posed on fewer marker observations states its uncertainty with
            its corners at least :attr:`~annotator.noise.NoiseModel.corner_px` off (the
            sequence's median residual, which the sharp frames set, understates so few
            corners: a shift traded against a turn); where that is more than
            ``frame_max_uncertainty_mm`` (or ``_deg``) it is flagged ``weak_geometry``.
    """

    high_reprojection_px: float = 1.5
    few_markers: int = 3
    moved_share: float = 0.2
    frame_max_uncertainty_mm: float = 2.0
    frame_max_uncertainty_deg: float = 0.5
    visibility_step: int = 4
    solve_rounds: int = 3
    scale_rounds: int = 3
    scale_sigma: float = 0.003
    depth_scale_sigma: float = 0.0003
    joint_share: float = 0.6
    max_candidates: int = 120
    start_frames: int = 24
    site_sigma_mm: float = NOISE.site_mm
    glued_share: float = 0.3
    phantom_frames: int = 3
    weak_markers: int = 25


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
            (each shift in its plane, the turn about its normal), at best, in a pose's
            uncertainty (:mod:`annotator.annotation.site_trust`).
        one_scene_site_mm: 1-sigma of each shift of a site measured from one scene; from
            ``n`` scenes, this over ``n`` (at least ``measured_site_mm``).
        depth_correlation: In a refined pose's uncertainty, the measured points count as
            this many times fewer independent ones (stereo depth is matched over windows).
        depth_bias_mm: 1-sigma of an offset shared by all of a part's measured points along
            their rays: the refinement solves for it (with this prior) and a refined pose's
            uncertainty counts it.
        completeness: The completeness checks' own thresholds.
        sequence: A moving rig's sequences' own thresholds.

    >>> s = AnnotateSettings(refine_max_markers=0)
    >>> s.refine_max_markers, s.depth_bias_mm
    (0, 0.2)
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
    measured_site_mm: float = NOISE.measured_site_mm
    measured_site_deg: float = NOISE.measured_site_deg
    one_scene_site_mm: float = NOISE.one_scene_site_mm
    depth_correlation: float = NOISE.depth_correlation
    depth_bias_mm: float = NOISE.depth_bias_mm
    completeness: CompletenessSettings = field(default_factory=CompletenessSettings)
    sequence: SequenceSettings = field(default_factory=SequenceSettings)
