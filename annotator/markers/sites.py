"""Where the markers go on a part: the record every stage shares (object.yaml's ``markers``).

Corners are in ArUco order (top-left, top-right, bottom-right, bottom-left, seen from
outside the part) in the model frame, in mm (docs/FORMAT.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MarkerSites:
    """Marker sites on a part: ``size`` mm squares, ``corners`` (S, 4, 3) in ArUco order."""

    size: float
    corners: np.ndarray
