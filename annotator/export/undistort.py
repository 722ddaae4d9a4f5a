"""Undistorting a scene's images, depth and masks to a pinhole camera with the same K.

BOP and the Siléane format have no lens distortion model. Images are resampled bilinearly,
depth maps with the nearest neighbour (no blending across depth edges); masks are not
resampled but rendered directly with the pinhole camera, so they stay exact; poses do not
change (the camera frame is the same, only the image is).
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import cv2
import numpy as np

from annotator.dataset.model import Rig
from annotator.geometry.camera import Camera


def pinhole(cam: Camera) -> Camera:
    """The same camera without distortion."""
    return replace(cam, dist=np.zeros(5))


def pinhole_rig(rig: Rig) -> Rig:
    return Rig(cameras=tuple(pinhole(c) for c in rig.cameras), depth=rig.depth)


@lru_cache(maxsize=8)
def _maps(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    return cv2.initUndistortRectifyMap(
        cam.K, cam.dist, None, cam.K, (cam.width, cam.height), cv2.CV_32FC1
    )


def undistort_image(img: np.ndarray, cam: Camera) -> np.ndarray:
    mx, my = _maps(cam)
    return cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def undistort_depth(depth_mm: np.ndarray, cam: Camera) -> np.ndarray:
    """Depth (mm, NaN holes) on the pinhole grid; z is unchanged by undistortion."""
    mx, my = _maps(cam)
    return cv2.remap(
        depth_mm.astype(np.float32),
        mx,
        my,
        cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )
