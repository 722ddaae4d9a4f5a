"""Reading the bits of blurred markers by inverting a blur model.

On a blurred image (a Gaussian of 2 px over the 3-4 px cells of a 20 px marker), thresholding
the samples of each cell, as OpenCV does, reads the wrong bits: every cell is mixed with its
neighbours. Here each candidate square is sampled on a grid (``SAMPLES_PER_CELL`` per cell,
over the marker and half a cell around it) and explained as a grid of uniform cells blurred
by a Gaussian of known width: the marker's cells plus ``RING`` unknown cells around it (what
lies next to the marker). The model is separable (rows and columns), so the cell values are
two small least-squares solves, ``V = P Y P^T``, with ``P`` the regularised pseudo-inverse of
the 1-D blur matrix. The cells are then split into dark and light by two-means, and each bit
gets a *margin*, its distance to the split in units of the contrast.

The blur width is estimated per image (:func:`estimate_blur`): the width whose model
explains the largest candidate squares best. It is given in pixels and turned into cells per
candidate (the perspective is taken as locally uniform: a candidate's mean side).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from annotator.detection.homography import apply_homographies_on_grid, unit_square_homographies

RING = 2
SAMPLES_PER_CELL = 4
RIDGE = 1e-2
BLUR_GRID = np.arange(0.25, 4.01, 0.25)  # px, the candidate blur widths


@lru_cache(maxsize=512)
def _model(cells: int, sigma_cells: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """1-D sample positions (cells), blur matrix A (samples x cells) and its regularised
    pseudo-inverse P (cells x samples), for ``cells`` marker cells and ``RING`` more on each
    side."""
    from scipy.special import ndtr

    xs = np.linspace(-0.5, cells + 0.5, (cells + 1) * SAMPLES_PER_CELL + 1)
    edges = np.arange(-RING, cells + RING + 1, dtype=float)
    cdf = ndtr((xs[:, None] - edges[None, :]) / max(sigma_cells, 1e-3))
    A = cdf[:, :-1] - cdf[:, 1:]
    P = np.linalg.solve(A.T @ A + RIDGE * np.eye(A.shape[1]), A.T)
    return xs, A, P


def _quantised(sigma_cells: np.ndarray) -> np.ndarray:
    """Blur widths (cells) on a grid of 0.02: the models' cache keys."""
    return np.round(np.maximum(sigma_cells, 0.02) / 0.02) * 0.02


@lru_cache(maxsize=512)
def _projector(cells: int, sigma_cells: float) -> tuple[np.ndarray, np.ndarray]:
    """The model's fit ``A P`` as ``U diag(d) U^T``: ``U`` (samples x unknown cells) the
    orthonormal columns of A's thin SVD, ``d`` the ridge's shrinkage of each."""
    _, A, _ = _model(cells, sigma_cells)
    U, s, _ = np.linalg.svd(A, full_matrices=False)
    return U, s**2 / (s**2 + RIDGE)


