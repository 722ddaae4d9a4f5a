"""Filling the marker regions of an image with what the surface around them looks like.

Two methods, both changing only the pixels of the mask:

- ``surface`` (the default): each masked pixel is filled from its *own surface* only
  (``labels``: which posed instance the pixel shows, -1 for the rest). Per instance, a
  shading model ``a + b (n.v)`` (Lambert's law for a light beside the camera, as a
  bin-picking rig's projector or ring light; ``n`` the face's normal from the pose, ``v``
  towards the camera) is fitted on all its known pixels; one light lights every part, so a
  part seen on one face only (its other faces under markers) borrows the others' ratio
  ``a / b`` and fits its albedo alone. The model is what carries a face's shading across a
  marker, and a crease between two faces, and a cylinder's fast-changing shading near its
  outline. What it leaves (the albedo's and light's local departures from it) is carried in
  from the region's border by a normalised convolution over the known pixels of the same
  surface. The fill is then blurred as the image is, so that an outline crossing a region is
  as soft as elsewhere, and given the sensor noise the image has around it. A marker next to another part's edge is thus filled with its own
  part's shading, never with the neighbour's grey level. Pixels of no instance (the bin, an
  unannotated part) get the mean of the known pixels of the same label around them.
- ``telea``: OpenCV's ``cv2.inpaint`` (Telea's fast marching), which blends every known
  pixel around the region whatever surface it belongs to.

The markers are on the part in every view and every frame, so no other camera ever sees the
surface beneath one: its surroundings in the same image are what is known of it. Richer
lighting models (the normal's three components) extrapolate wildly to a face seen nowhere
else; a harmonic interpolation of the residual (a sparse solve) was a little closer to the
truth and several times slower (see benchmarks/bench_remove_markers.py).
"""

from __future__ import annotations

import hashlib

import cv2
import numpy as np

from annotator.geometry.robust import robust_sigma

METHODS = ("surface", "telea")
#: Radius (px) of OpenCV's inpainting neighbourhood.
INPAINT_RADIUS = 5
#: A part's shading model is fitted on its known pixels (every FIT_STEP-th row and column:
#: a part's shading varies slowly) ...
FIT_STEP = 2
#: ... when there are at least this many; and it is evaluated within this distance (px) of
#: the mask, where what it leaves is read.
MIN_FIT_PIXELS = 30
NEAR_PX = 8


def fill_markers(
    image: np.ndarray,
    mask: np.ndarray,
    labels: np.ndarray | None = None,
    *,
    normals: np.ndarray | None = None,
    rays: np.ndarray | None = None,
    blur: float = 0.0,
    noise: bool = True,
    method: str = "surface",
) -> np.ndarray:
    """``image`` (H, W) or (H, W, C), 8 or 16 bit, with the pixels of ``mask`` filled; every
    other pixel is returned as it was. For the ``surface`` method: ``labels`` (H, W), the
    instance each pixel shows (-1: none; None: one surface), ``normals`` (H, W, 3), the unit
    normal (camera frame) of its face (0: unknown; None: no shading model), ``rays``
    (H, W, 3), the viewing ray through each pixel (any length; None: along z), and ``blur``,
    the image's blur (Gaussian sigma, px); ``noise``: give the filled pixels the sensor
    noise the image has around them (a smooth patch is a cue a network could learn as it
    learns the markers), drawn from the image's own content, so the same image is always
    filled the same way.

    >>> img = np.full((32, 32), 100, np.uint8)
    >>> img[10:20, 10:20] = 0  # a marker's black square
    >>> mask = np.zeros((32, 32), bool)
    >>> mask[10:20, 10:20] = True
    >>> int(fill_markers(img, mask, noise=False)[15, 15])
    100
    """
    if method not in METHODS:
        raise ValueError(f"unknown fill method {method!r} (expected one of {', '.join(METHODS)})")
    out = image.copy()
    if not mask.any():
        return out
    if method == "telea":
        out[mask] = _telea(image, mask)[mask]
        return out
    if labels is None:
        labels = np.zeros(mask.shape, np.int32)
    model = None if normals is None else _shading(image, mask, labels, normals, rays)
    filled = _spread(image, mask, labels, model, _surroundings(image, mask))
    if blur > 0:
        # Blur the filled pixels with their neighbourhood (already blurred as the camera
        # blurs): the outlines the fill draws hard are made as soft as the image's.
        canvas = image.astype(np.float32).reshape(*mask.shape, -1)
        canvas[mask] = filled
        soft = cv2.GaussianBlur(canvas, (0, 0), blur).reshape(canvas.shape)
        filled = soft[mask].astype(np.float64)
    if noise:
        filled = filled + _grain(image, mask, filled.shape)
    info = np.iinfo(image.dtype) if np.issubdtype(image.dtype, np.integer) else None
    if info is not None:
        filled = np.clip(np.round(filled), info.min, info.max)
    out[mask] = filled.astype(image.dtype).reshape(out[mask].shape)
    return out


