"""ArUco detection (OpenCV 4.8+ and 5.x): OpenCV finds the candidate squares, a codebook lookup
identifies them (:mod:`.identify`), and an edge fit refines their corners (:mod:`.corners`).

OpenCV's detector is given a one-marker dictionary, so that it returns every candidate square
(as "rejected") almost for free; the candidates that thresholding cannot identify get a second
reading through the blur model (:mod:`.deblur`).

Corner order is OpenCV's: top-left, top-right, bottom-right, bottom-left of the printed marker.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from annotator.detection.corners import refine_corners
from annotator.detection.deblur import estimate_blur, read_soft_bits
from annotator.detection.identify import Codebook, identify, one_per_marker, pack_bits
from annotator.io.images import to_gray8
from annotator.markers.texture import dictionary

#: Candidates read through the blur model need cells of at least this many pixels: below,
#: the model has too few samples per cell to tell the bits apart.
SOFT_MIN_PX_PER_CELL = 2.0

#: Images blurred more than this (px) get a second search for candidate squares with a looser
#: polygon fit (on blurred renderings it finds visible markers the first search misses).
SECOND_PASS_BLUR_PX = 1.5


@dataclass(frozen=True)
class Detection:
    """One detected marker: its id and its 4 corners (4, 2) in pixels, OpenCV order.

    ``soft``: the id was read only through the blur model (:mod:`.deblur`), not by
    thresholding; such a reading needs the support of other markers before it is trusted.
    """

    id: int
    corners: np.ndarray
    soft: bool = False


@dataclass(frozen=True)
class ImageReading:
    """Everything the detector saw in one image.

    Attributes:
        markers: Identified markers (some ``soft``).
        unread: (K, 4, 2) candidate squares that could not be identified, corners as found.
        unread_bits: (K, n, n) their inner bits through the blur model (True = white), in
            their own corner order, and ``unread_margin`` the bits' margins (contrasts).
        blur_px: The image's blur (Gaussian sigma, px) estimated from the candidate squares,
            or None when there were none large enough.
    """

    markers: list[Detection]
    unread: np.ndarray
    unread_bits: np.ndarray
    unread_margin: np.ndarray
    blur_px: float | None


class MarkerDetector:
    """Detects markers of one dictionary; build once, call :meth:`detect` per image.

    Args:
        dictionary_name: An OpenCV predefined dictionary, e.g. ``DICT_4X4_1000``.
        opencv_only: Use OpenCV's own identification and sub-pixel corners instead (several
            times slower, corners biased on small markers): the reference the fast path is
            tested against.

    A 60 px marker drawn from pixel 30 on: its outline's corners are half a pixel before
    the first pixel centre (pixel centres are at integer coordinates).

    >>> import cv2, numpy as np
    >>> image = np.full((120, 120), 255, np.uint8)
    >>> d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_1000)
    >>> image[30:90, 30:90] = cv2.aruco.generateImageMarker(d, 7, 60)
    >>> [(m.id, m.corners.round(1).tolist()) for m in MarkerDetector("DICT_4X4_1000").detect(image)]
    [(7, [[29.5, 29.5], [89.5, 29.5], [89.5, 89.5], [29.5, 89.5]])]
    """

    def __init__(self, dictionary_name: str, *, opencv_only: bool = False) -> None:
        full = dictionary(dictionary_name)
        params = cv2.aruco.DetectorParameters()
        self.opencv_only = opencv_only
        if opencv_only:
            params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
            self._detector = cv2.aruco.ArucoDetector(full, params, cv2.aruco.RefineParameters())
            return
        self._codebook = Codebook.of(full, error_correction_rate=params.errorCorrectionRate)
        self._border_tolerance = int(full.markerSize**2 * params.maxErroneousBitsInBorderRate)
        self._min_std = float(params.minOtsuStdDev)
        # Keep every candidate: OpenCV groups nested or nearby squares and, given a one-marker
        # dictionary, returns only one per group, losing a marker whose outline nests in
        # another (a marker next to a dark edge). On rendered bin scenes OpenCV's default loses
        # some markers that OpenCV's own search finds, and this loses none.
        params.minMarkerDistanceRate = 0.0
        probe = cv2.aruco.Dictionary(full.bytesList[:1].copy(), full.markerSize, 0)
        self._detector = cv2.aruco.ArucoDetector(probe, params, cv2.aruco.RefineParameters())
        loose = cv2.aruco.DetectorParameters()
        loose.minMarkerDistanceRate = 0.0
        loose.polygonalApproxAccuracyRate = 0.06  # OpenCV's default: 0.03
        self._blurred_detector = cv2.aruco.ArucoDetector(probe, loose, cv2.aruco.RefineParameters())

    def detect(self, image: np.ndarray) -> list[Detection]:
        """Detect markers in an 8/16-bit grey or colour image (thresholded reading only)."""
        gray = to_gray8(image)
        found, ids, rejected = self._detector.detectMarkers(gray)
        if self.opencv_only:
            if ids is None or len(ids) == 0:
                return []
            quads = np.asarray(found, dtype=np.float64).reshape(-1, 4, 2)
            return [Detection(int(i), q) for i, q in zip(np.ravel(ids), quads)]
        ids, quads, _ = self._identify(gray, _candidates(found, rejected))
        return [Detection(int(i), q) for i, q in zip(ids, self.refine(gray, quads))]

    def read(self, image: np.ndarray) -> ImageReading:
        """:meth:`detect`, then a second reading, through the blur model, of the candidate
        squares that thresholding could not identify (see :mod:`.deblur`)."""
        if self.opencv_only:
            raise ValueError("read() needs the project's own reader (opencv_only=False)")
        gray = to_gray8(image)
        found, _, rejected = self._detector.detectMarkers(gray)
        candidates = _candidates(found, rejected)
        n = self._codebook.marker_size
        # The blur model samples the image as float, twice: converted once.
        grayf = gray.astype(np.float32)
        blur = estimate_blur(grayf, candidates, n + 2) if len(candidates) else None
        if blur is not None and blur > SECOND_PASS_BLUR_PX:
            # Blurred corners are round: a looser polygon fit finds squares the first missed.
            more = _candidates(*self._blurred_detector.detectMarkers(gray)[::2])
            candidates = _merge_candidates(candidates, more)
        ids, quads, identified = self._identify(gray, candidates)
        rest = candidates[~identified]
        sides = np.linalg.norm(rest - np.roll(rest, 1, axis=1), axis=2).min(axis=1)
        rest = rest[sides >= SOFT_MIN_PX_PER_CELL * (n + 2)] if len(rest) else rest
        soft = read_soft_bits(grayf, rest, n, blur if blur is not None else 1.0)
        # An exact code with a clean border is a soft identification; the others stay unread.
        codes = pack_bits(soft.bits)
        soft_ids, rot = self._codebook.lookup_exact(codes)
        ok = (soft_ids >= 0) & (soft.border_errors <= 1)
        turned = rest[np.arange(len(rest))[:, None], (np.arange(4)[None, :] - rot[:, None]) % 4]
        s_ids, s_quads = one_per_marker(
            soft_ids[ok],
            turned[ok].reshape(-1, 4, 2),
            np.linalg.norm(turned[ok] - np.roll(turned[ok], 1, axis=1), axis=2).sum(axis=1),
        )
        # Both readings' corners in one fit (each quad's own, whoever shares the call).
        corners = self.refine(gray, np.concatenate([quads.reshape(-1, 4, 2), s_quads]))
        markers = [Detection(int(i), q) for i, q in zip(ids, corners[: len(ids)])]
        known = {int(m.id) for m in markers}
        markers += [
            Detection(int(i), q, soft=True)
            for i, q in zip(s_ids, corners[len(ids) :])
            if int(i) not in known
        ]
        return ImageReading(markers, rest[~ok], soft.bits[~ok], soft.margin[~ok], blur)

    def _identify(
        self, gray: np.ndarray, candidates: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return identify(
            gray,
            candidates,
            self._codebook,
            border_tolerance=self._border_tolerance,
            min_std=self._min_std,
        )

    def refine(self, gray: np.ndarray, quads: np.ndarray) -> np.ndarray:
        """Sub-pixel corners of (N, 4, 2) quads (see :mod:`.corners`)."""
        return refine_corners(gray, quads, cells=self._codebook.marker_size + 2)


def _merge_candidates(first: np.ndarray, more: np.ndarray) -> np.ndarray:
    """``first`` and those of ``more`` that are not the same square as one of ``first``'s
    (every corner within 2 px, in some rotation)."""
    if len(first) == 0 or len(more) == 0:
        return first if len(more) == 0 else more
    # Squares whose every corner is within 2 px have centres within 2 px too: only the pairs
    # whose centres are within 3 px (a margin for rounding) are compared corner by corner.
    gap = np.abs(more.mean(axis=1)[:, None] - first.mean(axis=1)[None]).max(axis=2)  # (M, N)
    m, k = np.nonzero(gap < 3.0)
    same = np.zeros(len(more), bool)
    for r in range(4):
        d = np.linalg.norm(more[m] - np.roll(first, r, axis=1)[k], axis=2).max(axis=1)
        same[m[d < 2.0]] = True
    return np.concatenate([first, more[~same]])


def _candidates(found, rejected) -> np.ndarray:
    """OpenCV's candidate squares as one (N, 4, 2) float array."""
    quads = (*found, *rejected)
    if not quads:
        return np.zeros((0, 4, 2))
    # Joined as OpenCV gives them (float32), then converted at once.
    return np.concatenate(quads, axis=None).reshape(-1, 4, 2).astype(np.float64)
