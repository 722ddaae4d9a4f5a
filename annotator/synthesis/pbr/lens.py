"""Lens distortion for a renderer that has none: a wider pinhole image, remapped.

Cycles' perspective camera is an ideal pinhole. The rig's cameras are OpenCV cameras with
Brown-Conrady distortion; so the scene is rendered by a distortion-free camera with the
same focal length, wide enough to hold every ray of the distorted image, and each output
pixel then takes the value where its own ray (through its distorted pixel centre) meets
the wide image.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from annotator.geometry.camera import Camera


@dataclass(frozen=True)
class WidePinhole:
    """The distortion-free camera that covers ``camera``'s field, and the remap to it.

    Attributes:
        f: Its focal length (px), the camera's ``fx``; square pixels, the principal point
            at the image centre (``(size - 1) / 2``).
        width, height: Its size (px).
        map_x, map_y: (H, W) float32, per pixel of ``camera``, where its ray meets the wide
            image (for ``cv2.remap``).
    """

    f: float
    width: int
    height: int
    map_x: np.ndarray
    map_y: np.ndarray

    def remap(self, image: np.ndarray, *, nearest: bool = False) -> np.ndarray:
        """The camera's distorted image from the wide one (linear, or nearest for labels)."""
        return cv2.remap(
            image,
            self.map_x,
            self.map_y,
            cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )


def wide_pinhole(camera: Camera, *, margin: int = 2) -> WidePinhole:
    """The :class:`WidePinhole` of ``camera`` (``margin`` px kept around the rays' reach).

    >>> import numpy as np
    >>> K = np.array([[500.0, 0, 159.5], [0, 500.0, 119.5], [0, 0, 1]])
    >>> w = wide_pinhole(Camera("c", 320, 240, K, np.zeros(5)))
    >>> (w.width, w.height), float(abs(w.map_x[0, 0] - (0 + (w.width - 320) / 2)))  < 1e-3
    ((324, 244), True)
    """
    rays = camera.pixel_rays()
    x = rays[..., 0] / rays[..., 2]
    y = rays[..., 1] / rays[..., 2]
    f = float(camera.K[0, 0])
    half_w = float(np.abs(x).max()) * f + 0.5 + margin
    half_h = float(np.abs(y).max()) * f + 0.5 + margin
    # The tolerance keeps a reach of exactly a whole pixel (float32 rounding aside) from growing.
    width, height = 2 * int(np.ceil(half_w - 1e-3)), 2 * int(np.ceil(half_h - 1e-3))
    map_x = (f * x + (width - 1) / 2).astype(np.float32)
    map_y = (f * y + (height - 1) / 2).astype(np.float32)
    return WidePinhole(f, width, height, map_x, map_y)
