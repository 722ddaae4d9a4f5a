"""The scene as oriented points: a depth map back-projected, the setting removed, subsampled.

- **Points**: each pixel's measured z-depth times its exact ray ``(x, y, 1)`` (lens
  distortion included, :meth:`Camera.pixel_rays`), in the depth camera's frame.
- **Normals**: from the organised grid, the cross product of the central differences
  ``step`` pixels apart along the row and the column, turned towards the camera; pixels
  where a difference spans a depth edge (longer than ``edge_factor`` times the pixel
  footprint) get none.
- **Setting**: points within ``max(3 mm, 0.5%)`` of the background, or behind it, or beyond
  the farthest background depth, belong to the bin or the support, not to parts (the tolerances of annotate's completeness check).
  The background is the dataset's empty-bin depth (``rig.depth.background``), else the
  support plane and the bin's walls found in the scene's own depth (as annotate does).
- **Subsampling**: one point per cube of side ``voxel`` mm (mean position, mean normal), the
  same spacing as the model's samples: spacing relative to the *part*, not to the scene's
  extent (OpenCV's detector subsamples a scene relative to its own bounding box, so the
  same part is sampled differently in a bigger bin).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from annotator.geometry.camera import Camera


@dataclass(frozen=True)
class OrientedCloud:
    """Points (N, 3) and unit normals (N, 3), mm, in one frame."""

    points: np.ndarray
    normals: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


def depth_points(camera: Camera, depth: np.ndarray) -> np.ndarray:
    """Measured points (H, W, 3) of a depth map (mm, NaN = none) in the camera frame."""
    return camera.pixel_rays().astype(np.float64) * depth[..., None]


def grid_normals(
    points: np.ndarray, camera: Camera, *, step: int = 2, edge_factor: float = 4.0
) -> np.ndarray:
    """Unit normals (H, W, 3) of an organised grid of points, NaN where there is none (see
    the module docstring)."""
    h, w = points.shape[:2]
    n = np.full((h, w, 3), np.nan)
    s = step
    du = points[s:-s, 2 * s :] - points[s:-s, : -2 * s]
    dv = points[2 * s :, s:-s] - points[: -2 * s, s:-s]
    z = points[s:-s, s:-s, 2]
    # The footprint of 2*step pixels at this depth: a difference much longer is an edge.
    reach = edge_factor * 2 * s * z / float(camera.K[0, 0])
    with np.errstate(invalid="ignore"):
        ok = (np.linalg.norm(du, axis=2) < reach) & (np.linalg.norm(dv, axis=2) < reach)
    c = np.cross(du, dv)
    norm = np.linalg.norm(c, axis=2, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = c / norm
        # Towards the camera: a visible surface faces the viewer.
        flip = np.einsum("hwi,hwi->hw", c, points[s:-s, s:-s]) > 0
    c[flip] *= -1
    c[~ok] = np.nan
    n[s:-s, s:-s] = c
    return n


def voxel_subsample(points: np.ndarray, normals: np.ndarray, voxel: float) -> OrientedCloud:
    """One oriented point per cube of side ``voxel``: the mean position and the normalised
    mean normal of the points in it (cubes whose normals cancel out are dropped)."""
    if len(points) == 0:
        return OrientedCloud(np.zeros((0, 3)), np.zeros((0, 3)))
    keys = np.floor(points / voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    m = len(counts)
    p = np.stack([np.bincount(inverse, points[:, k], m) for k in range(3)], 1) / counts[:, None]
    nsum = np.stack([np.bincount(inverse, normals[:, k], m) for k in range(3)], 1)
    norm = np.linalg.norm(nsum, axis=1)
    ok = norm > 0.5 * counts  # normals that roughly agree
    return OrientedCloud(p[ok], nsum[ok] / norm[ok, None])


def setting_mask(
    camera: Camera,
    depth: np.ndarray,
    background: np.ndarray | None,
    *,
    tolerance_mm: float = 3.0,
    tolerance_rel: float = 0.005,
) -> np.ndarray:
    """Pixels (H, W) whose measured depth belongs to the setting (bin, support), see the
    module docstring; ``background`` is the empty bin's depth (mm, NaN = none) or None."""
    from annotator.annotation.completeness import support_depth

    if background is None:
        background = support_depth(depth, camera.pixel_rays())
    tol = np.maximum(tolerance_mm, tolerance_rel * depth)
    with np.errstate(invalid="ignore"):
        setting = np.isfinite(background) & (depth >= background - tol)
        if np.isfinite(background).any():
            # Behind the farthest setting (a far wall, a sensor's junk where the background
            # has a hole): not a part, and a far plane of points would swamp the voting.
            setting |= depth > np.nanmax(background) + tol
    return setting


def scene_cloud(
    camera: Camera,
    depth: np.ndarray,
    background: np.ndarray | None,
    voxel: float,
    *,
    normal_step: int = 2,
) -> tuple[OrientedCloud, np.ndarray]:
    """The parts' oriented points, subsampled to ``voxel`` mm, and the setting mask (H, W)
    (see the module docstring). Frame: the depth camera's."""
    pts = depth_points(camera, depth)
    nrm = grid_normals(pts, camera, step=normal_step)
    setting = setting_mask(camera, depth, background)
    ok = np.isfinite(pts).all(axis=2) & np.isfinite(nrm).all(axis=2) & ~setting
    return voxel_subsample(pts[ok], nrm[ok], voxel), setting