#: Known pixels within this distance (px) of the mask measure the image's noise.
NOISE_RING_PX = 8


def noise_sigma(image: np.ndarray, where: np.ndarray) -> float:
    """The sensor noise (Gaussian sigma, grey levels) of ``image`` at the pixels ``where``:
    the median absolute response of Immerkaer's kernel (which cancels shading that is
    linear over 3x3 pixels and answers white noise with 6 sigma), robust to edges."""
    img = image.reshape(*image.shape[:2], -1).astype(np.float32)
    kernel = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    sel = where.copy()
    sel[[0, -1], :] = False
    sel[:, [0, -1]] = False
    if sel.sum() < 50:
        return 0.0
    resp = np.stack(
        [cv2.filter2D(img[..., c], -1, kernel)[sel] for c in range(img.shape[2])], axis=1
    )
    return robust_sigma(resp) / 6.0


def _grain(image: np.ndarray, mask: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """White Gaussian noise of the image's own level around the mask, for the filled pixels;
    the generator is seeded by the image and the mask, so a fill is reproducible."""
    d = 2 * NOISE_RING_PX + 1
    ring = (cv2.dilate(mask.astype(np.uint8), np.ones((d, d), np.uint8)) > 0) & ~mask
    # The mask's own border is left out: the fill's blur reaches into it.
    ring &= cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) == 0
    sigma = noise_sigma(image, ring)
    if sigma <= 0:
        return np.zeros(shape)
    seed = int.from_bytes(
        hashlib.blake2b(image.tobytes() + np.packbits(mask).tobytes(), digest_size=8).digest(),
        "little",
    )
    return np.random.default_rng(seed).normal(0.0, sigma, shape)


#: Gaussian sigma (px) of the average of the known pixels around a region.
SURROUNDINGS_PX = 6.0


def _surroundings(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, C) float32: at each pixel, the Gaussian-weighted mean of the known pixels
    around it, whatever their surface (the fill of a pixel its own surface does not reach)."""
    known = (~mask).astype(np.float32)
    img = image.reshape(*mask.shape, -1).astype(np.float32)
    d = int(4 * SURROUNDINGS_PX) | 1
    weight = cv2.GaussianBlur(known, (d, d), SURROUNDINGS_PX)
    out = np.empty_like(img)
    for ch in range(img.shape[2]):
        total = cv2.GaussianBlur(img[..., ch] * known, (d, d), SURROUNDINGS_PX)
        mean = np.divide(total, weight, out=np.zeros_like(total), where=weight > 1e-6)
        out[..., ch] = mean
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


#: Gaussian sigma (px) of the normalised convolution that carries what the model leaves (or
#: the image itself, on a surface without one) in from a region's border.
SPREAD_PX = 6.0


def _spread(
    image: np.ndarray,
    mask: np.ndarray,
    labels: np.ndarray,
    model: np.ndarray | None,
    fallback: np.ndarray,
) -> np.ndarray:
    """(N, C) float64 values of the masked pixels (row-major order): ``model`` plus the
    Gaussian-weighted mean of what it leaves at the known pixels of the same surface around
    (normalised convolution, per surface); where none is near, the model alone, or
    ``fallback`` for a surface without one."""
    h, w = mask.shape
    img = image.reshape(h, w, -1).astype(np.float32)
    res = img if model is None else img - model.astype(np.float32)
    out = np.zeros((h, w, img.shape[2]), np.float32)
    pad = int(np.ceil(4 * SPREAD_PX))
    d = 2 * pad + 1
    n, comp, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    for i in range(1, n):
        x, y, bw, bh, _ = stats[i]
        x0, y0 = max(x - pad, 0), max(y - pad, 0)
        x1, y1 = min(x + bw + pad, w), min(y + bh + pad, h)
        sub = (slice(y0, y1), slice(x0, x1))
        region = comp[sub] == i
        lab, known_all = labels[sub], ~mask[sub]
        defined = None if model is None else np.any(model[sub] != 0, axis=2)
        for L in np.unique(lab[region]):
            todo = region & (lab == L)
            modelled = defined is not None and bool(np.any(defined[todo]))
            # A modelled surface's residual is known only where the model is evaluated.
            known = (known_all & (lab == L) & (defined if modelled else True)).astype(np.float32)
            weight = cv2.GaussianBlur(known, (d, d), SPREAD_PX)[todo]
            spread = np.stack(
                [
                    cv2.GaussianBlur(res[sub][..., ch] * known, (d, d), SPREAD_PX)[todo]
                    for ch in range(img.shape[2])
                ],
                axis=1,
            )
            far = weight < 1e-6
            val = spread / np.maximum(weight, 1e-6)[:, None]
            if modelled:
                val[far] = 0.0
            else:
                val[far] = fallback[sub][todo][far]
            out[sub][todo] = val
    values = out[mask].astype(np.float64)
    return values if model is None else values + model[mask]
