"""The scale of a one-camera sequence from its measured depth.

Marker corners fix a sequence only up to its scale: every pose's translation and every
marker's size can grow together and the images stay the same. The printed (or measured,
``annotator sites``) sizes of the markers fix it, but then any bias of the corners (a corner
that reads a little inward, as on any blurred image) or of the sites scales the whole scene:
every part too far or too near by the same fraction. The depth camera measures the scale
directly: the depth it reads at the markers' centres over the depth the solve predicts
there is the factor the scene is off by. The depth camera sees the part's surface under a
marker's centre (:func:`surface_under`), not the mean of its corners: on a curved face the
two differ by the face's sagitta, a bias of the depth and not of the scale. :func:`depth_scale` estimates it robustly; the
solve then takes the sites at that scale (a similarity: the images do not change) and
adjusts again, so that the depth, not a corner bias, says how far the parts are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from annotator.geometry.robust import robust_sigma

__all__ = ["DepthScale", "depth_scale", "surface_under"]

#: At least this many markers with a measured depth to estimate the scale.
MIN_DEPTHS = 12
#: A scale further from 1 than this is not a corner bias but a depth map at fault (another
#: depth unit, a misregistered depth camera): it is not applied.
MAX_SCALE_ERROR = 0.02


@dataclass(frozen=True)
class DepthScale:
    """The factor the scene's translations are off by (measured over predicted depth), its
    1-sigma, and how many markers' depths gave it."""

    factor: float
    sigma: float
    markers: int


def depth_scale(predicted_mm: np.ndarray, measured_mm: np.ndarray) -> DepthScale | None:
    """The median ratio of ``measured_mm`` to ``predicted_mm`` depths (NaN: not measured)
    and its spread (the ratios' robust deviation over the square root of their number);
    None with too few depths, or a factor not within :data:`MAX_SCALE_ERROR` of 1.

    >>> z = np.linspace(400, 600, 50)
    >>> s = depth_scale(z, 1.002 * z + np.r_[0.0, 0.0, 80.0, np.zeros(47)])
    >>> round(s.factor, 4), s.markers
    (1.002, 50)
    """
    ok = np.isfinite(measured_mm) & np.isfinite(predicted_mm) & (predicted_mm > 0)
    if int(ok.sum()) < MIN_DEPTHS:
        return None
    ratio = measured_mm[ok] / predicted_mm[ok]
    factor = float(np.median(ratio))
    if abs(factor - 1.0) > MAX_SCALE_ERROR:
        return None
    spread = robust_sigma(ratio, factor)
    return DepthScale(factor, spread * 1.25 / np.sqrt(ratio.size), int(ratio.size))


def surface_under(triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The point of the surface (``triangles``, (F, 3, 3), model frame) nearest each of
    ``points`` (N, 3): where a marker's centre lies on the part.

    >>> tri = np.array([[[0.0, 0, 0], [10, 0, 0], [0, 10, 0]]])
    >>> surface_under(tri, np.array([[1.0, 1.0, 0.3]])).tolist()
    [[1.0, 1.0, 0.0]]
    """
    from annotator.geometry.mesh import closest_on_triangles

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.empty_like(pts)
    step = max(1, 2_000_000 // max(1, len(triangles)))
    for i in range(0, len(pts), step):
        p = pts[i : i + step]
        q = closest_on_triangles(p[:, None, :], triangles[None])
        best = np.argmin(((q - p[:, None, :]) ** 2).sum(-1), axis=1)
        out[i : i + step] = q[np.arange(len(p)), best]
    return out
