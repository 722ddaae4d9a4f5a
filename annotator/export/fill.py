"""Filling the marker regions of an image with what the surface around them looks like.

Two methods, both changing only the pixels of the mask:

- ``surface`` (the default): each masked pixel is filled from the pixels of its *own
  surface* only (``labels``: which instance the pixel shows, -1 for the rest; ``normals``:
  its face's normal, so that two faces of a part meeting at a crease are two surfaces), by
  harmonic interpolation: the filled values solve Laplace's equation over the masked pixels,
  equal to the known pixels of the same surface at the region's border, with no flux across
  a boundary between surfaces. With normals (and viewing rays), what is interpolated is what
  a shading model of each part does not explain: per part, its known pixels around the
  regions are fitted by ``a + b (n.v)`` (Lambert's law for a light beside the camera, as a
  bin-picking rig's projector or ring light; richer models, with the normal's three
  components, extrapolate wildly to a face seen nowhere else), so shading that changes fast (a cylinder towards its outline) is carried
  across a marker, not only its values at the border. The fill is then blurred as the image
  is, so that an outline crossing a region is as soft as elsewhere. A marker next to another part's edge is thus filled with its
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
#: Neighbouring pixels are on one surface when their normals are within this angle (cosine):
#: a curved part's normals turn a few degrees from a pixel to the next, a box's by 90.
SMOOTH_COS = float(np.cos(np.radians(20.0)))
#: A part's shading model is fitted on its known pixels (every FIT_STEP-th row and column:
#: a part's shading varies slowly) ...
FIT_STEP = 2
#: ... when there are at least this many; and it is used within this distance (px) of the
#: mask (the harmonic fill's neighbours).
MIN_FIT_PIXELS = 30
NEAR_PX = 2


def fill_markers(
    image: np.ndarray,
    mask: np.ndarray,
    labels: np.ndarray | None = None,
    *,
    normals: np.ndarray | None = None,
    rays: np.ndarray | None = None,
    blur: float = 0.0,
    method: str = "surface",
) -> np.ndarray:
    """``image`` (H, W) or (H, W, C), 8 or 16 bit, with the pixels of ``mask`` filled; every
    other pixel is returned as it was. For the ``surface`` method: ``labels`` (H, W), the
    surface each pixel shows (None: one surface), ``normals`` (H, W, 3), its unit normal
    (0: unknown, joins nothing but its own label), ``rays`` (H, W, 3), the viewing ray through
    each pixel (any length), and ``blur``, the image's blur (Gaussian sigma, px)."""
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
    model = None if normals is None else _shading(image, mask, labels, normals, rays)
    filled = _harmonic(image, mask, labels, normals, model, telea)
    if blur > 0:
        # Blur the filled pixels with their neighbourhood (already blurred as the camera
        # blurs): the outlines the fill draws hard are made as soft as the image's.
        canvas = image.astype(np.float32).reshape(*mask.shape, -1)
        canvas[mask] = filled
        soft = cv2.GaussianBlur(canvas, (0, 0), blur).reshape(canvas.shape)
        filled = soft[mask].astype(np.float64)
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
    image: np.ndarray,
    mask: np.ndarray,
    labels: np.ndarray,
    normals: np.ndarray | None,
    model: np.ndarray | None,
    anchor: np.ndarray,
) -> np.ndarray:
    """(N, C) float64 values of the masked pixels (row-major order): ``model`` (H, W, C)
    plus the harmonic interpolation of what it leaves (None: of the image itself)."""
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    n = len(ys)
    index = np.full((h, w), -1, np.int64)
    index[ys, xs] = np.arange(n)
    img = image.reshape(h, w, -1).astype(np.float64)
    channels = img.shape[2]
    base = anchor.reshape(h, w, -1)[ys, xs].astype(np.float64)
    if model is not None:
        img = img - model
        # A pixel no known pixel of its surface reaches is its part's shading where the part
        # has a model (the residual's anchor is 0), OpenCV's inpainting elsewhere.
        modelled: np.ndarray = np.any(model[ys, xs] != 0, axis=1)
        base = np.where(modelled[:, None], 0.0, base)
    diag = np.full(n, ANCHOR)
    rhs = ANCHOR * base
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    own = labels[ys, xs]
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        qy, qx = ys + dy, xs + dx
        inside = (qy >= 0) & (qy < h) & (qx >= 0) & (qx < w)
        qy_c, qx_c = np.clip(qy, 0, h - 1), np.clip(qx, 0, w - 1)
        same = inside & (labels[qy_c, qx_c] == own)
        if normals is not None:
            np_, nq = normals[ys, xs], normals[qy_c, qx_c]
            unknown_normal = ~np_.any(axis=1) | ~nq.any(axis=1)
            same &= unknown_normal | ((np_ * nq).sum(axis=1) > SMOOTH_COS)
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
    out = np.stack([solve.solve(rhs[:, ch]) for ch in range(channels)], axis=1)
    return out if model is None else out + model[ys, xs]


