"""Filling the marker regions of an image with what the surface around them looks like.

Two methods, both changing only the pixels of the mask:

- ``surface`` (the default): each masked pixel is filled from the pixels of its *own
  surface* only (``labels``: which instance the pixel shows, -1 for the rest), by harmonic
  interpolation: the filled values solve Laplace's equation over the masked pixels, equal to
  the known pixels of the same surface at the region's border, with no flux across a
  boundary between surfaces. A marker next to another part's edge is thus filled with its
  own part's shading, never with the neighbour's grey level, and a smooth shading gradient
  across the marker is continued. Pixels whose surface shows nothing known around them
  (a marker covering all that is visible of a part) fall back on OpenCV's inpainting.
- ``telea``: OpenCV's ``cv2.inpaint`` (Telea's fast marching), which blends every known
  pixel around the region whatever surface it belongs to.

The markers are on the part in every view and every frame, so no other camera ever sees the
surface beneath one: its surroundings in the same image are what is known of it.
"""

from __future__ import annotations

import cv2
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

METHODS = ("surface", "telea")
#: Radius (px) of OpenCV's inpainting neighbourhood.
INPAINT_RADIUS = 5
#: Weight of the inpainted image in the harmonic fill: it only decides pixels that no known
#: pixel of their surface reaches (the system is singular without it), and is negligible
#: against a neighbour's weight of 1 everywhere else.
ANCHOR = 1e-4


def fill_markers(
    image: np.ndarray,
    mask: np.ndarray,
    labels: np.ndarray | None = None,
    *,
    method: str = "surface",
) -> np.ndarray:
    """``image`` (H, W) or (H, W, C), 8 or 16 bit, with the pixels of ``mask`` filled; every
    other pixel is returned as it was. ``labels`` (H, W): the surface each pixel shows (the
    ``surface`` method; None: one surface)."""
    if method not in METHODS:
        raise ValueError(f"unknown fill method {method!r} (expected one of {', '.join(METHODS)})")
    out = image.copy()
    if not mask.any():
        return out
    telea = _telea(image, mask)
    if method == "telea":
        out[mask] = telea[mask]
        return out
    if labels is None:
        labels = np.zeros(mask.shape, np.int32)
    filled = _harmonic(image, mask, labels, telea)
    info = np.iinfo(image.dtype) if np.issubdtype(image.dtype, np.integer) else None
    if info is not None:
        filled = np.clip(np.round(filled), info.min, info.max)
    out[mask] = filled.astype(image.dtype).reshape(out[mask].shape)
    return out


def _telea(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    m = mask.astype(np.uint8)
    if image.dtype == np.uint8:
        return cv2.inpaint(image, m, INPAINT_RADIUS, cv2.INPAINT_TELEA)
    # cv2.inpaint takes 8-bit images only (and 16/32-bit single-channel ones): fill each
    # channel as float32.
    chans = image.reshape(*image.shape[:2], -1).astype(np.float32)
    done = [
        cv2.inpaint(chans[..., c], m, INPAINT_RADIUS, cv2.INPAINT_TELEA)
        for c in range(chans.shape[2])
    ]
    res = np.stack(done, axis=-1).reshape(image.shape)
    if np.issubdtype(image.dtype, np.integer):
        info = np.iinfo(image.dtype)
        res = np.clip(np.round(res), info.min, info.max)
    return res.astype(image.dtype)


def _harmonic(
    image: np.ndarray, mask: np.ndarray, labels: np.ndarray, anchor: np.ndarray
) -> np.ndarray:
    """(N, C) float64 values of the masked pixels (row-major order)."""
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    n = len(ys)
    index = np.full((h, w), -1, np.int64)
    index[ys, xs] = np.arange(n)
    img = image.reshape(h, w, -1).astype(np.float64)
    channels = img.shape[2]
    diag = np.full(n, ANCHOR)
    rhs = ANCHOR * anchor.reshape(h, w, -1)[ys, xs].astype(np.float64)
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    own = labels[ys, xs]
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        qy, qx = ys + dy, xs + dx
        inside = (qy >= 0) & (qy < h) & (qx >= 0) & (qx < w)
        qy_c, qx_c = np.clip(qy, 0, h - 1), np.clip(qx, 0, w - 1)
        same = inside & (labels[qy_c, qx_c] == own)
        q = index[qy_c, qx_c]
        unknown = same & (q >= 0)
        known = same & (q < 0)
        diag += same
        rows.append(np.flatnonzero(unknown))
        cols.append(q[unknown])
        k = np.flatnonzero(known)
        rhs[k] += img[qy_c[k], qx_c[k]]
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    A = sp.csc_matrix(
        (
            np.concatenate([diag, -np.ones(len(r))]),
            (np.r_[np.arange(n), r], np.r_[np.arange(n), c]),
        ),
        shape=(n, n),
    )
    solve = splu(A)
    return np.stack([solve.solve(rhs[:, ch]) for ch in range(channels)], axis=1)
