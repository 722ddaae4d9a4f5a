"""Simulated active stereo (paper section 3.2): the depth map a real sensor would measure.

A pseudo-random dot pattern is projected from between the cameras; both cameras see it on the
scene's surfaces; the image pair is rectified and matched with OpenCV's semi-global matcher;
the disparity is turned back into z-depth on the reference camera's own (distorted) pixel
grid. Holes (0) appear where matching fails: projector shadows, occlusions seen by one camera
only, steep surfaces.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from scipy.ndimage import map_coordinates

from annotator.geometry.camera import Camera
from annotator.geometry.transforms import invert
from annotator.rendering.raycast import RayScene
from annotator.synthesis.shading import View


def dot_pattern(width: int, height: int, *, seed: int = 7, density: float = 0.12) -> np.ndarray:
    """A float32 pattern of random dots (about 1.5 px), 0..1, the projector's slide."""
    rng = np.random.default_rng(seed)
    dots = (rng.random((height, width)) < density).astype(np.float32)
    return np.clip(cv2.GaussianBlur(dots, (0, 0), 0.7) * 2.5, 0.0, 1.0)


@dataclass(frozen=True)
class ShadowMap:
    """What the projector lights: the z-depth (mm, projector frame) of the nearest surface
    through each of its pixels, cast once per scene (shadow mapping), instead of one ray from
    the projector to every point each camera sees."""

    depth: np.ndarray  # (H, W) float32, inf where nothing
    K: np.ndarray

    @classmethod
    def cast(
        cls, scene: RayScene, K: np.ndarray, size: tuple[int, int], *, scale: float = 1.0
    ) -> ShadowMap:
        """``scene`` in the projector's frame; ``K`` its pinhole intrinsics; the map has
        ``scale`` times the projector's resolution (1: shadow edges within a projector
        pixel; 0.5 casts a quarter of the rays, at the cost of blunter shadow edges)."""
        K = K.copy()
        K[:2] *= scale
        K[:2, 2] += 0.5 * scale - 0.5  # pixel centres at integer coordinates at both scales
        w, h = int(round(size[0] * scale)), int(round(size[1] * scale))
        u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
        return cls(scene.cast(rays).depth, K)

    def lit(self, p: np.ndarray, tolerance: float = 1.0) -> np.ndarray:
        """True for points ``p`` (N, 3, projector frame) that no other surface hides from the
        projector (nearest map pixel; ``tolerance`` mm plus a slope bias of two pixels'
        footprint)."""
        h, w = self.depth.shape
        z = p[:, 2]
        uv = p[:, :2] / z[:, None] * self.K[[0, 1], [0, 1]] + self.K[:2, 2]
        iu = np.clip(np.rint(uv[:, 0]).astype(int), 0, w - 1)
        iv = np.clip(np.rint(uv[:, 1]).astype(int), 0, h - 1)
        bias = tolerance + 2.0 * z / self.K[0, 0]
        return z <= self.depth[iv, iu] + bias


def pattern_image(
    view: View,
    camera: Camera,
    world_T_cam: np.ndarray,
    *,
    projector_T_world: np.ndarray,
    projector_K: np.ndarray,
    pattern: np.ndarray,
    shadows: ShadowMap | None = None,
) -> np.ndarray:
    """What ``camera`` sees of the projected pattern (float32, 0..1), ambient included; with
    ``shadows``, the points the projector cannot see stay in its shadow."""
    hit = view.hits.hit
    rays = camera.pixel_rays()[hit]
    p_cam = rays * view.hits.depth[hit][:, None]
    proj_T_cam = (projector_T_world @ world_T_cam).astype(np.float32)
    p_proj = p_cam @ proj_T_cam[:3, :3].T + proj_T_cam[:3, 3]
    uv = p_proj[:, :2] / p_proj[:, 2:3] @ projector_K[:2, :2].T.astype(np.float32)
    uv += projector_K[:2, 2].astype(np.float32)
    # OpenCV's remap limits maps to 32767 rows: sample with scipy instead.
    lit = map_coordinates(pattern, [uv[:, 1], uv[:, 0]], order=1, mode="constant", cval=0.0).astype(
        np.float32
    )
    if shadows is not None:
        lit[~shadows.lit(p_proj)] = 0.0
    # Lambert towards the projector, in the projector's frame.
    n_proj = view.normals_cam[hit] @ proj_T_cam[:3, :3].T
    cos = np.clip(-(n_proj * p_proj).sum(axis=1) / np.linalg.norm(p_proj, axis=1), 0.0, 1.0)
    albedo = np.maximum(view.albedo[hit], 0.25)
    img = np.zeros(hit.shape, np.float32)
    img[hit] = albedo * (0.08 + 0.92 * lit * cos)
    return img


