"""ArUco detection (OpenCV 4.8+ and 5.x): OpenCV finds the candidate squares, a codebook lookup
identifies them, and an edge fit refines their corners.

*Identification.* OpenCV compares every candidate square with every marker of the dictionary
(and its four rotations), which with the 1000-marker dictionaries that parts need is most of
the detection's time (``benchmarks/bench_detection.py``). Here OpenCV's detector is given a one-marker
dictionary, so that it returns every candidate square (as "rejected") almost for free, and
each candidate's bits are read and looked up in a sorted table of all codes in all rotations.
The bits are read the way OpenCV reads them: the square is resampled to ``4`` pixels per cell,
split by Otsu's threshold, the border cells must be black (up to OpenCV's tolerance), and a
cell is white if most of its samples are. Dictionaries with error correction fall back to the
nearest code within OpenCV's number of correctable bits.

*Corners.* OpenCV's sub-pixel refinement leaves the corners of small markers (20-40 px) about
0.4 px inside the true square (measured on rendered images whose corners are known exactly).
So each identified quad is refined here: cv2.cornerSubPix with a small window first, then along
each side, at many points, the centroid of the intensity gradient across the side (within half
a cell each way), a line fitted to these points, and the corners where adjacent lines meet. For
a step edge under any symmetric blur, the centroid of the gradient is the edge itself, hence no
bias (``benchmarks/bench_detection.py`` measures it against OpenCV's sub-pixel corners on
rendered bin scenes).

Corner order is OpenCV's: top-left, top-right, bottom-right, bottom-left of the printed marker.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from annotator.detection.deblur import estimate_blur, read_soft_bits
from annotator.detection.homography import apply_homographies, unit_square_homographies
from annotator.io.images import to_gray8
from annotator.markers.texture import dictionary

#: Samples per cell side when reading a candidate's bits (OpenCV's perspectiveRemovePixelPerCell).
PIXELS_PER_CELL = 4

#: A candidate with a side shorter than this many pixels per cell (border included) is not
#: read: its cells are below the pixel size, and seen edge-on a square's bits can read as any
#: code (measured: such slivers were false identifications, which OpenCV makes too).
MIN_PX_PER_CELL = 1.0

#: Candidates read through the blur model need cells of at least this many pixels: below,
#: the model has too few samples per cell to tell the bits apart.
SOFT_MIN_PX_PER_CELL = 2.0

#: Images blurred more than this (px) get a second search for candidate squares with a looser
#: polygon fit (measured on sigma = 2 px renderings: 7% more of the visible markers found).
SECOND_PASS_BLUR_PX = 1.5


#: Half-size of cv2.cornerSubPix's window before the edge fit; larger windows reach across
#: the cells of 20 px markers and pull the corners inwards (measured: 2 px gives the
#: smallest corner error on rendered markers).
SUBPIX_HALF_WINDOW = 2
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)


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
        # another (a marker next to a dark edge). Measured on rendered bin scenes: with
        # OpenCV's default 29 of ~1200 markers that OpenCV's own search finds are lost, none
        # without.
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
        blur = estimate_blur(gray, candidates, n + 2) if len(candidates) else None
        if blur is not None and blur > SECOND_PASS_BLUR_PX:
            # Blurred corners are round: a looser polygon fit finds squares the first missed.
            more = _candidates(*self._blurred_detector.detectMarkers(gray)[::2])
            candidates = _merge_candidates(candidates, more)
        ids, quads, identified = self._identify(gray, candidates)
        markers = [Detection(int(i), q) for i, q in zip(ids, self.refine(gray, quads))]
        rest = candidates[~identified]
        sides = np.linalg.norm(rest - np.roll(rest, 1, axis=1), axis=2).min(axis=1)
        rest = rest[sides >= SOFT_MIN_PX_PER_CELL * (n + 2)] if len(rest) else rest
        soft = read_soft_bits(gray, rest, n, blur if blur is not None else 1.0)
        # An exact code with a clean border is a soft identification; the others stay unread.
        codes = pack_bits(soft.bits)
        soft_ids, rot = self._codebook.lookup_exact(codes)
        ok = (soft_ids >= 0) & (soft.border_errors <= 1)
        turned = rest[np.arange(len(rest))[:, None], (np.arange(4)[None, :] - rot[:, None]) % 4]
        s_ids, s_quads = _one_per_marker(
            soft_ids[ok],
            turned[ok].reshape(-1, 4, 2),
            np.linalg.norm(turned[ok] - np.roll(turned[ok], 1, axis=1), axis=2).sum(axis=1),
        )
        known = {int(m.id) for m in markers}
        markers += [
            Detection(int(i), q, soft=True)
            for i, q in zip(s_ids, self.refine(gray, s_quads))
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
        """Sub-pixel corners of (N, 4, 2) quads (see the module docstring)."""
        if len(quads) == 0:
            return quads
        # A small-window corner fit first, so that the edge fit starts near the sides.
        start: np.ndarray = quads.reshape(-1, 1, 2).astype(np.float32)
        window = (SUBPIX_HALF_WINDOW, SUBPIX_HALF_WINDOW)
        start = cv2.cornerSubPix(gray, start, window, (-1, -1), _SUBPIX_CRITERIA)
        cells = self._codebook.marker_size + 2
        return refine_quads(gray, start.reshape(-1, 4, 2).astype(np.float64), cells=cells)


def _merge_candidates(first: np.ndarray, more: np.ndarray) -> np.ndarray:
    """``first`` and those of ``more`` that are not the same square as one of ``first``'s
    (every corner within 2 px, in some rotation)."""
    if len(first) == 0 or len(more) == 0:
        return first if len(more) == 0 else more
    same = np.zeros(len(more), bool)
    for r in range(4):
        turned = np.roll(first, r, axis=1)
        d = np.linalg.norm(more[:, None] - turned[None], axis=3).max(axis=2)  # (M, N)
        same |= (d < 2.0).any(axis=1)
    return np.concatenate([first, more[~same]])


def _candidates(found, rejected) -> np.ndarray:
    """OpenCV's candidate squares as one (N, 4, 2) float array."""
    quads = [np.asarray(q, np.float64).reshape(4, 2) for q in (*found, *rejected)]
    return np.stack(quads) if quads else np.zeros((0, 4, 2))