def _samples(gray: np.ndarray, quads: np.ndarray, xs: np.ndarray, cells: int) -> np.ndarray:
    """Bilinear samples of each quad on the grid ``xs`` x ``xs`` (cell units): (N, S, S),
    from an 8-bit image or the same as float32 (not converted again)."""
    x, y = apply_homographies_on_grid(unit_square_homographies(quads), xs / cells)
    vals = cv2.remap(
        np.asarray(gray, np.float32),
        x.astype(np.float32),
        y.astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return vals.reshape(len(quads), len(xs), len(xs))


def _cell_px(quads: np.ndarray, cells: int) -> np.ndarray:
    return np.linalg.norm(quads - np.roll(quads, 1, axis=1), axis=2).mean(axis=1) / cells


def estimate_blur(
    gray: np.ndarray, quads: np.ndarray, cells: int, *, count: int = 30
) -> float | None:
    """The Gaussian blur (px) that best explains the ``count`` largest candidate squares
    of an 8-bit image ``gray`` (or the same as float32) (None without candidates of at least
    2 px per cell)."""
    size = _cell_px(quads, cells)
    order = np.argsort(-size)[:count]
    order = order[size[order] >= 2.0]
    if len(order) == 0:
        return None
    q, size = quads[order], size[order]
    xs = _model(cells, 1.0)[0]
    Y = _samples(gray, q, xs, cells).astype(np.float64)  # (K, S, S)
    # Every blur width's fit of every square at once. With the fit A P = U diag(d) U^T and
    # Z = U^T Y U, the squared residual |A P Y P^T A^T - Y|^2 is |Y|^2 + sum over the cells
    # (i, j) of ((d_i d_j)^2 - 2 d_i d_j) Z_ij^2: two products with the thin U (samples x
    # cells) instead of four with the full-size model per pair.
    sigma_cells = _quantised(BLUR_GRID[:, None] / size[None, :])  # (G, K)
    keys, which = np.unique(sigma_cells, return_inverse=True)
    fits = [_projector(cells, float(k)) for k in keys]
    U = np.stack([f[0] for f in fits])[which.reshape(sigma_cells.shape)]  # (G, K, S, C)
    d = np.stack([f[1] for f in fits])[which.reshape(sigma_cells.shape)]  # (G, K, C)
    Z = U.transpose(0, 1, 3, 2) @ Y[None] @ U
    dd = d[..., :, None] * d[..., None, :]
    err = (Y**2).sum(axis=(1, 2)) + ((dd**2 - 2 * dd) * Z**2).sum(axis=(2, 3))
    cost = err.sum(axis=1)  # every square has as many samples: sums rank as means do
    return float(BLUR_GRID[int(np.argmin(cost))])


@dataclass(frozen=True)
class SoftBits:
    """Bits read through the blur model.

    Attributes:
        bits: (N, n, n) inner bits, True = white, in the quads' own corner order.
        margin: (N, n, n) distance of each cell to the dark/light split, in contrasts.
        border_errors: (N,) border cells read light (they must be dark).
    """

    bits: np.ndarray
    margin: np.ndarray
    border_errors: np.ndarray


def read_soft_bits(
    gray: np.ndarray, quads: np.ndarray, marker_size: int, sigma_px: float
) -> SoftBits:
    """Read (N, 4, 2) quads of markers with ``marker_size`` inner bits per side in an 8-bit
    image ``gray`` (or the same as float32)."""
    cells = marker_size + 2
    n = len(quads)
    bits = np.zeros((n, marker_size, marker_size), bool)
    margin = np.zeros((n, marker_size, marker_size))
    border_errors = np.zeros(n, int)
    if n == 0:
        return SoftBits(bits, margin, border_errors)
    widths = _quantised(sigma_px / _cell_px(quads, cells))
    xs = _model(cells, 1.0)[0]
    Y = _samples(gray, quads, xs, cells)
    ring = np.ones((cells, cells), bool)
    ring[1:-1, 1:-1] = False
    for k in range(n):
        _, _, P = _model(cells, float(widths[k]))
        V = (P @ Y[k] @ P.T)[RING : RING + cells, RING : RING + cells]
        values = V.ravel()
        lo, hi = values.min(), values.max()
        thr = 0.5 * (lo + hi)
        for _ in range(8):  # two-means split of the marker's cells
            dark, light = values[values <= thr], values[values > thr]
            if len(dark) == 0 or len(light) == 0:
                break
            # Sums over counts: np.mean's own arithmetic without its overhead per call.
            new = 0.5 * (dark.sum() / len(dark) + light.sum() / len(light))
            if abs(new - thr) < 1e-6:
                break
            thr = new
        contrast = max(float(hi - lo), 1e-6)
        inner = V[1:-1, 1:-1]
        bits[k] = inner > thr
        margin[k] = np.abs(inner - thr) / contrast
        border_errors[k] = np.count_nonzero(V[ring] > thr)
    return SoftBits(bits, margin, border_errors)
