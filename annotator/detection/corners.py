"""Sub-pixel marker corners without bias.

OpenCV's sub-pixel refinement leaves the corners of small markers (20-40 px) inside the true
square (``benchmarks/bench_detection.py`` measures by how much, on rendered images whose
corners are known exactly). So each identified quad is refined here: cv2.cornerSubPix with a
small window first, then along each side, at many points, the centroid of the intensity
gradient across the side (within half a cell each way), a line fitted to these points (those
far from it left out), and the corners where adjacent lines meet, over a few rounds. For a
step edge under any symmetric blur, the centroid of the gradient is the edge itself, hence no
bias; a highlight beside the paper or a neighbour's edge is a point off the line, left out.

A marker wrapped round a curved part (a shaft, a cylinder) has sides that bow in the image
when seen at a slant: a line through a bowed side's points passes beside its ends, and every
corner moves outwards or inwards alike (the part then seems nearer or farther). Where a side
and its opposite side both bow the same way in the image, each significantly (a parabola's
curvature term :data:`BOW_SIGMAS` standard errors from zero), the corners are where the
parabolas' tangents at their ends meet; a side alone that seems to bow is noise and keeps its
line.

Corner order is OpenCV's: top-left, top-right, bottom-right, bottom-left of the printed marker.
"""

from __future__ import annotations

import cv2
import numpy as np

from annotator.geometry.robust import MAD_TO_SIGMA

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


#: The edge fit reads the image under this slight blur (px): the profiles across a side
#: smoothed of single pixels' noise.
BLUR_SIGMA_PX = 0.5
#: Rows each way that blur reaches (OpenCV's kernel for a float image: 4 sigmas, 5 taps).
_BLUR_ROWS = 2


class EdgeImage:
    """An 8-bit image as the edge fit reads it (as float, under :data:`BLUR_SIGMA_PX`),
    made a band of rows at a time where the fit samples it, and kept: the markers' rows are
    a share of the image, and the fit reads them in each of its rounds. Each
    band is blurred with the blur's reach of rows round it (the image's own border where it
    reaches that) and the image's whole width, so its pixels are those a blur of the whole
    image gives, bit for bit."""

    def __init__(self, gray: np.ndarray) -> None:
        self.gray = gray
        self.image = np.empty(gray.shape, np.float32)  # read only where blurred
        self.done = np.zeros(gray.shape[0], bool)  # rows blurred

    def sample(self, px: np.ndarray, py: np.ndarray) -> np.ndarray:
        """Bilinear samples at points ``(px, py)`` (arrays of one shape), clipped to the image."""
        h, w = self.gray.shape
        x = np.clip(px, 0, w - 1.001)
        y = np.clip(py, 0, h - 1.001)
        x0, y0 = np.floor(x), np.floor(y)
        top = y0.astype(np.intp)
        # The rows the samples read: each point's and the one below.
        need = np.zeros(h + 1, bool)
        need[top] = True
        need[1:] |= need[:-1]
        missing = need[:h] & ~self.done
        if missing.any():
            # Runs of missing rows (gaps of a few rows joined: one blur costs more than
            # the few rows it spares), each blurred as one band.
            rows = np.flatnonzero(missing)
            breaks = np.flatnonzero(np.diff(rows) > 2 * _BLUR_ROWS + 1)
            for a, b in zip(np.r_[0, breaks + 1], np.r_[breaks, len(rows) - 1]):
                self._blur(int(rows[a]), int(rows[b]) + 1)
        # The four neighbours by flat index (indexing by row and column costs twice as much).
        at = top * w + x0.astype(np.intp)
        flat = self.image.reshape(-1)
        fx, fy = x - x0, y - y0
        gx, gy = 1 - fx, 1 - fy
        # The neighbours right and below through views shifted by their offsets: the same
        # pixels without an index array for each.
        return (
            flat.take(at) * gx * gy
            + flat[1:].take(at) * fx * gy
            + flat[w:].take(at) * gx * fy
            + flat[w + 1 :].take(at) * fx * fy
        )

    def _blur(self, y0: int, y1: int) -> None:
        h = self.gray.shape[0]
        b0, b1 = max(y0 - _BLUR_ROWS, 0), min(y1 + _BLUR_ROWS, h)
        # The band blurred in place, not copied in: its rows of reach beyond [y0, y1) come out
        # wrong (the band's border), so those the image had are put back.
        above, below = self.image[b0:y0].copy(), self.image[y1:b1].copy()
        src = self.gray[b0:b1].astype(np.float32)
        band = self.image[b0:b1]
        out = cv2.GaussianBlur(src, (0, 0), BLUR_SIGMA_PX, dst=band)
        if not np.shares_memory(out, band):  # a binding that made its own array after all
            band[...] = out
        self.image[b0:y0], self.image[y1:b1] = above, below
        self.done[y0:y1] = True


