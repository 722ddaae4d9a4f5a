"""Motion blur of one frame, seen on its markers' own edges.

A hand-held camera smears each point along the path the image moved during the exposure: a
*streak*, a line of some length and direction, not the round blur of a lens. Which instant of
the exposure the frame's pose stands for is not known, so a streak of ``L`` px leaves the
frame's pose uncertain by a shift of up to ``L / 2`` px, however many markers it reads; its
corners are also noisier. A round-blur measure (``edge_blur_px``) hardly sees a streak: the
edges along it stay sharp.

Each marker read is a known picture (its dictionary's bits in a black border, on white):
:func:`marker_streak` draws it where its corners say, smears it along every streak of a grid
(length and direction) over a lens blur, and keeps the streak whose picture explains the
pixels best (gain and offset fitted, least squares). :func:`frame_streak` is the median over
the largest markers of a frame. Pure functions of the image and the corners.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np

__all__ = ["Streak", "frame_streak", "marker_streak", "marker_picture"]

#: Pixels per cell of the drawn picture before it is warped into the image.
PICTURE_PX_PER_CELL = 8
#: White around the marker's black border that the fit uses, in cells (a sticker's margin).
MARGIN_CELLS = 0.5
#: The lens blur under every streak (Gaussian sigma, px).
LENS_SIGMA_PX = 0.7
#: Streak lengths (px) and directions (degrees, modulo 180) of the coarse grid; the best is
#: refined on a finer one round it.
COARSE_LENGTHS = (0.0, 2.0, 4.0, 7.0, 11.0, 16.0)
COARSE_ANGLES = tuple(float(a) for a in range(0, 180, 30))
#: A marker smaller than this (px, mean side) says little about a streak.
MIN_SIDE_PX = 14.0
#: Nor is a marker larger than this (px, mean side) measured: its picture's cost grows with
#: its area and it tells no more than a smaller one; a "marker" filling the image is rather
#: a large square of the scene read as a code (such a quad took seconds).
MAX_SIDE_PX = 120.0
#: Markers of a frame measured (spread over the image).
MAX_MARKERS = 6


@dataclass(frozen=True)
class Streak:
    """A motion streak: ``length_px`` long, at ``angle_deg`` (image x towards y, modulo
    180); ``markers``: how many markers told; ``per_marker``: each one's own length (px)
    by marker id."""

    length_px: float
    angle_deg: float
    markers: int
    per_marker: dict[int, float] = field(default_factory=dict)


@lru_cache(maxsize=256)
def marker_picture(grid: bytes, cells: int) -> np.ndarray:
    """The marker of ``cells`` x ``cells`` cells (``grid``: row-major, border included, 0
    black) drawn at :data:`PICTURE_PX_PER_CELL` with :data:`MARGIN_CELLS` of white round it
    (float32, 0 black, 1 white)."""
    p = PICTURE_PX_PER_CELL
    marker = (np.frombuffer(grid, dtype=np.uint8).reshape(cells, cells) > 0).astype(np.float32)
    big = np.kron(marker, np.ones((p, p), np.float32))
    m = int(round(MARGIN_CELLS * p))
    return np.pad(big, m, constant_values=1.0)


@lru_cache(maxsize=4096)
def _line_kernel(length: float, angle_deg: float) -> tuple[np.ndarray, tuple[int, int]]:
    """A streak's kernel: a segment ``length`` px long at ``angle_deg``, sum 1 (a point
    for 0), drawn with sub-pixel samples, and its anchor (x, y: the segment's middle). Only
    the rows and columns the segment crosses are kept: OpenCV filters by Fourier transform a
    kernel of more than 130 taps, which costs several times a direct filter of the few
    taps a line has. Cached (read-only): every marker tries the same grid of streaks, and
    drawing a kernel costs more than applying it."""
    half = int(np.ceil(length / 2)) + 1
    k = np.zeros((2 * half + 1, 2 * half + 1), np.float32)
    if length < 0.5:
        k[half, half] = 1.0
        return _trimmed(k, half)
    a = np.radians(angle_deg)
    s = np.linspace(-length / 2, length / 2, int(np.ceil(length * 4)) + 1)
    xs, ys = half + s * np.cos(a), half + s * np.sin(a)
    x0, y0 = np.floor(xs).astype(int), np.floor(ys).astype(int)
    fx, fy = xs - x0, ys - y0
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy)):
        np.add.at(k, (y0 + dy, x0 + dx), w)
    np.add.at(k, (y0 + 1, x0 + 1), fx * fy)
    k /= k.sum()
    return _trimmed(k, half)


def _trimmed(k: np.ndarray, half: int) -> tuple[np.ndarray, tuple[int, int]]:
    """Kernel ``k`` (anchor at ``(half, half)``) without its rows and columns of zeros, and
    where the anchor is then (read-only)."""
    rows, cols = np.flatnonzero(k.any(axis=1)), np.flatnonzero(k.any(axis=0))
    out = np.ascontiguousarray(k[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1])
    out.flags.writeable = False
    return out, (half - int(cols[0]), half - int(rows[0]))


def marker_streak(
    gray: np.ndarray, corners: np.ndarray, grid: np.ndarray
) -> tuple[float, float] | None:
    """The streak (length px, angle degrees) that best explains one marker's pixels, its
    ``corners`` (4, 2, OpenCV order) and ``grid`` its cells as printed ((n+2, n+2), border
    included, 0 black); None for a marker too small, too large (:data:`MAX_SIDE_PX`) or too
    near the border of the image to tell."""
    corners = np.asarray(corners, np.float64)
    side = float(np.mean(np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1)))
    if not MIN_SIDE_PX <= side <= MAX_SIDE_PX:
        return None
    cells = grid.shape[0]
    picture = marker_picture(np.asarray(grid, np.uint8).tobytes(), cells)
    p, m = PICTURE_PX_PER_CELL, int(round(MARGIN_CELLS * PICTURE_PX_PER_CELL))
    span = cells * p
    src = np.array([[m, m], [m + span, m], [m + span, m + span], [m, m + span]], np.float32)
    src -= 0.5  # pixel centres: the picture's pixel k covers [k, k + 1)
    H = cv2.getPerspectiveTransform(src, corners.astype(np.float32))
    size = picture.shape[0]
    outline = np.array([[0, 0], [size, 0], [size, size], [0, size]], np.float32) - 0.5
    hull = cv2.perspectiveTransform(outline[None], H)[0]
    pad = int(np.ceil(max(COARSE_LENGTHS) / 2)) + 3
    x0, y0 = np.floor(hull.min(axis=0)).astype(int) - pad
    x1, y1 = np.ceil(hull.max(axis=0)).astype(int) + pad
    h, w = gray.shape[:2]
    if x0 < 0 or y0 < 0 or x1 >= w or y1 >= h:
        return None
    shift = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1]], np.float64)
    box = (int(x1 - x0), int(y1 - y0))
    drawn = cv2.warpPerspective(picture, shift @ H, box, flags=cv2.INTER_AREA, borderValue=1.0)
    inside = cv2.warpPerspective(np.ones_like(picture), shift @ H, box, flags=cv2.INTER_NEAREST)
    # The fit looks where the picture is known (the marker and its margin), not beyond:
    # what lies round a sticker is unknown, and a long streak brings it in.
    # (As flat indices: taking them is quicker than a boolean mask, in the same order.)
    known = np.flatnonzero(inside > 0.5)
    observed = np.take(gray[y0:y1, x0:x1], known).astype(np.float64)
    centred = observed - observed.mean()  # gain and offset fitted in closed form
    lens = cv2.GaussianBlur(drawn, (0, 0), LENS_SIGMA_PX)

    def misfits(trials: list[tuple[float, float]]) -> list[float]:
        # Each streak's picture by OpenCV; the fits of all of them as one array.
        models = np.stack(
            [
                np.take(
                    cv2.filter2D(lens, -1, k, anchor=at, borderType=cv2.BORDER_REPLICATE),
                    known,
                )
                for k, at in (_line_kernel(L, a) for L, a in trials)
            ]
        ).astype(np.float64)
        dx = models - models.mean(axis=1, keepdims=True)
        gain = (dx @ centred) / np.maximum(np.einsum("tk,tk->t", dx, dx), 1e-12)
        cost = ((centred - gain[:, None] * dx) ** 2).sum(axis=1)
        # A picture that fits only inverted explains nothing.
        return np.where(gain > 0, cost, np.inf).tolist()

    # No streak has no direction: its misfit is worked out once for every angle.
    coarse = [(L, a) for L in COARSE_LENGTHS for a in COARSE_ANGLES if L > 0]
    costs = dict(zip(coarse, misfits(coarse)))
    still = misfits([(0.0, 0.0)])[0]
    best = min(
        (costs[L, a] if L > 0 else still, L, a) for L in COARSE_LENGTHS for a in COARSE_ANGLES
    )
    _, L0, a0 = best
    if L0 > 0:  # finer between the coarse grid's neighbours
        k = COARSE_LENGTHS.index(L0)
        lo = COARSE_LENGTHS[k - 1]
        hi = COARSE_LENGTHS[k + 1] if k + 1 < len(COARSE_LENGTHS) else 1.25 * L0
        fine = [
            (float(L), a)
            for L in np.linspace(lo + (L0 - lo) / 3, hi - (hi - L0) / 3, 5)
            for a in (a0 - 15, a0 - 7.5, a0, a0 + 7.5, a0 + 15)
        ]
        best = min(best, *((m, L, a) for m, (L, a) in zip(misfits(fine), fine)))
    _, L, a = best
    return float(L), float(a % 180.0)


def frame_streak(
    gray: np.ndarray, markers: list[tuple[int, np.ndarray, np.ndarray]]
) -> Streak | None:
    """The frame's streak from up to :data:`MAX_MARKERS` of its markers (``(id, corners,
    grid)`` each), spread over the image (a turning camera smears one side of the image and
    not the other): the largest first, then each the farthest from those already taken. Its
    length is the second longest of theirs (the longest with fewer than three: one marker
    misfitted does not flag a frame), its direction that of the longest streaks (a short
    streak's direction means little); None when no marker tells."""
    sides = [
        float(np.mean(np.linalg.norm(c - np.roll(c, 1, axis=0), axis=1))) for _, c, _ in markers
    ]
    order = [k for k in np.argsort(sides)[::-1] if MIN_SIDE_PX <= sides[k] <= MAX_SIDE_PX]
    centres = np.array([c.mean(axis=0) for _, c, _ in markers]).reshape(-1, 2)
    chosen: list[int] = []
    while order and len(chosen) < MAX_MARKERS:
        if chosen:
            far = np.linalg.norm(centres[order][:, None] - centres[chosen][None], axis=2)
            k = order[int(np.argmax(far.min(axis=1)))]
        else:
            k = order[0]
        order.remove(k)
        chosen.append(k)
    per_marker: dict[int, float] = {}
    found = []
    for k in chosen:
        mid, c, g = markers[k]
        if (st := marker_streak(gray, c, g)) is not None:
            found.append(st)
            per_marker[int(mid)] = round(st[0], 2)
    if not found:
        return None
    lengths = np.array([st[0] for st in found])
    angles = np.radians([st[1] for st in found])
    # Directions modulo 180 degrees: averaged as doubled angles.
    c, s = np.cos(2 * angles) * lengths, np.sin(2 * angles) * lengths
    angle = float(np.degrees(np.arctan2(s.sum(), c.sum())) / 2) % 180.0
    ranked = np.sort(lengths)[::-1]
    length = float(ranked[1] if len(ranked) >= 3 else ranked[0])
    return Streak(round(length, 2), round(angle, 1), len(found), per_marker)
