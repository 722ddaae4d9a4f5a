"""A structured-light depth sensor, modelled on the exact geometry: where it has no data,
where its depth flies, how noisy it is.

A projector beside the camera lights the scene with its code; a pixel has a depth when the
camera receives enough of the projector's light, and not so much that it saturates:

* **Shadows**: points the projector does not light (another surface in the way) have none.
* **Reflectance**: the light a point returns to the camera is its diffuse part (the
  material's diffuse reflectance times the cosine towards the projector) plus its specular
  part, a lobe about the projector's mirror direction whose width grows with the roughness.
  A metal has almost no diffuse part: away from the mirror direction its light reflects
  away from the camera (a hole), at the mirror direction it saturates (a hole too).
* **Grazing angles** seen by the camera or the projector give none.
* **Flying pixels**: across a depth edge a pixel mixes the near and the far surface and
  reads a depth in between.
* **Noise** is that of triangulation: a disparity error of ``disparity_sigma`` px makes
  ``z^2 / (f b)`` times as much depth error (``b`` the camera-projector baseline), more
  where the returned signal is weak.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class StructuredLightSettings:
    """The sensor's limits (signals in units of a white diffuse surface facing the projector).

    Attributes:
        min_signal: Less returned light than this decodes to nothing.
        max_signal: More saturates the camera.
        min_cosine: Surfaces more oblique than this to the camera or projector give nothing.
        disparity_sigma: The decoder's disparity noise (px) at full signal.
        edge_jump_mm: A depth step larger than this (plus ``edge_jump_rel`` of the depth) is
            an edge whose pixels may fly.
        flying_fraction: The share of an edge's pixels that fly.
    """

    min_signal: float = 0.03
    max_signal: float = 4.0
    min_cosine: float = 0.1
    disparity_sigma: float = 0.08
    edge_jump_mm: float = 4.0
    edge_jump_rel: float = 0.01
    flying_fraction: float = 0.5


@dataclass(frozen=True)
class Reflectance:
    """Per pixel (H, W) the surface's diffuse reflectance, its specular reflectance at
    normal incidence and its roughness (0..1)."""

    diffuse: np.ndarray
    mirror: np.ndarray
    roughness: np.ndarray


def returned_signal(
    points: np.ndarray, normals: np.ndarray, projector: np.ndarray, reflectance: Reflectance
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The projector's light each point returns to the camera (at the origin), and the
    cosines of its surface towards the projector and the camera.

    ``points``, ``normals`` (H, W, 3) in the camera frame (mm); ``projector`` (3,) its
    centre in that frame.
    """
    to_proj = projector - points
    dist_p = np.linalg.norm(to_proj, axis=-1, keepdims=True)
    to_proj = to_proj / np.maximum(dist_p, 1e-9)
    to_cam = -points / np.maximum(np.linalg.norm(points, axis=-1, keepdims=True), 1e-9)
    cos_p = np.sum(normals * to_proj, axis=-1)
    cos_c = np.sum(normals * to_cam, axis=-1)
    mirror_dir = 2.0 * cos_p[..., None] * normals - to_proj
    off_mirror = np.arccos(np.clip(np.sum(mirror_dir * to_cam, axis=-1), -1.0, 1.0))
    # Blender's GGX takes alpha = roughness^2; the lobe's width follows it, kept above a
    # hair so that a perfect mirror does not divide by zero.
    width = np.maximum(reflectance.roughness**2, 0.02) * 1.5
    lobe = np.exp(-0.5 * (off_mirror / width) ** 2) / (4.0 * width**2)
    diffuse = reflectance.diffuse * np.clip(cos_p, 0.0, None)
    specular = reflectance.mirror * lobe * np.clip(cos_p, 0.0, None)
    return diffuse + specular, cos_p, cos_c


def structured_light_depth(
    points: np.ndarray,
    normals: np.ndarray,
    hit: np.ndarray,
    lit: np.ndarray,
    reflectance: Reflectance,
    *,
    projector: np.ndarray,
    focal_px: float,
    rng: np.random.Generator,
    settings: StructuredLightSettings = StructuredLightSettings(),
) -> np.ndarray:
    """The sensor's z-depth (mm, NaN = no data) on the camera's pixel grid.

    Args:
        points: (H, W, 3) the exact surface point of each pixel, camera frame (mm).
        normals: (H, W, 3) its unit normal.
        hit: (H, W) bool, the pixel sees a surface.
        lit: (H, W) bool, the projector lights that point (no shadow).
        reflectance: The surface's :class:`Reflectance` per pixel.
        projector: (3,) the projector's centre in the camera frame (mm).
        focal_px: The camera's focal length (px), for the triangulation noise.

    >>> import numpy as np
    >>> h, w = 4, 5
    >>> pts = np.zeros((h, w, 3)); pts[..., 2] = 500.0
    >>> nrm = np.zeros((h, w, 3)); nrm[..., 2] = -1.0
    >>> ones = np.ones((h, w), bool)
    >>> r = Reflectance(np.full((h, w), 0.5), np.full((h, w), 0.04), np.full((h, w), 0.5))
    >>> d = structured_light_depth(pts, nrm, ones, ones, r, projector=np.array([50.0, 0, 0]),
    ...                            focal_px=1000.0, rng=np.random.default_rng(0))
    >>> bool(np.all(np.abs(d - 500.0) < 2.0))
    True
    """
    z = points[..., 2]
    signal, cos_p, cos_c = returned_signal(points, normals, projector, reflectance)
    valid = hit & lit & np.isfinite(z)
    valid &= (cos_p > settings.min_cosine) & (cos_c > settings.min_cosine)
    valid &= (signal >= settings.min_signal) & (signal <= settings.max_signal)
    baseline = float(np.linalg.norm(projector))
    strength = np.sqrt(np.clip(signal, settings.min_signal, 1.0))
    sigma = z**2 * settings.disparity_sigma / (focal_px * baseline) / strength
    depth = np.where(valid, z + rng.normal(0.0, 1.0, z.shape) * np.nan_to_num(sigma), np.nan)
    return _flying_pixels(depth, np.where(hit, z, np.nan), rng, settings)


def _flying_pixels(
    depth: np.ndarray,
    exact: np.ndarray,
    rng: np.random.Generator,
    settings: StructuredLightSettings,
) -> np.ndarray:
    """Along the depth edges of ``exact``, a share of the pixels that have a depth get one
    between the near and the far side (the decoder mixes both surfaces' codes)."""
    filled = np.where(np.isfinite(exact), exact, 0.0).astype(np.float32)
    far = np.where(np.isfinite(exact), exact, np.float32(np.nanmax(exact, initial=0.0)))
    kernel = np.ones((3, 3), np.uint8)
    near = cv2.erode(far.astype(np.float32), kernel)
    back = cv2.dilate(filled, kernel)
    jump = back - near
    edge = np.isfinite(depth) & (jump > settings.edge_jump_mm + settings.edge_jump_rel * near)
    fly = edge & (rng.random(depth.shape) < settings.flying_fraction)
    mix = rng.random(depth.shape)
    out = depth.copy()
    out[fly] = (near + mix * jump)[fly]
    return out