def refine_quads(
    gray: np.ndarray,
    quads: np.ndarray,
    *,
    samples: int = 12,
    cells: int = 6,
) -> np.ndarray:
    """Refine (N, 4, 2) quads by fitting lines to the gradient centroids across each side.

    The search across a side reaches at most half a marker cell each way (``cells`` per side,
    border included, of the marker's extent across that side; at least 0.7 px), so that it
    never reaches the edges of the inner bits, and counts only the gradient of the side's own
    direction (dark ink inside, paper outside). A line is fitted to each side's edge points
    with the points far from it left out (a highlight beside the paper, a neighbour's edge),
    and the corners are where adjacent lines meet; this is done :data:`ROUNDS` times, each
    round searching across the sides the last one found. All sides of all quads are processed
    at once. A quad is left as it is if a side is too short, too weak or not straight, or if
    a corner moved further than :func:`_max_move` allows.
    """
    if len(quads) == 0:
        return quads
    img = EdgeImage(gray)
    current = quads.copy()
    found = np.zeros(len(quads), bool)
    for _ in range(ROUNDS):
        corners, good = _edge_fit(img, current, samples=samples, cells=cells)
        current = np.where(good[:, None, None], corners, current)
        found |= good
    moved = np.nan_to_num(np.abs(current - quads), nan=np.inf).max(axis=(1, 2))
    found &= moved < _max_move(quads)
    return np.where(found[:, None, None], current, quads)


#: Edge-fit rounds: a corner the contour put a few pixels off (a highlight beside the paper
#: joins the margin to the ink) comes back over the rounds as its sides' lines settle. One
#: round leaves the corners a few hundredths of a pixel inside the square on average, three
#: as far outside; two are balanced (the scale of a scene seen without depth follows that).
ROUNDS = 2


#: Edge points nearer their side's line than this (px) are never left out of its fit: the
#: sides of a marker wrapped round a cylinder bow by a few tenths of a pixel.
TRIM_PX = 0.6


def _max_move(quads: np.ndarray) -> np.ndarray:
    """How far (px) the edge fit may move a quad's corners: 2 px, or a quarter of its
    shortest side."""
    sides = np.linalg.norm(_turn(quads, -1) - quads, axis=2).min(axis=1)
    return np.maximum(2.0, 0.25 * sides)


