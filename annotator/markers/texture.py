"""ArUco marker images and the mapping from a marker site to its image.

A site's four corners ``TL, TR, BR, BL`` (ArUco order, seen from outside) span the printed
square, black border included, with no white margin. A point ``p = TL + s (TR - TL) +
t (BL - TL)`` with ``(s, t)`` in ``[0, 1]^2`` shows the marker image at column ``s * pixels``
and row ``t * pixels`` (pixel *edges*, so pixel ``(i, j)`` covers ``s in [i, i+1] / pixels``).
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from annotator.errors import UserError


@lru_cache(maxsize=8)
def dictionary(name: str) -> cv2.aruco.Dictionary:
    """The OpenCV predefined ArUco dictionary called ``name`` (e.g. ``DICT_4X4_1000``)."""
    code = getattr(cv2.aruco, name, None)
    if not name.startswith("DICT_") or not isinstance(code, int):
        raise UserError(f"unknown ArUco dictionary {name!r}")
    return cv2.aruco.getPredefinedDictionary(code)


def dictionary_size(name: str) -> int:
    """How many distinct markers the dictionary has."""
    return int(dictionary(name).bytesList.shape[0])


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
