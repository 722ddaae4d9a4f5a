"""The flags and kinds a reviewer reads: why to look at an instance (:class:`Flag`), at a
frame of a sequence (:class:`FrameFlag`), and what a scene-level warning is about
(:class:`WarningKind`). The values are the JSON strings of annotation.json; a flag this
version does not know is kept as its text (:func:`known_member`).
"""

from __future__ import annotations

from enum import StrEnum
from typing import Any

__all__ = [
    "PHYSICS_FLAGS",
    "Flag",
    "FrameFlag",
    "WarningKind",
    "known_member",
    "sort_flags",
]


class Flag(StrEnum):
    """Reasons a reviewer should look at an instance, in the order annotation.json lists them.

    >>> Flag("high_uncertainty") is Flag.HIGH_UNCERTAINTY
    True
    """

    #: A lone marker / single view whose two pose solutions fit about equally well.
    AMBIGUOUS = "ambiguous"
    #: Only one camera's markers were usable.
    SINGLE_VIEW = "single_view"
    #: Reprojection error well above the corner noise.
    HIGH_RESIDUAL = "high_residual"
    #: Some of the instance's markers disagreed with the others and were dropped.
    REJECTED_MARKERS = "rejected_markers"
    #: The depth rendered at the pose disagrees with the measured depth.
    DEPTH_DISAGREEMENT = "depth_disagreement"
    #: Estimated uncertainty above 1% of the part's diameter.
    HIGH_UNCERTAINTY = "high_uncertainty"
    #: Its markers' sites were measured (``annotator sites``) from one scene each at most,
    #: most likely this one: nothing independent places them.
    UNCHECKED_SITES = "unchecked_sites"
    #: Another copy of the part is posed in the same place (a marker on the wrong copy).
    OVERLAP = "overlap"
    #: A sequence's frames disagree about the part: it moved while the rig moved (the pose
    #: is the one most frames agree with).
    MOVED = "moved"
    #: It reaches inside another part or below the support (:attr:`PhysicsCheck.partners`).
    PENETRATES = "penetrates"
    #: Nothing is under it: its lower half is clear of the support and of every part.
    FLOATS = "floats"
    #: Left to gravity (``annotator check --physics --stability``), it moves.
    UNSTABLE = "unstable"


#: What the physics check may flag (:mod:`annotator.physics`).
PHYSICS_FLAGS = (Flag.PENETRATES, Flag.FLOATS, Flag.UNSTABLE)


class FrameFlag(StrEnum):
    """Why a reviewer should look at a frame (``frames[f].flags`` in annotation.json); the
    values are the JSON strings, as :class:`Flag`'s."""

    #: No marker of a known instance was read: ``scene_T_rig`` is null, not a guess.
    NO_KNOWN_MARKERS = "no_known_markers"
    #: Its markers belong to instances no other frame connects to the rest: null too.
    UNCONNECTED = "unconnected"
    #: Left out of the solve (``reason`` says why): null too.
    OUTLIER = "outlier"
    #: Corners reproject worse than the sequence settings' ``high_reprojection_px`` after the solve.
    HIGH_REPROJECTION = "high_reprojection"
    #: Posed on fewer than the sequence settings' ``few_markers`` marker observations.
    FEW_MARKERS = "few_markers"
    #: Its images are smeared by a motion streak at least :data:`~annotator.annotation.sequence.noise.MOTION_BLUR_PX` long.
    MOTION_BLUR = "motion_blur"
    #: Its markers place several parts differently from the rest of the sequence
    #: (:mod:`~annotator.annotation.consistency`).
    INCONSISTENT = "inconsistent"
    #: Posed on the markers of one part only.
    SINGLE_PART = "single_part"
    #: Posed on fewer than the sequence settings' ``weak_markers`` marker observations, which
    #: at the detector's corner noise leave its pose more uncertain than a posed frame
    #: promises (``frame_max_uncertainty_mm``, ``_deg``): few corners, a shift traded against
    #: a turn. Its ``uncertainty_mm`` and ``uncertainty_deg`` say how much.
    WEAK_GEOMETRY = "weak_geometry"


class WarningKind(StrEnum):
    """What a scene-level warning is about.

    >>> WarningKind.NOTE.value
    'note'
    """

    NO_MARKERS = "no_markers"
    UNEXPLAINED_DEPTH = "unexplained_depth"
    BLURRED = "blurred"
    UNDER_EXPOSED = "under_exposed"
    OVER_EXPOSED = "over_exposed"
    #: Plain text (files of earlier versions, or an entry that is not an object).
    NOTE = "note"


def known_member(enum: type[StrEnum], text: str) -> Any:
    """``text`` as a member of ``enum`` when it is one, else the text itself."""
    try:
        return enum(text)
    except ValueError:
        return text


def sort_flags(flags: list[Flag | str]) -> list[Flag | str]:
    """Flags without repeats, in :class:`Flag`'s order (unknown ones last, as found)."""
    known = [f for f in Flag if f in flags]
    return known + [f for f in dict.fromkeys(flags) if f not in known]
