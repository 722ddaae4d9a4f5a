"""The OpenCV camera model: projection with lens distortion and pixel-exact viewing rays.

Pixel centres are at integer coordinates (FORMAT.md). open3d's ``create_rays_pinhole`` shoots
through ``(u + 0.5, v + 0.5)``, half a pixel off this convention, so rays are built here from
``K`` and ``dist`` instead: for each pixel centre ``(u, v)`` of the *distorted* image, the
undistorted normalised coordinates ``(x, y)`` are found by iterative inversion of OpenCV's
distortion model, and the ray direction is ``(x, y, 1)``. Casting these rays renders an image
with the lens distortion already applied, and the ray parameter ``t`` is the z-depth.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np


@dataclass(frozen=True, eq=False)
class Camera:
    """A calibrated camera of the rig.

    Attributes:
        name: The camera's name (its image is ``scenes/<id>/<name>.png``).
        width: Image width in pixels.
        height: Image height in pixels.
        K: 3x3 pinhole intrinsics.
        dist: Distortion coefficients in OpenCV order (k1, k2, p1, p2[, k3[, k4, k5, k6]]).
        rig_T_cam: 4x4 camera-to-reference transform in mm (identity for the reference camera).
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    rig_T_cam: np.ndarray = field(default_factory=lambda: np.eye(4))

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return (self.width, self.height)

    @property
    def grid_key(self) -> tuple:
        """What fixes the camera's pixel rays (size, K, distortion): a key for caches of
        per-pixel tables."""
        return (self.width, self.height, self.K.tobytes(), np.asarray(self.dist, float).tobytes())

    @cached_property
    def cam_T_rig(self) -> np.ndarray:
        """4x4 reference-to-camera transform."""
        from annotator.geometry.transforms import invert

        return invert(self.rig_T_cam)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Project points given in *this camera's* frame (..., 3) to distorted pixels (..., 2).

        Points at or behind the camera (z <= 0) give NaN.
        """
        pts = np.asarray(points_cam, dtype=np.float64)
        shape = pts.shape[:-1]
        flat = pts.reshape(-1, 3)
        if flat.shape[0] == 0:
            return np.zeros((*shape, 2))
        uv, _ = cv2.projectPoints(flat, np.zeros(3), np.zeros(3), self.K, self.dist)
        uv = uv.reshape(-1, 2)
        uv[flat[:, 2] <= 1e-9] = np.nan
        return uv.reshape(*shape, 2)

    def project_from_rig(self, points_rig: np.ndarray) -> np.ndarray:
        """Project points given in the reference (rig) frame to this camera's pixels."""
        pts = np.asarray(points_rig, dtype=np.float64)
        return self.project(pts @ self.cam_T_rig[:3, :3].T + self.cam_T_rig[:3, 3])

    def undistort_pixels(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixel coordinates (..., 2) to undistorted normalised coordinates (..., 2)."""
        uv = np.asarray(uv, dtype=np.float64)
        shape = uv.shape[:-1]
        flat = uv.reshape(-1, 1, 2)
        if not np.any(self.dist):
            Kinv = np.linalg.inv(self.K)
            xy = flat.reshape(-1, 2) @ Kinv[:2, :2].T + Kinv[:2, 2]
            return xy.reshape(*shape, 2)
        # OpenCV's default (5 fixed-point iterations) is exact for a mild lens but leaves
        # errors of 0.1 px at the image corners of a strongly distorted one: check every point
        # by distorting it again, and iterate to convergence where the check fails.
        xy = cv2.undistortPoints(flat, self.K, self.dist).reshape(-1, 2)
        bad = np.arange(len(xy))
        if np.size(self.dist) <= 8:
            target = flat.reshape(-1, 2)
            ok = np.empty(len(xy), bool)
            # In chunks: the temporaries stay in cache (touching fresh memory costs more than
            # the arithmetic).
            for i in range(0, len(xy), 1 << 16):
                j = slice(i, i + (1 << 16))
                ok[j] = (np.abs(self._distort(xy[j]) - target[j]) < UNDISTORT_TOLERANCE_PX).all(1)
            bad = np.flatnonzero(~ok)
        if len(bad):
            criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
            some = flat[bad]
            if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
                fine = cv2.undistortPointsIter(some, self.K, self.dist, None, None, criteria)
            else:  # OpenCV 5.x folded the criteria into undistortPoints
                fine = cv2.undistortPoints(
                    some, self.K, self.dist, R=None, P=None, criteria=criteria
                )
            xy[bad] = fine.reshape(-1, 2)
        return xy.reshape(*shape, 2)

    def _distort(self, xy: np.ndarray) -> np.ndarray:
        """OpenCV's lens model (up to 8 coefficients: k1, k2, p1, p2, k3, k4, k5, k6) from
        undistorted normalised coordinates (N, 2) to pixels (N, 2); ``cv2.projectPoints``
        without its Jacobians, which make it several times slower."""
        k = np.zeros(8)
        k[: np.size(self.dist)] = np.ravel(self.dist)
        k1, k2, p1, p2, k3, k4, k5, k6 = k
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        r4, r6 = r2 * r2, r2 * r2 * r2
        radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        K = self.K
        return np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=1)

    def pixel_rays(self, step: int = 1) -> np.ndarray:
        """Ray directions ``(x, y, 1)`` through every pixel centre, shape (height, width, 3);
        with ``step``, through every ``step``-th pixel of every ``step``-th row only, shape
        (ceil(height / step), ceil(width / step), 3) (the same as
        ``pixel_rays()[::step, ::step]``).

        Computed once per camera and step, and cached (the undistortion of every pixel is
        the slow part; ``step=2`` does a quarter of the work).
        """
        key = self.grid_key
        rays = _RAY_CACHE.get((key, step))
        if rays is None:
            full = _RAY_CACHE.get((key, 1))
            if full is not None:
                rays = full[::step, ::step]
            else:
                u, v = np.meshgrid(
                    np.arange(0, self.width, step, dtype=np.float64),
                    np.arange(0, self.height, step, dtype=np.float64),
                )
                xy = self.undistort_pixels(np.stack([u, v], axis=-1))
                rays = np.concatenate([xy, np.ones((*xy.shape[:2], 1))], axis=-1)
                rays = rays.astype(np.float32)
            rays.setflags(write=False)
            if len(_RAY_CACHE) > 16:
                _RAY_CACHE.clear()
            _RAY_CACHE[(key, step)] = rays
        return rays


_RAY_CACHE: dict[tuple, np.ndarray] = {}

#: A pixel's undistorted coordinates are accepted when distorting them again lands within this
#: distance (px) of the pixel; float32 rays are only good to about 1e-4 px anyway.
UNDISTORT_TOLERANCE_PX = 1e-6
