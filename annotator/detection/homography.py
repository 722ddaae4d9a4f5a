"""Homographies from the unit square to quadrilaterals, many at once: how a marker's own
coordinates (``(0, 0)`` top-left corner, ``(1, 1)`` bottom-right) map to the image."""

from __future__ import annotations

import numpy as np


def unit_square_homographies(quads: np.ndarray) -> np.ndarray:
    """(N, 3, 3) homographies taking the unit square's corners (0,0), (1,0), (1,1), (0,1)
    to each quad's corners."""
    src = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    A = np.zeros((len(quads), 8, 8))
    b = quads.reshape(-1, 8)
    for i, (x, y) in enumerate(src):
        A[:, 2 * i, 0:3] = [x, y, 1]
        A[:, 2 * i + 1, 3:6] = [x, y, 1]
        A[:, 2 * i, 6:8] = -np.outer(quads[:, i, 0], [x, y])
        A[:, 2 * i + 1, 6:8] = -np.outer(quads[:, i, 1], [x, y])
    h = np.linalg.solve(A, b[..., None])[..., 0]
    return np.concatenate([h, np.ones((len(quads), 1))], axis=1).reshape(-1, 3, 3)


def apply_homographies(H: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3, 3) homographies applied to (P, 2) points: x and y, each (N, P) (apart: the
    callers read them so, and an interleaved array would be copied to be read)."""
    u, v = pts[:, 0], pts[:, 1]
    x, y, w = (H[:, i, 0:1] * u + H[:, i, 1:2] * v + H[:, i, 2:3] for i in range(3))
    return x / w, y / w