def _shading(
    image: np.ndarray,
    mask: np.ndarray,
    labels: np.ndarray,
    normals: np.ndarray,
    rays: np.ndarray | None,
) -> np.ndarray:
    """(H, W, C) float64: per part (label >= 0), its shading model fitted on its known
    pixels, evaluated near the mask; 0 elsewhere and for parts too little seen.

    One light lights every part, which differ by albedo only: ``a + b (n.v)`` with one ratio
    ``a / b`` for the whole image. A part whose known pixels span enough orientations fits
    its own two numbers (and its ratio); a part seen on one face only (its other faces under
    markers) takes the median ratio of the others and fits its albedo alone."""
    h, w = mask.shape
    img = image.reshape(h, w, -1).astype(np.float64)
    model = np.zeros_like(img)
    d = 2 * NEAR_PX + 1
    near = cv2.dilate(mask.astype(np.uint8), np.ones((d, d), np.uint8)) > 0
    has_normal = normals.any(axis=2)
    parts = np.unique(labels[mask & has_normal])
    parts = parts[parts >= 0]
    if not len(parts):
        return model
    sample = np.zeros_like(mask)
    sample[::FIT_STEP, ::FIT_STEP] = True
    fits: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    coefs: dict[int, np.ndarray] = {}
    ratios = []
    for k in parts:
        on = labels == k
        fy, fx = np.nonzero(on & sample & ~mask & has_normal)
        if len(fy) < MIN_FIT_PIXELS:
            continue
        F = _features(normals[fy, fx], None if rays is None else rays[fy, fx])
        v = img[fy, fx]
        ey, ex = np.nonzero(on & near & has_normal)
        fits[int(k)] = (F, v, np.stack([ey, ex]))
        lo, hi = np.percentile(F[:, 1], [5, 95])
        if hi - lo < MIN_SPREAD:
            continue
        coef = _robust_fit(F, v)
        coefs[int(k)] = coef
        if np.all(coef[1] > 0):
            ratios.append(coef[0] / coef[1])
    ratio = np.median(np.stack(ratios), axis=0) if ratios else None
    for k, (F, v, (ey, ex)) in fits.items():
        if k in coefs:
            coef = coefs[k]
        else:
            if ratio is None:  # nothing pins the light down: the part's mean grey
                coef = np.stack([v.mean(axis=0), np.zeros(v.shape[1])])
            else:
                basis = ratio[None, :] + F[:, 1:2]  # (N, C): albedo * basis = value
                scale = (basis * v).sum(axis=0) / np.maximum((basis * basis).sum(axis=0), 1e-12)
                coef = np.stack([scale * ratio, scale])
        model[ey, ex] = _features(normals[ey, ex], None if rays is None else rays[ey, ex]) @ coef
    return model


#: A part fits its own light ratio when the cosines of its known pixels spread this much
#: (5th to 95th percentile): two faces at 40 degrees do.
MIN_SPREAD = 0.2


def _robust_fit(F: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Least squares of ``v`` (N, C) on ``F`` (N, 2), once more without the worst-fitting
    pixels (outlines, shadows, another marker's blur: not the part's shading)."""
    coef = np.linalg.lstsq(F, v, rcond=None)[0]
    res = np.abs(v - F @ coef).max(axis=1)
    keep = res <= max(3.0 * float(np.median(res)), 1e-6)
    if keep.sum() >= MIN_FIT_PIXELS:
        coef = np.linalg.lstsq(F[keep], v[keep], rcond=None)[0]
    return coef


def _features(n: np.ndarray, rays: np.ndarray | None) -> np.ndarray:
    """(N, 2) shading features of unit normals ``n``: 1 and n.v, v the unit direction
    towards the camera (the normal's z without rays)."""
    if rays is not None:
        v = -rays / np.linalg.norm(rays, axis=1, keepdims=True)
        cos = (n * v).sum(axis=1)
    else:
        cos = -n[:, 2]
    return np.stack([np.ones(len(n)), cos], axis=1).astype(np.float64)
