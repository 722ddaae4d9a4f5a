"""Pose from marker corners: per-camera initialisation and joint multi-camera refinement.

An *observation* is one marker's four corners seen by one camera. Poses are ``rig_T_model``
(the reference camera's frame), so that every camera's residuals constrain the same pose.
"""

from annotator.pnp.multiview import (
    Observation,
    PoseEstimate,
    candidate_poses,
    iter_candidate_poses,
    refine_pose,
    reprojection_errors,
)
from annotator.pnp.uncertainty import rms_displacement_matrix, rms_uncertainty

__all__ = [
    "Observation",
    "PoseEstimate",
    "candidate_poses",
    "iter_candidate_poses",
    "refine_pose",
    "reprojection_errors",
    "rms_displacement_matrix",
    "rms_uncertainty",
]