@dataclass(frozen=True)
class Codebook:
    """Every code of a dictionary in its four rotations, sorted for lookup.

    Attributes:
        marker_size: Inner bits per side (4 for ``DICT_4X4_*``).
        codes: (4n,) uint64 codes, sorted; bits read row by row, first bit most significant.
        ids: (4n,) marker id of each code.
        rotations: (4n,) ``k`` such that the code is the marker turned ``k`` quarter turns
            counter-clockwise (``np.rot90``).
        max_correction: Bits that may be wrong and still identify a marker (OpenCV's rule).
    """

    marker_size: int
    codes: np.ndarray
    ids: np.ndarray
    rotations: np.ndarray
    max_correction: int

    @classmethod
    def of(cls, d: cv2.aruco.Dictionary, *, error_correction_rate: float = 0.6) -> Codebook:
        n = d.markerSize
        bits = np.stack(
            [
                cv2.aruco.Dictionary.getBitsFromByteList(d.bytesList[i : i + 1], n)
                for i in range(len(d.bytesList))
            ]
        )
        turned = np.stack([np.rot90(bits, k, axes=(1, 2)) for k in range(4)], axis=1)
        codes = pack_bits(turned.reshape(-1, n, n))
        order = np.argsort(codes, kind="stable")
        ids = np.repeat(np.arange(len(bits)), 4)
        rotations = np.tile(np.arange(4), len(bits))
        return cls(
            n,
            codes[order],
            ids[order],
            rotations[order],
            int(d.maxCorrectionBits * error_correction_rate),
        )

    def lookup_exact(self, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Marker id and rotation of each code that is exactly a marker's; id -1 otherwise."""
        at = np.clip(np.searchsorted(self.codes, codes), 0, len(self.codes) - 1)
        exact = self.codes[at] == codes
        return np.where(exact, self.ids[at], -1), np.where(exact, self.rotations[at], 0)

    def lookup(self, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Marker id and rotation of each code; id -1 where no marker is close enough."""
        ids, rot = self.lookup_exact(codes)
        exact = ids >= 0
        if self.max_correction > 0 and not exact.all():
            for k in np.flatnonzero(~exact):
                dist = _popcount(self.codes ^ codes[k])
                best = int(np.argmin(dist))
                if dist[best] <= self.max_correction:
                    ids[k], rot[k] = self.ids[best], self.rotations[best]
        return ids, rot


def pack_bits(bits: np.ndarray) -> np.ndarray:
    """(..., n, n) 0/1 bits to (...,) uint64 codes, row by row, first bit most significant."""
    flat = bits.reshape(*bits.shape[:-2], -1).astype(np.uint64)
    weights = np.left_shift(np.uint64(1), np.arange(flat.shape[-1] - 1, -1, -1, dtype=np.uint64))
    return (flat * weights).sum(axis=-1, dtype=np.uint64)


def _popcount(x: np.ndarray) -> np.ndarray:
    return np.unpackbits(x.astype("<u8").view(np.uint8).reshape(-1, 8), axis=1).sum(axis=1)


def identify(
    gray: np.ndarray,
    quads: np.ndarray,
    codebook: Codebook,
    *,
    border_tolerance: int,
    min_std: float = 5.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read the bits of (N, 4, 2) candidate quads and look them up.

    Returns the ids (M,) and quads (M, 4, 2) of the markers found, corners turned to OpenCV's
    order (the marker's top-left first), and which of the N candidates were identified.
    Several candidates of one printed marker are kept once (see :func:`_one_per_marker`).
    """
    if len(quads) == 0:
        return np.zeros(0, int), np.zeros((0, 4, 2)), np.zeros(0, bool)
    n = codebook.marker_size
    cells = n + 2
    side = cells * PIXELS_PER_CELL
    g = np.arange(side) / (side - 1)
    grid = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)  # (u, v): column, row
    pts = apply_homographies(unit_square_homographies(quads), grid)
    h, w = gray.shape
    xy = np.rint(pts.reshape(-1, 2)).astype(int)
    values = (
        gray[np.clip(xy[:, 1], 0, h - 1), np.clip(xy[:, 0], 0, w - 1)]
        .astype(np.float32)
        .reshape(len(quads), -1)
    )
    white = values > _otsu_thresholds(values)[:, None]
    low = values.std(axis=1) < min_std  # no contrast: OpenCV calls every cell by the mean
    white[low] = (values[low].mean(axis=1) > 127)[:, None]
    frac = white.reshape(-1, cells, PIXELS_PER_CELL, cells, PIXELS_PER_CELL).mean(axis=(2, 4))
    bits = frac > 0.5
    border = bits.copy()
    border[:, 1:-1, 1:-1] = False
    ok = border.sum(axis=(1, 2)) <= border_tolerance
    sides = np.linalg.norm(quads - np.roll(quads, 1, axis=1), axis=2)  # (N, 4) px
    ok &= sides.min(axis=1) >= MIN_PX_PER_CELL * cells
    ids = np.full(len(quads), -1)
    rot = np.zeros(len(quads), int)
    ids[ok], rot[ok] = codebook.lookup(pack_bits(bits[ok, 1:-1, 1:-1]))
    ok &= ids >= 0
    # np.roll(quad, k, axis=0) for every quad at once: corner i comes from corner i - k.
    turned = quads[np.arange(len(quads))[:, None], (np.arange(4)[None, :] - rot[:, None]) % 4]
    ids_kept, quads_kept = _one_per_marker(
        ids[ok], turned[ok].reshape(-1, 4, 2), sides[ok].sum(axis=1)
    )
    return ids_kept, quads_kept, ok


def _one_per_marker(
    ids: np.ndarray, quads: np.ndarray, perimeter: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Keep one of several quads of the same id on the same spot (nested or near-identical
    contours of one printed marker): the one with the largest perimeter. Copies of an id far
    apart are all kept, for the caller to report."""
    centre = quads.mean(axis=1)
    keep: list[int] = []
    kept_where: dict[int, list[int]] = {}  # id -> indices kept so far
    for k in np.argsort(-perimeter, kind="stable"):
        same = kept_where.setdefault(int(ids[k]), [])
        if all(np.linalg.norm(centre[j] - centre[k]) >= perimeter[j] / 8 for j in same):
            same.append(int(k))
            keep.append(int(k))
    keep.sort()
    return ids[keep], quads[keep]


def _otsu_thresholds(values: np.ndarray) -> np.ndarray:
    """Otsu's threshold of each row: the split maximising the between-class variance."""
    v = np.sort(values, axis=1)
    m = v.shape[1]
    c = np.cumsum(v, axis=1)
    k = np.arange(1, m)
    mu0 = c[:, :-1] / k
    mu1 = (c[:, -1:] - c[:, :-1]) / (m - k)
    w0 = k / m
    between = w0 * (1 - w0) * (mu0 - mu1) ** 2
    i = np.argmax(between, axis=1)
    rows = np.arange(len(v))
    return 0.5 * (v[rows, i] + v[rows, i + 1])


def refine_quads(
    gray: np.ndarray, quads: np.ndarray, *, samples: int = 12, cells: int = 6
) -> np.ndarray:
    """Refine (N, 4, 2) quads by fitting lines to the gradient centroids across each side.

    The search across a side reaches at most half a marker cell (``cells`` per side, border
    included) each way, so that it never reaches the edges of the inner bits. All sides of all
    quads are processed at once. A quad is left as it is if a side is too short or too weak,
    or if a refined corner moved more than 2 px.
    """
    if len(quads) == 0:
        return quads
    img = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 0.5)
    a = quads.reshape(-1, 2)  # (N*4, 2): side k runs from corner k to corner k+1
    b = np.roll(quads, -1, axis=1).reshape(-1, 2)
    side = b - a
    length = np.linalg.norm(side, axis=1)
    tangent = side / np.maximum(length, 1e-9)[:, None]
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    reach = np.clip(0.5 * length / cells, 1.0, 2.5)
    steps = 21
    offs = np.linspace(-1.0, 1.0, steps)[None, :] * reach[:, None]  # (S, steps)
    s = np.linspace(0.15, 0.85, samples)  # stay away from the corners
    base = a[:, None, :] + s[None, :, None] * side[:, None, :]  # (S, samples, 2)
    pts = base[:, :, None, :] + offs[:, None, :, None] * normal[:, None, None, :]
    prof = _bilinear(img, pts.reshape(-1, 2)).reshape(len(a), samples, steps)
    grad = np.abs(np.diff(prof, axis=2))  # between consecutive offsets
    mid = 0.5 * (offs[:, 1:] + offs[:, :-1])  # (S, steps-1)
    # The centroid of the gradient across the window, not a parabola through its peak: the
    # profile is bilinear between pixels, so its gradient is flat across each pixel and a
    # parabola snaps to the pixel grid (0.3 px saw-teeth along a side).
    g1 = grad.sum(axis=2)
    pos = (grad * mid[:, None, :]).sum(axis=2) / np.maximum(g1, 1e-12)
    edge = base + pos[..., None] * normal[:, None, :]  # (S, samples, 2)
    strong = g1 > 0.25 * np.median(g1, axis=1, keepdims=True)
    point, direction = _fit_lines(edge, strong.astype(np.float64))
    usable = (length >= 8) & (strong.sum(axis=1) >= 4)
    # Corner k is where side k-1 (ending at it) meets side k (starting at it).
    p = point.reshape(-1, 4, 2)
    d = direction.reshape(-1, 4, 2)
    corners = _intersect(np.roll(p, 1, axis=1), np.roll(d, 1, axis=1), p, d)
    good = usable.reshape(-1, 4).all(axis=1)
    good &= np.isfinite(corners).all(axis=(1, 2))
    good &= np.nan_to_num(np.abs(corners - quads), nan=np.inf).max(axis=(1, 2)) < 2.0
    return np.where(good[:, None, None], corners, quads)


def _bilinear(img: np.ndarray, pts: np.ndarray) -> np.ndarray:
    h, w = img.shape
    x = np.clip(pts[:, 0], 0, w - 1.001)
    y = np.clip(pts[:, 1], 0, h - 1.001)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    return (
        img[y0, x0] * (1 - fx) * (1 - fy)
        + img[y0, x0 + 1] * fx * (1 - fy)
        + img[y0 + 1, x0] * (1 - fx) * fy
        + img[y0 + 1, x0 + 1] * fx * fy
    )


def _fit_lines(pts: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total least squares lines through weighted points (L, P, 2): (L, 2) points on them and
    (L, 2) unit directions (the principal axis of each 2x2 scatter matrix)."""
    wsum = np.maximum(weights.sum(axis=1, keepdims=True), 1e-12)
    c = (weights[..., None] * pts).sum(axis=1) / wsum
    q = pts - c[:, None, :]
    sxx = (weights * q[..., 0] ** 2).sum(axis=1)
    syy = (weights * q[..., 1] ** 2).sum(axis=1)
    sxy = (weights * q[..., 0] * q[..., 1]).sum(axis=1)
    angle = 0.5 * np.arctan2(2 * sxy, sxx - syy)
    return c, np.column_stack([np.cos(angle), np.sin(angle)])


def _intersect(p: np.ndarray, d: np.ndarray, q: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Intersections of lines ``p + s d`` and ``q + r e`` (arrays (..., 2)); NaN if parallel."""
    det = d[..., 0] * -e[..., 1] + e[..., 0] * d[..., 1]
    w = q - p
    s = (w[..., 0] * -e[..., 1] + e[..., 0] * w[..., 1]) / np.where(np.abs(det) > 1e-9, det, np.nan)
    return p + s[..., None] * d
