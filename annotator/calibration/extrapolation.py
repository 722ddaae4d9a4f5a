"""Where a camera's distortion model is extrapolated, and by how much.

Lens distortion is measured only where the board's corners were seen. Outside that region
(the convex hull of the corners used) the fitted polynomial is extrapolated: a model with
more coefficients than the covered region supports can bend the image borders by tens of
pixels while fitting the middle perfectly. The figures: the fraction of the image inside
the hull (``coverage``), the distortion's displacement (distorted minus pinhole position,
px) at the four image corners, and its largest value over the corners actually seen. A
displacement at the image corners beyond ``RATIO`` times the covered region's largest (and
at least ``MIN_PX`` more) means the corners of the image are predicted by extrapolation
alone: a warning, and a reason to prefer a simpler model.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from annotator.geometry.camera import Camera

#: The image corners' displacement may exceed the covered region's by this factor ...
RATIO = 3.0
#: ... and by this many pixels, before it counts as extrapolation.
MIN_PX = 2.0


@dataclass(frozen=True)
class Extrapolation:
    """How much of one camera's distortion rests on extrapolation.

    Attributes:
        coverage: Fraction of the image inside the convex hull of the corners used.
        corner_px: Largest displacement of the distortion at the four image corners.
        covered_px: Largest displacement over the corners used.
        hull: (n, 2) the hull's vertices, px.
    """

    coverage: float
    corner_px: float
    covered_px: float
    hull: np.ndarray

    @property
    def extrapolated(self) -> bool:
        """True if the image corners are bent well beyond anything the corners support."""
        return self.corner_px > max(RATIO * self.covered_px, self.covered_px + MIN_PX)

    def warning(self, camera: str) -> str:
        """The one-line warning for the report."""
        return (
            f"camera {camera}: the board covered {100 * self.coverage:.0f}% of the image and "
            f"the distortion model is extrapolated: it moves the image corners by "
            f"{self.corner_px:.1f} px against at most {self.covered_px:.1f} px where the "
            "board was seen (take shots with the board near the image borders and corners)"
        )


def displacement(cam: Camera, uv: np.ndarray) -> np.ndarray:
    """(n,) distance (px) between where the distortion puts a ray and where a pinhole camera
    with the same K would, for the rays of pinhole pixels ``uv`` (n, 2)."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    K = cam.K
    x = np.column_stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1]])
    pts = np.column_stack([x, np.ones(len(x))])
    distorted, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, cam.dist)
    return np.linalg.norm(distorted.reshape(-1, 2) - uv, axis=1)


def extrapolation(cam: Camera, corners_px: np.ndarray) -> Extrapolation:
    """The figures of the module docstring for ``cam`` and the (n, 2) corners it used."""
    w, h = cam.width, cam.height
    pts = np.asarray(corners_px, np.float32).reshape(-1, 2)
    if len(pts) < 3:
        return Extrapolation(0.0, float("inf"), 0.0, pts.astype(np.float64))
    hull = cv2.convexHull(pts).reshape(-1, 2).astype(np.float64)
    coverage = float(cv2.contourArea(hull.astype(np.float32))) / (w * h)
    image_corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float64)
    return Extrapolation(
        coverage=coverage,
        corner_px=float(displacement(cam, image_corners).max()),
        covered_px=float(displacement(cam, pts).max()),
        hull=hull,
    )
