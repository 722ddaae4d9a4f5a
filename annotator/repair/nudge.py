"""Nudging a pose by a fixed step in the reference camera's frame.

A translation step moves the part along a camera axis; a rotation step turns it about a
camera axis through its surface centroid (turning about the model's origin, which may lie
far off the part, would also move it).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from annotator.dataset.review import RepairOp, RepairStep
from annotator.geometry.transforms import axis_angle, make_transform


class NudgeKind(StrEnum):
    """What a nudge does; the values are review.json's ``kind`` strings."""

    MOVE = "move"  # along a camera axis, by mm
    TURN = "turn"  # about a camera axis through the part's centroid, by degrees


@dataclass(frozen=True)
class Nudge:
    """A step: ``kind`` move (``amount`` mm) or turn (``amount`` degrees), about or along
    camera axis ``axis`` (0 x right, 1 y down, 2 z forward); the sign gives the direction."""

    kind: NudgeKind
    axis: int
    amount: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", NudgeKind(self.kind))  # ValueError for another

    def step(self) -> RepairStep:
        """The step review.json records for it."""
        details = {"kind": self.kind.value, "axis": "xyz"[self.axis], "amount": self.amount}
        return RepairStep(RepairOp.NUDGE, details)


def nudged(T: np.ndarray, step: Nudge, centroid: np.ndarray) -> np.ndarray:
    """``rig_T_model`` T moved by ``step``; ``centroid`` is the part's surface centroid in
    its model frame."""
    e = np.zeros(3)
    e[step.axis] = 1.0
    if step.kind == NudgeKind.MOVE:
        return make_transform(T[:3, :3], T[:3, 3] + step.amount * e)
    dR = axis_angle(e, np.radians(step.amount))
    c = T[:3, :3] @ centroid + T[:3, 3]
    return make_transform(dR @ T[:3, :3], dR @ (T[:3, 3] - c) + c)