def _edge_fit(
    img: EdgeImage, quads: np.ndarray, *, samples: int, cells: int
) -> tuple[np.ndarray, np.ndarray]:
    """One round of the edge fit: the (N, 4, 2) corners where the sides' lines meet, and
    which quads all four of whose sides were fitted."""
    a = quads.reshape(-1, 2)  # (N*4, 2): side k runs from corner k to corner k+1
    b = _turn(quads, -1).reshape(-1, 2)
    side = b - a
    length = np.linalg.norm(side, axis=1)
    tangent = side / np.maximum(length, 1e-9)[:, None]
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    # Half a cell across the side, from the marker's extent along the side's normal (to the
    # opposite side's midpoint): a slanted view shortens the cells across some sides and not
    # along them, and a search as long as the side's own cells reached the inner bits, whose
    # blurred edges pulled the corners outwards (markers seen at a slant looked too near).
    mid = 0.5 * (a + b)
    opposite = _turn(mid.reshape(-1, 4, 2), -2).reshape(-1, 2)
    across = np.abs(np.einsum("sd,sd->s", opposite - mid, normal))
    reach = np.clip(0.5 * across / cells, 0.7, 2.5)
    steps = 21
    offs = np.linspace(-1.0, 1.0, steps)[None, :] * reach[:, None]  # (S, steps)
    s = np.linspace(0.1, 0.9, samples)  # stay away from the corners
    base = a[:, None, :] + s[None, :, None] * side[:, None, :]  # (S, samples, 2)
    # The points across the sides (S, samples, steps), x and y apart: the sampler reads each
    # as one contiguous array.
    px = base[:, :, None, 0] + offs[:, None, :] * normal[:, None, None, 0]
    py = base[:, :, None, 1] + offs[:, None, :] * normal[:, None, None, 1]
    prof = img.sample(px, py)
    # The side's own direction of change across it, from most of its samples; a gradient
    # the other way (the inner bits' edges, the paper's own border) counts for nothing.
    # (The three samples at each end summed in order, as np.mean sums them.)
    inside = (prof[..., 0] + prof[..., 1] + prof[..., 2]) / 3
    outside = (prof[..., -3] + prof[..., -2] + prof[..., -1]) / 3
    sign = np.sign(_row_medians(outside - inside))
    grad = prof[..., 1:] - prof[..., :-1]
    grad *= sign[:, None, None]
    np.maximum(grad, 0.0, out=grad)
    mid = 0.5 * (offs[:, 1:] + offs[:, :-1])  # (S, steps-1)
    # The centroid of the gradient across the window, not a parabola through its peak: the
    # profile is bilinear between pixels, so its gradient is flat across each pixel and a
    # parabola snaps to the pixel grid (0.3 px saw-teeth along a side).
    g1 = grad.sum(axis=2)
    pos = (grad * mid[:, None, :]).sum(axis=2) / np.maximum(g1, 1e-12)
    edge = base + pos[..., None] * normal[:, None, :]  # (S, samples, 2)
    strong = g1 > 0.25 * _row_medians(g1)[:, None]
    strong &= np.abs(pos) < 0.8 * reach[:, None]  # an edge at the window's end is cut off
    point, direction, used, rms = _fit_lines_robust(edge, strong)
    usable = (length >= 8) & (used.sum(axis=1) >= 4) & (rms < 0.5)
    # Each side's tangent at its two ends: its line, or where the side bows (a marker
    # wrapped round a curved part) the tangents of a parabola through its points.
    start, start_dir, end, end_dir = _bowed_ends(
        edge, used & (length >= BOW_MIN_PX)[:, None], point, direction, a, b
    )
    # Corner k is where side k-1 (ending at it) meets side k (starting at it).
    p, d = start.reshape(-1, 4, 2), start_dir.reshape(-1, 4, 2)
    q, e = end.reshape(-1, 4, 2), end_dir.reshape(-1, 4, 2)
    corners = _intersect(_turn(q, 1), _turn(e, 1), p, d)
    good = usable.reshape(-1, 4).all(axis=1) & np.isfinite(corners).all(axis=(1, 2))
    return corners, good


#: Sides shorter than this (px) keep their line: on a small marker a bow is below the noise,
#: and a parabola through a dozen points bends with it.
BOW_MIN_PX = 16.0
#: A side bows when its parabola's curvature term, and its opposite side's, are this many
#: standard errors from zero.
BOW_SIGMAS = 2.0


