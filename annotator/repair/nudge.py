"""Nudging a pose by a fixed step in the reference camera's frame.

A translation step moves the part along a camera axis; a rotation step turns it about a
camera axis through its surface centroid (turning about the model's origin, which may lie
far off the part, would also move it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from annotator.geometry.transforms import axis_angle, make_transform


@dataclass(frozen=True)
class Nudge:
    """A step: ``kind`` "move" (``amount`` mm) or "turn" (``amount`` degrees), about or along
    camera axis ``axis`` (0 x right, 1 y down, 2 z forward); the sign gives the direction."""

    kind: str
    axis: int
    amount: float

    def to_json(self) -> dict[str, object]:
        return {"op": "nudge", "kind": self.kind, "axis": "xyz"[self.axis], "amount": self.amount}


def nudged(T: np.ndarray, step: Nudge, centroid: np.ndarray) -> np.ndarray:
    """``rig_T_model`` T moved by ``step``; ``centroid`` is the part's surface centroid in
    its model frame."""
    e = np.zeros(3)
    e[step.axis] = 1.0
    if step.kind == "move":
        return make_transform(T[:3, :3], T[:3, 3] + step.amount * e)
    if step.kind != "turn":
        raise ValueError(f"unknown nudge {step.kind!r}")
    dR = axis_angle(e, np.radians(step.amount))
    c = T[:3, :3] @ centroid + T[:3, 3]
    return make_transform(dR @ T[:3, :3], dR @ (T[:3, 3] - c) + c)
