"""How decisions look in the pictures: colours, and the :class:`Look` of a scene (what each
instance's outline and the reviewer's marks must show).

Colours are BGR, as the pictures are drawn with OpenCV (they are sent as RGB).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import cv2
import numpy as np

from annotator.dataset.figures import DepthRegion, depth_regions
from annotator.dataset.review import MissingPart, ReviewStatus

if TYPE_CHECKING:
    from annotator.review import SceneInfo

COLOURS = {
    ReviewStatus.PENDING: (0, 220, 255),  # yellow
    ReviewStatus.ACCEPTED: (60, 220, 60),  # green
    ReviewStatus.REJECTED: (40, 40, 255),  # red
}
FLAG_COLOUR = (255, 0, 255)  # magenta
SELECTED_COLOUR = (255, 255, 255)
UNEXPLAINED_COLOUR = (0, 0, 255)  # pure red: unexplained measured depth
MISSING_COLOUR = (255, 255, 0)  # cyan: "a part has no pose here"


@dataclass(frozen=True)
class Look:
    """What to draw for a scene besides the pictures themselves (hashable: pictures made
    for a look are kept)."""

    states: tuple[tuple[str, ReviewStatus], ...] = ()
    flagged: frozenset[str] = frozenset()
    selected: str | None = None
    missing: tuple[MissingPart, ...] = ()
    regions: tuple[DepthRegion, ...] = ()
    edited: frozenset[str] = frozenset()  # poses repaired by a reviewer (labelled with a *)

    @classmethod
    def of(cls, info: SceneInfo, selected: str | None = None) -> Look:
        """The look of a scene as its files say, with ``selected`` highlighted."""
        return cls(
            states=tuple((p.key, info.instance_status(p.key)) for p in info.poses),
            flagged=frozenset(p.key for p in info.poses if p.flags),
            selected=selected,
            missing=tuple(info.review.missing),
            regions=depth_regions(info.warnings),
            edited=frozenset(info.edited),
        )

    @cached_property
    def _state_of(self) -> dict[str, ReviewStatus]:
        return dict(self.states)

    def colour(self, key: str) -> tuple[int, int, int]:
        return COLOURS[self._state_of.get(key, ReviewStatus.PENDING)]


def label(key: str, flagged: bool) -> str:
    """The short name drawn at an instance's centre, e.g. ``bra01!``."""
    return key.split("/")[0][:3] + key.split("/")[-1] + ("!" if flagged else "")


def put_label(img: np.ndarray, text: str, x: int, y: int, colour: tuple[int, int, int]) -> None:
    """Text with a dark halo, readable on any background."""
    for c, t in (((0, 0, 0), 3), (colour, 1)):
        cv2.putText(img, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, c, t, cv2.LINE_AA)


def put_title(img: np.ndarray, text: str) -> None:
    """A panel's name in its top-left corner."""
    cv2.rectangle(img, (0, 0), (8 + 9 * len(text), 22), (0, 0, 0), -1)
    cv2.putText(img, text, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)


def draw_missing(img: np.ndarray, x: float, y: float) -> None:
    """A "no pose here" mark centred on display position (x, y)."""
    c = (int(round(x)), int(round(y)))
    cv2.circle(img, c, 9, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.circle(img, c, 9, MISSING_COLOUR, 2, cv2.LINE_AA)
    cv2.drawMarker(img, c, MISSING_COLOUR, cv2.MARKER_CROSS, 10, 1, cv2.LINE_AA)


def tint(img: np.ndarray, mask: np.ndarray, colour: tuple[int, int, int], alpha: float) -> None:
    """Blend ``colour`` into ``img`` where ``mask`` (bool, or float weights in 0..1)."""
    w = mask.astype(np.float32) * alpha
    if not w.any():
        return
    w = w[..., None]
    img[:] = (img * (1.0 - w) + np.asarray(colour, np.float32) * w).astype(np.uint8)
