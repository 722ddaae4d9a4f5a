"""Whether a frame of a sequence shows the same arrangement as the rest of it.

After the solve, each frame read markers of some instances; for each, the solve either kept
some of that frame's observations (the frame agrees with the instance's pose) or left them
all out (the frame's markers place the part elsewhere: two of its markers read, neither
agreeing). Such a frame is flagged inconsistent, and so left out of every export: the
scene's poses are not that frame's truth, whether one part moved under it or the frame
comes from another arrangement. Several parts that disagree are a frame of another
arrangement (copied from another take, or the parts were moved): its pose rests on
whichever few parts happen to agree with it, so it is refused when those are not the most. A frame posed on one part's markers alone is flagged too: nothing in
it checks that part against the rest of the sequence (a camera looking away from the bin).
Pure functions of the solve's index arrays.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass

import numpy as np

__all__ = ["FrameAgreement", "frame_agreement"]

#: A frame in which at least this many parts disagree with the solve may show another
#: arrangement: refused unless more parts agree.
MIN_DISAGREEING = 2


@dataclass(frozen=True)
class FrameAgreement:
    """One frame's parts (instance indices): those its kept markers pose (``agreeing``) and
    those it read markers of that the solve left out entirely, though other frames pose
    them (``disagreeing``)."""

    agreeing: tuple[int, ...]
    disagreeing: tuple[int, ...]

    @property
    def inconsistent(self) -> bool:
        """A part placed differently from the rest of the sequence: the scene's poses are
        not all this frame's truth."""
        return len(self.disagreeing) >= 1

    @property
    def refused(self) -> bool:
        """Several parts placed differently, and the parts that agree are not the most: which
        arrangement the frame shows, the sequence's or another, is not known."""
        return len(self.disagreeing) >= MIN_DISAGREEING and len(self.agreeing) <= len(
            self.disagreeing
        )

    @property
    def single_part(self) -> bool:
        """Posed on the markers of one part only."""
        return len(self.agreeing) == 1


def frame_agreement(
    frame: np.ndarray,
    instance: np.ndarray,
    marker: np.ndarray,
    agrees: np.ndarray,
    n_frames: int,
    *,
    posed: Collection[int] | None = None,
) -> list[FrameAgreement]:
    """Per frame (``0 .. n_frames - 1``), its :class:`FrameAgreement`, from every
    observation's ``frame``, ``instance`` and ``marker`` id and whether it ``agrees`` with
    the solve. A part disagrees when the frame read two of its markers or more and none of
    them agrees (one marker alone is as likely misread or half hidden), and the solve poses
    it: it is in ``posed`` (default: every instance with an observation that agrees). A
    part the solve leaves out (markers misread as another copy's, in a frame or two)
    disagrees with nothing.

    >>> f = np.array([0, 0, 0, 1, 1, 1, 1, 1]); i = np.array([0, 1, 2, 0, 1, 1, 2, 2])
    >>> m = np.array([1, 2, 4, 1, 2, 3, 4, 5]); k = np.array([1, 1, 1, 1, 0, 0, 0, 0], bool)
    >>> a = frame_agreement(f, i, m, k, 2)
    >>> a[1].agreeing, a[1].disagreeing, a[1].refused
    ((0,), (1, 2), True)
    >>> frame_agreement(f, i, m, k, 2, posed={0, 1})[1].disagreeing  # part 2 is not posed
    (1,)
    """
    posed = set(instance[agrees].tolist()) if posed is None else set(posed)
    out = []
    for f in range(n_frames):
        mine = frame == f
        agreeing = sorted(set(instance[mine & agrees].tolist()))
        seen = {
            i
            for i in set(instance[mine].tolist())
            if len(set(marker[mine & (instance == i)].tolist())) >= 2
        }
        disagreeing = sorted((seen & posed) - set(agreeing))
        out.append(FrameAgreement(tuple(agreeing), tuple(disagreeing)))
    return out
