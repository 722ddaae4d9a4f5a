"""Homographies from the unit square to quadrilaterals, many at once: how a marker's own
coordinates (``(0, 0)`` top-left corner, ``(1, 1)`` bottom-right) map to the image."""

from __future__ import annotations

import numpy as np


def unit_square_homographies(quads: np.ndarray) -> np.ndarray:
    """(N, 3, 3) homographies taking the unit square's corners (0,0), (1,0), (1,1), (0,1)
    to each quad's corners."""
    src = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    # Two rows per corner (its x, then its y), all corners' at once.
    A = np.zeros((len(quads), 4, 2, 8))
    A[:, :, 0, 0:2] = A[:, :, 1, 3:5] = src
    A[:, :, 0, 2] = A[:, :, 1, 5] = 1
    A[:, :, 0, 6:8] = -(quads[:, :, 0, None] * src)
    A[:, :, 1, 6:8] = -(quads[:, :, 1, None] * src)
    b = quads.reshape(-1, 8)
    h = np.linalg.solve(A.reshape(-1, 8, 8), b[..., None])[..., 0]
    return np.concatenate([h, np.ones((len(quads), 1))], axis=1).reshape(-1, 3, 3)


def apply_homographies_on_grid(H: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3, 3) homographies applied to the points (u, v) of the grid ``g`` x ``g`` (G values),
    row by row (v the row, u the column): x and y, each (N, G * G)."""
    u, v = g[None, None, :], g[None, :, None]
    # Each product of a homography's entry with u (or v) made once per grid column (or row)
    # and broadcast over the grid: the sums are those of every point's own products.
    x, y, w = (
        H[:, i, 0, None, None] * u + H[:, i, 1, None, None] * v + H[:, i, 2, None, None]
        for i in range(3)
    )
    return (x / w).reshape(len(H), -1), (y / w).reshape(len(H), -1)
