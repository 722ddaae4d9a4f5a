"""ArUco marker images and the mapping from a marker site to its image.

A site's four corners ``TL, TR, BR, BL`` (ArUco order, seen from outside) span the printed
square, black border included, with no white margin. A point ``p = TL + s (TR - TL) +
t (BL - TL)`` with ``(s, t)`` in ``[0, 1]^2`` shows the marker image at column ``s * pixels``
and row ``t * pixels`` (pixel *edges*, so pixel ``(i, j)`` covers ``s in [i, i+1] / pixels``).
"""

from __future__ import annotations

import cv2
import numpy as np

from annotator.errors import UserError
from annotator.markers.dictionary import dictionary, dictionary_size

__all__ = ["dictionary", "dictionary_size", "marker_bits", "marker_image"]


def marker_bits(name: str, marker_id: int) -> np.ndarray:
    """The marker as a (n+2, n+2) uint8 grid of cells (black border included), 0 or 255."""
    d = dictionary(name)
    cells = d.markerSize + 2
    return cv2.aruco.generateImageMarker(d, int(marker_id), cells, borderBits=1)


def marker_image(name: str, marker_id: int, pixels: int) -> np.ndarray:
    """The printed square of marker ``marker_id`` as a ``pixels`` x ``pixels`` uint8 image."""
    if not 0 <= marker_id < dictionary_size(name):
        raise UserError(f"marker id {marker_id} is outside {name} (0..{dictionary_size(name) - 1})")
    bits = marker_bits(name, marker_id)
    return cv2.resize(bits, (pixels, pixels), interpolation=cv2.INTER_NEAREST)
