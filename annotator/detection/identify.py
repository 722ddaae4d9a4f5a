"""Identifying candidate squares: each candidate's bits are read and looked up in a sorted
table of all codes of the dictionary in all rotations.

OpenCV compares every candidate square with every marker of the dictionary (and its four
rotations), which with the 1000-marker dictionaries that parts need is most of the
detection's time (``benchmarks/bench_detection.py``); a table lookup is not. The bits are read
the way OpenCV reads them: the square is resampled to :data:`PIXELS_PER_CELL` pixels per cell,
split by Otsu's threshold, the border cells must be black (up to OpenCV's tolerance), and a
cell is white if most of its samples are. Dictionaries with error correction fall back to the
nearest code within OpenCV's number of correctable bits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from annotator.detection.homography import apply_homographies_on_grid, unit_square_homographies

#: Samples per cell side when reading a candidate's bits (OpenCV's perspectiveRemovePixelPerCell).
PIXELS_PER_CELL = 4

#: A candidate with a side shorter than this many pixels per cell (border included) is not
#: read: its cells are below the pixel size, and seen edge-on a square's bits can read as any
#: code (such slivers were false identifications on rendered scenes, as they are for OpenCV).
MIN_PX_PER_CELL = 1.0


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
    flat = bits.reshape(*bits.shape[:-2], bits.shape[-2] * bits.shape[-1]).astype(np.uint64)
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
    Several candidates of one printed marker are kept once (see :func:`one_per_marker`).
    """
    if len(quads) == 0:
        return np.zeros(0, int), np.zeros((0, 4, 2)), np.zeros(0, bool)
    n = codebook.marker_size
    cells = n + 2
    side = cells * PIXELS_PER_CELL
    g = np.arange(side) / (side - 1)
    x, y = apply_homographies_on_grid(unit_square_homographies(quads), g)
    h, w = gray.shape
    rows, cols = np.rint(y).astype(int), np.rint(x).astype(int)
    raw = gray[np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1)]  # (N, side * side)
    values = raw.astype(np.float32)
    white = values > _otsu_thresholds(raw)[:, None]
    low = values.std(axis=1) < min_std  # no contrast: OpenCV calls every cell by the mean
    white[low] = (values[low].mean(axis=1) > 127)[:, None]
    bits = _cell_majority(white, cells)
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
    ids_kept, quads_kept = one_per_marker(
        ids[ok], turned[ok].reshape(-1, 4, 2), sides[ok].sum(axis=1)
    )
    return ids_kept, quads_kept, ok


def _cell_majority(white: np.ndarray, cells: int) -> np.ndarray:
    """(N, cells, cells) bits from (N, side * side) samples read row by row: True where more
    than half of a cell's samples are white."""
    p = PIXELS_PER_CELL
    w = white.view(np.uint8).reshape(-1, cells, p, cells, p)
    # The samples counted by adding slices: a reduction over such short axes costs far more.
    rows = w[:, :, 0].copy()  # (N, cells, cells, p): each cell's columns, summed down it
    for i in range(1, p):
        rows += w[:, :, i]
    count = rows[..., 0].copy()
    for j in range(1, p):
        count += rows[..., j]
    return count > p * p / 2


def one_per_marker(
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
        if all(_length(centre[j] - centre[k]) >= perimeter[j] / 8 for j in same):
            same.append(int(k))
            keep.append(int(k))
    keep.sort()
    return ids[keep], quads[keep]


def _length(v: np.ndarray) -> float:
    """np.linalg.norm of a vector, its own arithmetic (the root of the vector's dot product
    with itself) without its overhead per call."""
    return math.sqrt(v.dot(v))


def _otsu_thresholds(values: np.ndarray) -> np.ndarray:
    """Otsu's threshold of each row of 8-bit values: the split maximising the between-class
    variance (float32). The rows are sorted as stored: numpy sorts 8-bit values stably by
    radix, several times quicker than their float copies, in the same order. Their running
    sums are integers, exact (as float32 sums of them are, below 2**24) and quicker."""
    v = np.sort(values, axis=1, kind="stable")
    m = v.shape[1]
    c = np.cumsum(v, axis=1, dtype=np.int32)
    k = np.arange(1, m)
    mu0 = c[:, :-1] / k
    mu1 = (c[:, -1:] - c[:, :-1]) / (m - k)
    w0 = k / m
    between = w0 * (1 - w0) * (mu0 - mu1) ** 2
    i = np.argmax(between, axis=1)
    rows = np.arange(len(v))
    return 0.5 * (v[rows, i].astype(np.float32) + v[rows, i + 1])
