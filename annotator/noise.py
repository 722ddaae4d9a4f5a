"""The measurement noise every solver weighs its residuals by, written once (1-sigma).

Each figure is what one kind of measurement is worth; a solver reads the ones its residuals
are made of, as the defaults of its settings (a user changes them there, per run):

- PnP and the sequences' bundle adjustment weigh marker corners by :attr:`NoiseModel.corner_px`
  (a sharp corner as the detector fits it; a blurred one is worse, by its streak) and the
  depth under a marker's centre by :attr:`NoiseModel.marker_depth_mm`;
- the depth refinement weighs measured surface points by :attr:`NoiseModel.depth_mm` and the
  markers of the pose it moves by :attr:`NoiseModel.refined_corner_px`; the covariance of the
  pose it refines floors the corners at :attr:`NoiseModel.corner_px` and the points at
  :attr:`NoiseModel.depth_fit_mm`, counts the points :attr:`NoiseModel.depth_correlation`
  times fewer and adds their shared offset, :attr:`NoiseModel.depth_bias_mm`;
- ``annotator sites`` weighs corners against the part by :attr:`NoiseModel.site_corner_px`
  and depth points by :attr:`NoiseModel.depth_mm`;
- a sequence's uncertainties count each marker corner off on its part by
  :attr:`NoiseModel.site_mm`, and a site ``annotator sites`` measured by
  :attr:`NoiseModel.measured_site_mm` and :attr:`NoiseModel.measured_site_deg`.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["NOISE", "NoiseModel"]


@dataclass(frozen=True)
class NoiseModel:
    """Measurement noise, 1-sigma (px, mm, degrees).

    Attributes:
        corner_px: A sharp marker corner as the detector fits it (the floor of PnP's
            residual sigma: with few corners the residuals underestimate it).
        site_corner_px: A corner against the part's model across scenes: the detector's
            noise and what is left of the site's own error.
        refined_corner_px: A corner in the depth refinement, whose pose the depth pulls off
            the markers' own fit (the sites' error on top of the detector's).
        depth_mm: A measured depth point on a part's surface.
        depth_fit_mm: The floor of the measured points' point-to-plane spread about a refined
            pose (their residuals' own when larger).
        depth_correlation: The measured points count as this many times fewer independent
            ones: stereo depth is matched over windows and smoothed, so neighbouring points
            share their errors.
        depth_bias_mm: An offset all of a part's measured points share along their rays (a
            face seen flat gets one disparity: its depth is off by one amount).
        marker_depth_mm: The depth under a marker's centre, read on a few pixels where the
            printed pattern spoils the stereo match.
        site_mm: Each corner of a marker on its part (printing, gluing flat, the corner
            fit's bias); it does not average out over frames.
        measured_site_mm, measured_site_deg: A site ``annotator sites`` measured (its shift
            in its plane, its turn about its normal), at best.
        one_scene_site_mm: The shift of a site measured from one scene; from ``n`` scenes,
            this over ``n`` (the site error falls about as fast: ``bench_sites.py`` prints it
            by scene count), never below ``measured_site_mm``.
    """

    corner_px: float = 0.3
    site_corner_px: float = 0.4
    refined_corner_px: float = 0.5
    depth_mm: float = 1.0
    depth_fit_mm: float = 0.1
    depth_correlation: float = 30.0
    depth_bias_mm: float = 0.2
    marker_depth_mm: float = 2.0
    site_mm: float = 0.15
    measured_site_mm: float = 0.1
    measured_site_deg: float = 0.5
    one_scene_site_mm: float = 0.25


#: The noise the solvers assume unless told otherwise.
NOISE = NoiseModel()
