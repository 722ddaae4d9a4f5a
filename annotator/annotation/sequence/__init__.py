"""Annotating a sequence (one moving rig, FORMAT.md sequences): every frame's rig pose and every
instance's pose from the markers, in three steps.

1. :func:`read_frame`: the markers of every camera of one frame (and the measured depth at
   the centre of each marker the depth camera sees); frames are read independently, in any
   order, by any number of workers.
2. :func:`solve_sequence`: each frame's instances posed on their own (the fixed rig's robust
   consensus, :func:`~annotator.annotation.consensus.pose_instance`); a first frame fixes the
   scene frame; the other frames are placed one at a time, the one that sees most of what is
   already placed first, each from the hypothesis most of those markers agree with; every
   instance is then started from the frame whose pose of it most markers of all frames agree
   with; one bundle adjustment (:mod:`annotator.pnp.bundle`) refines everything over every
   corner and depth; observations that still disagree are left out and the solve repeated.
   A frame nothing connects to the rest keeps ``scene_T_rig: null`` and says why; an instance
   whose markers agree with its pose in some frames and not in others is flagged ``moved``.
   Each corner weighs as its noise says (its marker's motion streak,
   :mod:`~annotator.annotation.frame_quality`; its frame's residuals,
   :mod:`~annotator.annotation.sequence.noise`); with depth, the depth gives the scale
   (:mod:`~annotator.annotation.depth_scale`); a frame that places several parts
   differently from the rest is refused or flagged (:mod:`~annotator.annotation.consistency`).
3. :func:`frame_visibility`: occlusion rates and depth agreement of every instance as each
   frame sees it (the fixed rig's :func:`~annotator.annotation.visibility.add_visibility`).

:func:`annotate_sequence` runs the three on one scene in this process; ``annotator annotate``
runs them as batches over frames and scenes (:mod:`annotator.annotation.sequence.batch`).

The package's modules follow the steps: :mod:`.reading`, :mod:`.placing`, :mod:`.adjustment`
(with :mod:`.noise`: what each corner and depth weighs), :mod:`.solution` (the solve as
records), :mod:`.visibility`, :mod:`.annotation` (annotation.json), :mod:`.solve` (the steps
on one scene) and :mod:`.batch` (many scenes, frames in parallel). Their thresholds are
:class:`~annotator.annotation.settings.SequenceSettings`.
"""

from __future__ import annotations

from annotator.annotation.sequence.annotation import frame_annotations, sequence_annotation
from annotator.annotation.sequence.reading import FrameReading, read_frame
from annotator.annotation.sequence.solution import SequenceSolution
from annotator.annotation.sequence.solve import annotate_sequence, solve_sequence
from annotator.annotation.sequence.visibility import frame_visibility

__all__ = [
    "FrameReading",
    "SequenceSolution",
    "annotate_sequence",
    "frame_annotations",
    "frame_visibility",
    "read_frame",
    "sequence_annotation",
    "solve_sequence",
]
