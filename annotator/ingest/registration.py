"""Depth registered to colour: a depth map taken by one camera redrawn on another camera's
pixel grid (FORMAT.md: ``depth.png`` lies on ``rig.depth.camera``'s grid).

Each depth pixel is lifted to a 3D point along its own (undistorted) ray, moved into the
colour camera with ``colour_T_depth`` and projected with the colour camera's distortion. A
depth pixel seen from the colour camera covers about ``fx_colour / fx_depth`` colour pixels
across, so each point is drawn as a square a pixel wider than that (else a colour grid
finer than the depth grid would be a sieve of holes). Where several points land on one
colour pixel, the nearest surface wins (z-buffer), so a foreground edge hides what lies
behind it, and of that surface's points the one projected closest to the pixel's centre
gives its depth. Colour pixels that no depth point reaches are left without a measurement
(NaN), as is every pixel whose depth pixel had none.
"""

from __future__ import annotations

import math

import numpy as np

from annotator.geometry.camera import Camera

__all__ = ["register_depth"]

#: Depths within this fraction of the nearest one at a pixel count as the same surface.
SAME_SURFACE = 0.02


def register_depth(
    depth_mm: np.ndarray, depth_cam: Camera, colour_cam: Camera, colour_T_depth: np.ndarray
) -> np.ndarray:
    """The depth map ``depth_mm`` (float mm on ``depth_cam``'s grid, NaN or <= 0 = none) as
    the colour camera would see it: float mm on ``colour_cam``'s grid, NaN = none.

    ``colour_T_depth``: 4x4, mm, maps points of the depth camera into the colour camera.

    >>> cam = Camera("c", 4, 3, np.array([[2.0, 0, 1.5], [0, 2.0, 1.0], [0, 0, 1]]))
    >>> flat = np.full((3, 4), 500.0)
    >>> bool(np.allclose(register_depth(flat, cam, cam, np.eye(4)), 500.0))
    True
    """
    depth = np.asarray(depth_mm, np.float64)
    if depth.shape != (depth_cam.height, depth_cam.width):
        raise ValueError(f"depth map {depth.shape} is not of the depth camera's size")
    rays = depth_cam.pixel_rays()
    valid = np.isfinite(depth) & (depth > 0)
    points = rays[valid] * depth[valid][:, None]
    T = np.asarray(colour_T_depth, np.float64)
    points = points @ T[:3, :3].T + T[:3, 3]
    out = np.full((colour_cam.height, colour_cam.width), np.inf)
    in_front = points[:, 2] > 1e-6
    points = points[in_front]
    if len(points):
        uv = colour_cam.project(points)
        ok = np.isfinite(uv).all(axis=1)
        _splat(out, uv[ok], points[ok, 2], _footprint(depth_cam, colour_cam))
    out[~np.isfinite(out)] = np.nan
    return out


def _footprint(depth_cam: Camera, colour_cam: Camera) -> float:
    """How many colour pixels across a depth point is drawn: the colour pixels one depth
    pixel covers, and one more, so that neighbouring squares overlap where a slanted
    surface or the lens stretches them apart (the z-buffer settles the overlap)."""
    ratio = max(colour_cam.K[0, 0] / depth_cam.K[0, 0], colour_cam.K[1, 1] / depth_cam.K[1, 1])
    return max(1.0, float(ratio)) + 1.0


def _splat(out: np.ndarray, uv: np.ndarray, z: np.ndarray, size: float) -> None:
    """Draw each point as a ``size``-wide square of pixels centred on ``uv`` (in place).

    Of the squares covering a pixel, those within :data:`SAME_SURFACE` of the nearest one's
    depth are taken as one surface and the point whose centre is closest to the pixel gives
    its depth (the overlap then costs no accuracy on a slanted surface); a square farther
    back is hidden (z-buffer).
    """
    h, w = out.shape
    half = size / 2.0
    # The pixels whose centres fall in [u - half, u + half): at most ceil(size) + 1 across.
    lo_u = np.ceil(uv[:, 0] - half).astype(np.int64)
    lo_v = np.ceil(uv[:, 1] - half).astype(np.int64)
    hi_u = np.ceil(uv[:, 0] + half).astype(np.int64)
    hi_v = np.ceil(uv[:, 1] + half).astype(np.int64)
    span = math.ceil(size) + 1
    pixels, depths, dists = [], [], []
    for dv in range(span):
        for du in range(span):
            u = lo_u + du
            v = lo_v + dv
            keep = (u < hi_u) & (v < hi_v) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            pixels.append(v[keep] * w + u[keep])
            depths.append(z[keep])
            dists.append((u[keep] - uv[keep, 0]) ** 2 + (v[keep] - uv[keep, 1]) ** 2)
    flat = np.concatenate(pixels)
    if not len(flat):
        return
    zs = np.concatenate(depths)
    d2 = np.concatenate(dists)
    nearest = np.full(h * w, np.inf)
    np.minimum.at(nearest, flat, zs)
    front = zs <= nearest[flat] * (1.0 + SAME_SURFACE)
    flat, zs, d2 = flat[front], zs[front], d2[front]
    closest = np.full(h * w, np.inf)
    np.minimum.at(closest, flat, d2)
    best = d2 == closest[flat]
    out.reshape(-1)[flat[best]] = zs[best]  # ties (equally close) hold equal surfaces