@dataclass(frozen=True)
class Rectification:
    """Rectification of a camera pair and the lookup from reference pixels to rectified ones."""

    maps1: tuple[np.ndarray, np.ndarray]
    maps2: tuple[np.ndarray, np.ndarray]
    R1: np.ndarray
    P1: np.ndarray
    focal: float
    baseline: float
    offset: float  # disparity of a point at infinity: cx1 - cx2 of the rectified cameras
    ref_in_rect: np.ndarray  # (H, W, 2) rectified coordinates of every reference pixel centre


def rectify(cam1: Camera, cam2: Camera) -> Rectification:
    """Rectify the pair (cam1 is the reference); cached per camera pair."""
    return _rectify(cam1, cam2)


@lru_cache(maxsize=4)
def _rectify(cam1: Camera, cam2: Camera) -> Rectification:
    size = (cam1.width, cam1.height)
    c2_T_c1 = invert(cam2.rig_T_cam) @ cam1.rig_T_cam
    R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(
        cam1.K,
        cam1.dist,
        cam2.K,
        cam2.dist,
        size,
        c2_T_c1[:3, :3],
        c2_T_c1[:3, 3].reshape(3, 1),
        flags=0,
        alpha=0,  # not CALIB_ZERO_DISPARITY: a converging pair keeps disparities small
    )
    m1 = cv2.initUndistortRectifyMap(cam1.K, cam1.dist, R1, P1, size, cv2.CV_32FC1)
    m2 = cv2.initUndistortRectifyMap(cam2.K, cam2.dist, R2, P2, size, cv2.CV_32FC1)
    u, v = np.meshgrid(
        np.arange(cam1.width, dtype=np.float64), np.arange(cam1.height, dtype=np.float64)
    )
    xy = cam1.undistort_pixels(np.stack([u, v], axis=-1)).reshape(-1, 2)
    ray = np.column_stack([xy, np.ones(len(xy))]) @ R1.T
    ref_in_rect = (ray[:, :2] / ray[:, 2:3] * P1[0, 0] + P1[:2, 2]).reshape(
        cam1.height, cam1.width, 2
    )
    return Rectification(
        m1,
        m2,
        R1,
        P1,
        float(P1[0, 0]),
        float(-P2[0, 3] / P2[0, 0]),
        float(P1[0, 2] - P2[0, 2]),
        ref_in_rect.astype(np.float32),
    )


def stereo_depth(
    img1: np.ndarray, img2: np.ndarray, cam1: Camera, cam2: Camera, *, z_range: tuple[float, float]
) -> np.ndarray:
    """Match an 8-bit pattern image pair; z-depth (mm, float32) on cam1's pixels, NaN = hole.

    ``z_range`` (near, far) in mm bounds the disparity search.
    """
    rect = rectify(cam1, cam2)
    r1 = cv2.remap(img1, *rect.maps1, cv2.INTER_LINEAR)
    r2 = cv2.remap(img2, *rect.maps2, cv2.INTER_LINEAR)
    fb = rect.focal * rect.baseline
    d_min = int(np.floor(fb / z_range[1] + rect.offset)) - 2
    n_disp = int(np.ceil((fb / z_range[0] + rect.offset - d_min + 2) / 16.0)) * 16
    block = 5
    sgbm = cv2.StereoSGBM_create(
        minDisparity=d_min,
        numDisparities=n_disp,
        blockSize=block,
        P1=8 * block * block,
        P2=32 * block * block,
        disp12MaxDiff=1,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    disp = sgbm.compute(r1, r2).astype(np.float32) / 16.0
    disp[disp < d_min] = np.nan
    # Sample the disparity at each reference pixel's rectified position (nearest: no blending
    # of foreground and background disparities across depth edges).
    m = rect.ref_in_rect
    d = cv2.remap(
        disp,
        m[..., 0],
        m[..., 1],
        cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )
    z_rect = fb / (d - rect.offset)
    xr = (m[..., 0] - rect.P1[0, 2]) / rect.focal * z_rect
    yr = (m[..., 1] - rect.P1[1, 2]) / rect.focal * z_rect
    # Back from the rectified frame to cam1: x_cam1 = R1^T x_rect; only z is needed.
    z = rect.R1[0, 2] * xr + rect.R1[1, 2] * yr + rect.R1[2, 2] * z_rect
    z[~np.isfinite(z)] = np.nan
    return z.astype(np.float32)
