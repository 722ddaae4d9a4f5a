"""Sub-pixel marker corners without bias.

OpenCV's sub-pixel refinement leaves the corners of small markers (20-40 px) inside the true
square (``benchmarks/bench_detection.py`` measures by how much, on rendered images whose
corners are known exactly). So each identified quad is refined here: cv2.cornerSubPix with a
small window first, then along each side, at many points, the centroid of the intensity
gradient across the side (within half a cell each way), a line fitted to these points, and the
corners where adjacent lines meet. For a step edge under any symmetric blur, the centroid of
the gradient is the edge itself, hence no bias.

Corner order is OpenCV's: top-left, top-right, bottom-right, bottom-left of the printed marker.
"""

from __future__ import annotations

import cv2
import numpy as np

#: Half-size of cv2.cornerSubPix's window before the edge fit; larger windows reach across
#: the cells of 20 px markers and pull the corners inwards (2 px gave the smallest corner
#: error on rendered markers).
SUBPIX_HALF_WINDOW = 2
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)


def refine_corners(gray: np.ndarray, quads: np.ndarray, *, cells: int) -> np.ndarray:
    """Sub-pixel corners of (N, 4, 2) quads of markers ``cells`` cells wide (border
    included) in an 8-bit image: a small-window corner fit, then the edge fit
    (:func:`refine_quads`)."""
    if len(quads) == 0:
        return quads
    # The small-window corner fit first, so that the edge fit starts near the sides.
    start: np.ndarray = quads.reshape(-1, 1, 2).astype(np.float32)
    window = (SUBPIX_HALF_WINDOW, SUBPIX_HALF_WINDOW)
    start = cv2.cornerSubPix(gray, start, window, (-1, -1), _SUBPIX_CRITERIA)
    return refine_quads(gray, start.reshape(-1, 4, 2).astype(np.float64), cells=cells)


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
