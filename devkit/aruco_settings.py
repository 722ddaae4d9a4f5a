"""OpenCV's own ArUco detector at the settings a user could try to find markers that
``export --remove-markers`` left behind: its defaults, and each knob turned the way that
finds more (wider thresholding windows, smaller markers, sub-pixel corners, more
bits of the border allowed wrong, rougher polygons)."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np


def _default(p: cv2.aruco.DetectorParameters) -> None:
    pass


def _wide_windows(p: cv2.aruco.DetectorParameters) -> None:
    p.adaptiveThreshWinSizeMin, p.adaptiveThreshWinSizeMax = 3, 53
    p.adaptiveThreshWinSizeStep = 4


def _small(p: cv2.aruco.DetectorParameters) -> None:
    p.minMarkerPerimeterRate = 0.01


def _subpix(p: cv2.aruco.DetectorParameters) -> None:
    p.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX


def _lenient_bits(p: cv2.aruco.DetectorParameters) -> None:
    p.perspectiveRemovePixelPerCell = 8
    p.maxErroneousBitsInBorderRate = 0.6


def _rough_polygons(p: cv2.aruco.DetectorParameters) -> None:
    p.polygonalApproxAccuracyRate = 0.1


#: Name -> how the setting departs from OpenCV's defaults.
SETTINGS: dict[str, Callable[[cv2.aruco.DetectorParameters], None]] = {
    "default": _default,
    "wide threshold windows": _wide_windows,
    "min perimeter 0.01": _small,
    "subpix corners": _subpix,
    "8 px per cell, 60% border bits": _lenient_bits,
    "polygon accuracy 0.1": _rough_polygons,
}


def detector(setting: str, dictionary: int = cv2.aruco.DICT_4X4_1000) -> cv2.aruco.ArucoDetector:
    """OpenCV's detector of ``dictionary`` at the setting named ``setting``."""
    params = cv2.aruco.DetectorParameters()
    SETTINGS[setting](params)
    d = cv2.aruco.getPredefinedDictionary(dictionary)
    return cv2.aruco.ArucoDetector(d, params, cv2.aruco.RefineParameters())


def detections(det: cv2.aruco.ArucoDetector, image: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """Every marker ``det`` finds in ``image``: its id and (4, 2) corners."""
    corners, ids, _ = det.detectMarkers(image)
    if ids is None:
        return []
    # ids come back (N,) in OpenCV 5 and (N, 1) in 4.x
    return [
        (int(i), np.asarray(c, float).reshape(4, 2))
        for i, c in zip(np.asarray(ids).reshape(-1), corners)
    ]


def new_in(
    found: list[tuple[int, np.ndarray]], reference: list[tuple[int, np.ndarray]], tol: float = 3.0
) -> list[tuple[int, np.ndarray]]:
    """The detections of ``found`` that ``reference`` does not have (same id, every corner
    within ``tol`` px): what an image shows that a render without markers does not, i.e.
    not the detector's false reading of the parts' own edges."""
    return [
        (i, c)
        for i, c in found
        if not any(j == i and np.abs(c - r).max() <= tol for j, r in reference)
    ]
