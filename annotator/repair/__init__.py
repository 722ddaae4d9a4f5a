"""Repairing a pose: refinement against the measured depth and the markers
(:mod:`annotator.refinement`, which ``annotate`` uses too), the other candidate poses of an instance and a start pose for a part that
has none (:mod:`.candidates`), and nudges in the reference camera's frame (:mod:`.nudge`).

Pure functions of the dataset's records, images and depth: the viewer is a thin layer over
them (and a script can repair poses the same way).
"""

from annotator.refinement import Refinement, RefineSettings, Residuals, refine_instance
from annotator.repair.candidates import (
    Candidate,
    alternatives,
    instance_observations,
    start_pose,
    used_observations,
)
from annotator.repair.nudge import Nudge, NudgeKind, nudged

__all__ = [
    "Candidate",
    "Nudge",
    "NudgeKind",
    "RefineSettings",
    "Refinement",
    "Residuals",
    "alternatives",
    "instance_observations",
    "nudged",
    "refine_instance",
    "start_pose",
    "used_observations",
]
