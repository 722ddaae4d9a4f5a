"""Simulated active stereo (paper section 3.2): the depth map a real sensor would measure.

A pseudo-random dot pattern is projected from between the cameras; both cameras see it on the
scene's surfaces; the image pair is rectified and matched with OpenCV's semi-global matcher;
the disparity is turned back into z-depth on the reference camera's own (distorted) pixel
grid. Holes (0) appear where matching fails: projector shadows, occlusions seen by one camera
only, steep surfaces.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from annotator.geometry.camera import Camera
from annotator.geometry.transforms import invert
from annotator.rendering.raycast import PlacedMesh, render_scene
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
    def render(
        cls, projector: Camera, placed: Sequence[PlacedMesh], *, fixed: int = 0
    ) -> ShadowMap:
        """``placed`` in the frame of the ``projector`` (a distortion-free camera: one ray
        per pixel of its slide); the first ``fixed`` meshes are the scene's unchanging
        surroundings (see :func:`annotator.synthesis.shading.render_view`)."""
        return cls(render_scene(projector, placed, fixed=fixed)[0].depth, projector.K)

    def lit(
        self, u: np.ndarray, v: np.ndarray, z: np.ndarray, tolerance: float = 1.0
    ) -> np.ndarray:
        """True for points at projector pixel ``(u, v)`` and z-depth ``z`` (mm) that no other
        surface hides from the projector (nearest map pixel; ``tolerance`` mm plus a slope
        bias of two pixels' footprint)."""
        h, w = self.depth.shape
        iu = np.clip(np.rint(u), 0, w - 1).astype(np.intp)
        iv = np.clip(np.rint(v), 0, h - 1).astype(np.intp)
        bias = np.float32(tolerance) + z * np.float32(2.0 / self.K[0, 0])
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
    ``shadows``, the points the projector cannot see stay in its shadow.

    Computed on the whole pixel grid in float32, one coordinate plane at a time (a pixel the
    camera's ray misses is set to 0 at the end).
    """
    hit = view.hits.hit
    d = np.where(hit, view.hits.depth, np.float32(1.0))
    proj_T_cam = projector_T_world @ world_T_cam
    rays = camera.pixel_rays()
    # The point in the projector's frame: p = d * (R ray) + t.
    q = _rotated_rays(camera, proj_T_cam[:3, :3])
    t = proj_T_cam[:3, 3].astype(np.float32)
    x, y, z = (q[i] * d + t[i] for i in range(3))
    K = projector_K.astype(np.float32)
    u = (K[0, 0] * x + K[0, 1] * y) / z + K[0, 2]
    v = K[1, 1] * y / z + K[1, 2]
    lit = _bilinear(pattern, u, v)
    if shadows is not None:
        lit[~shadows.lit(u, v, z)] = 0.0
    # Lambert towards the projector: the normal against the direction from the projector,
    # n . (p_cam - c) with c the projector's centre in the camera's frame.
    c = (-proj_T_cam[:3, :3].T @ proj_T_cam[:3, 3]).astype(np.float32)
    n = view.normals_cam
    towards = (
        n[..., 0] * (rays[..., 0] * d - c[0])
        + n[..., 1] * (rays[..., 1] * d - c[1])
        + n[..., 2] * (d - c[2])
    )
    cos = np.clip(-towards / np.sqrt(x * x + y * y + z * z), 0.0, 1.0)
    img = np.maximum(view.albedo, np.float32(0.25)) * (0.08 + 0.92 * lit * cos)
    img[~hit] = 0.0
    return img.astype(np.float32, copy=False)


_ROTATED: dict[tuple, np.ndarray] = {}


def _rotated_rays(camera: Camera, R: np.ndarray) -> np.ndarray:
    """``R @ ray`` for every pixel ray of ``camera``, as three float32 planes (3, H, W); kept
    per camera and rotation (a rig's cameras and projector do not move)."""
    key = (camera.grid_key, np.asarray(R, float).tobytes())
    out = _ROTATED.get(key)
    if out is None:
        rays = camera.pixel_rays()
        out = np.ascontiguousarray(np.moveaxis(rays @ R.T.astype(np.float32), -1, 0))
        if len(_ROTATED) > 8:
            _ROTATED.clear()
        _ROTATED[key] = out
    return out


def _bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``image`` (float32) sampled at ``(u, v)`` (pixel centres at integer coordinates) by
    bilinear interpolation; 0 outside ``[0, w - 1] x [0, h - 1]`` (scipy's ``map_coordinates``
    with ``order=1, mode="constant"``)."""
    h, w = image.shape
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    u0 = np.clip(np.floor(u), 0, w - 2)
    v0 = np.clip(np.floor(v), 0, h - 2)
    fu, fv = u - u0, v - v0
    i = v0.astype(np.intp) * w + u0.astype(np.intp)
    flat = image.reshape(-1)
    top = flat[i] * (1 - fu) + flat[i + 1] * fu
    bottom = flat[i + w] * (1 - fu) + flat[i + w + 1] * fu
    out = top * (1 - fv) + bottom * fv
    out[~inside] = 0.0
    return out


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
    # The reference pixels' rays, undistorted already (float32: 1e-4 px at these focals).
    ray = cam1.pixel_rays().reshape(-1, 3).astype(np.float64) @ R1.T
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
    sgbm = cv2.StereoSGBM.create(
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