def _bowed_ends(
    pts: np.ndarray,
    used: np.ndarray,
    point: np.ndarray,
    direction: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per side (L): a point and unit direction of its tangent at its start (near ``a``) and
    at its end (near ``b``); the sides come four by four, a quad's in order. A side whose
    points (L, P, 2, those of ``used``) bow off its line (``point``, ``direction``) by more
    than :data:`BOW_SIGMAS` standard errors, as its opposite side does, gets a parabola's
    tangents; the others keep their line at both ends."""
    normal = np.stack([-direction[:, 1], direction[:, 0]], axis=1)
    rel = pts - point[:, None, :]
    t = np.einsum("lpd,ld->lp", rel, direction)
    off = np.einsum("lpd,ld->lp", rel, normal)
    w = used.astype(np.float64)
    # Weighted least squares of off = c0 + c1 t + c2 t^2, per side, in t scaled to [-1, 1].
    half = np.maximum(np.abs(np.where(used, t, 0.0)).max(axis=1), 1e-9)
    u = t / half[:, None]
    X = np.stack([np.ones_like(u), u, u**2], axis=-1)  # (L, P, 3)
    XtX = np.einsum("lpi,lp,lpj->lij", X, w, X) + 1e-9 * np.eye(3)
    coef = np.linalg.solve(XtX, np.einsum("lpi,lp,lp->li", X, w, off)[..., None])[..., 0]
    resid = off - np.einsum("lpi,li->lp", X, coef)
    dof = np.maximum(w.sum(axis=1) - 3, 1)
    sigma2 = (w * resid**2).sum(axis=1) / dof
    se2 = sigma2 * np.linalg.inv(XtX)[:, 2, 2]
    z = np.abs(coef[:, 2]) / np.sqrt(np.maximum(se2, 1e-18))
    z = np.where(w.sum(axis=1) >= 6, z, 0.0).reshape(-1, 4)
    # Opposite sides of a printed square wrapped round a part bow alike, the same way in the
    # image (seen at a slant, the middle of the square rises off the plane of its corners):
    # both must show it. A side alone that seems to bow is noise.
    bow = (coef[:, 2, None] * normal).reshape(-1, 4, 2)  # the way it bows, in the image
    alike = np.einsum("nkd,nkd->nk", bow, _turn(bow, 2)) > 0
    bowed = ((np.minimum(z, _turn(z, 2)) > BOW_SIGMAS) & alike).ravel()
    c = np.where(bowed[:, None], coef, 0.0)

    def tangent(at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ua = np.einsum("ld,ld->l", at - point, direction) / half
        where = point + (ua * half)[:, None] * direction
        where += (c[:, 0] + c[:, 1] * ua + c[:, 2] * ua**2)[:, None] * normal
        slope = (c[:, 1] + 2 * c[:, 2] * ua) / half
        d = direction + slope[:, None] * normal
        return where, d / np.linalg.norm(d, axis=1, keepdims=True)

    start, start_dir = tangent(a)
    end, end_dir = tangent(b)
    return start, start_dir, end, end_dir


def _fit_lines_robust(
    pts: np.ndarray, keep: np.ndarray, *, rounds: int = 2
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Lines through (L, P, 2) points, those of ``keep`` (L, P) only, refitted ``rounds``
    times without the points further from the line than 3 robust sigmas (at least
    :data:`TRIM_PX`): points on them, unit directions, the points used, and their RMS
    distance (px)."""
    used = keep.copy()
    point, direction = _fit_lines(pts, used.astype(np.float64))
    dist = _distances(pts, point, direction)
    for _ in range(rounds):
        # As np.median of the distances with NaN for the points left out was: NaN (then 0)
        # on any side with a point left out, so the MAD counts only where all are used.
        mad = np.where(used.all(axis=1), _row_medians(dist), 0.0)
        tol = np.maximum(TRIM_PX, 3.0 * MAD_TO_SIGMA * mad)
        used = keep & (dist < tol[:, None])
        point, direction = _fit_lines(pts, used.astype(np.float64))
        dist = _distances(pts, point, direction)
    n = np.maximum(used.sum(axis=1), 1)
    rms = np.sqrt(np.where(used, dist**2, 0.0).sum(axis=1) / n)
    return point, direction, used, rms


_FOUR = np.arange(4)


def _turn(x: np.ndarray, k: int) -> np.ndarray:
    """np.roll(x, k, axis=1) of (N, 4, ...) arrays, a quad's corners or sides (element i from
    element i - k), by take: np.roll's overhead is most of its cost on arrays this small."""
    return x.take((_FOUR - k) % 4, axis=1)


def _row_medians(x: np.ndarray) -> np.ndarray:
    """np.median along the rows of a finite (L, P) array, bit for bit (the mean of the two
    middle values when P is even), without its generic machinery."""
    m = x.shape[1]
    v = np.sort(x, axis=1)
    if m % 2:
        return v[:, m // 2]
    return (v[:, m // 2 - 1] + v[:, m // 2]) / 2


def _distances(pts: np.ndarray, point: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """(L, P) distances of points (L, P, 2) to the lines through ``point`` along
    ``direction`` (L, 2)."""
    normal = np.stack([-direction[:, 1], direction[:, 0]], axis=1)
    return np.abs(np.einsum("lpd,ld->lp", pts - point[:, None, :], normal))


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
