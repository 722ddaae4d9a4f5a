"""A two-camera rig with a dot-pattern projector, looking down into the bin.

The reference (left) camera is at ``(-baseline/2, 0, distance)`` above the bin centre, the
right one at ``(+baseline/2, 0, distance)``, both aimed at the bin centre (so slightly
converging), with realistic intrinsics (about 50 degrees horizontal field of view) and mild
lens distortion. The projector sits midway between them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from annotator.dataset.model import DepthSpec, Rig
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import invert

DEPTH_SCALE = 0.1  # mm per depth.png unit: 0.1 mm resolution up to 6.5 m


IMAGE_UP = np.array([0.0, -1.0, 0.0])


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = IMAGE_UP) -> np.ndarray:
    """``world_T_cam`` of an OpenCV camera (+z forward, +y down) at ``eye`` looking at ``target``;
    ``up`` is the world direction that appears towards the top of the image (world -y, so
    that image x runs along world +x and the right camera really is on the right)."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, -up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = eye
    return T


@dataclass(frozen=True)
class RigSetup:
    """The rig in the world (bin) frame."""

    rig: Rig
    world_T_cams: tuple[np.ndarray, ...]
    world_T_projector: np.ndarray
    projector_K: np.ndarray
    projector_size: tuple[int, int]

    @property
    def ref_T_world(self) -> np.ndarray:
        """World -> reference camera: poses in gt.json are ``ref_T_world @ world_T_part``."""
        return invert(self.world_T_cams[0])


def make_rig(
    width: int = 1280,
    height: int = 1024,
    *,
    distance: float = 520.0,
    baseline: float = 100.0,
    rng: np.random.Generator | None = None,
) -> RigSetup:
    """Build the rig; ``rng`` perturbs intrinsics and distortion slightly (per dataset)."""
    rng = rng or np.random.default_rng(0)
    target = np.array([0.0, 0.0, 30.0])
    cams, poses = [], []
    for k, (name, x) in enumerate((("left", -baseline / 2), ("right", baseline / 2))):
        f = width * 1.08 * (1 + rng.uniform(-0.01, 0.01))
        K = np.array(
            [
                [f, 0.0, (width - 1) / 2 + rng.uniform(-4, 4)],
                [0.0, f * (1 + rng.uniform(-0.001, 0.001)), (height - 1) / 2 + rng.uniform(-4, 4)],
                [0.0, 0.0, 1.0],
            ]
        )
        dist = np.array(
            [
                -0.08 + rng.uniform(-0.02, 0.02),
                0.06 + rng.uniform(-0.02, 0.02),
                rng.uniform(-5e-4, 5e-4),
                rng.uniform(-5e-4, 5e-4),
                -0.01 + rng.uniform(-0.005, 0.005),
            ]
        )
        world_T_cam = look_at(np.array([x, 0.0, distance]), target)
        poses.append(world_T_cam)
        rig_T_cam = invert(poses[0]) @ world_T_cam
        if k == 0:
            rig_T_cam = np.eye(4)
        cams.append(
            Camera(name=name, width=width, height=height, K=K, dist=dist, rig_T_cam=rig_T_cam)
        )
    proj_size = (width, height)
    fp = width * 0.9
    projector_K = np.array([[fp, 0, (width - 1) / 2], [0, fp, (height - 1) / 2], [0, 0, 1.0]])
    world_T_projector = look_at(np.array([0.0, 0.0, distance]), target)
    rig = Rig(cameras=tuple(cams), depth=DepthSpec(camera="left", scale=DEPTH_SCALE))
    return RigSetup(rig, tuple(poses), world_T_projector, projector_K, proj_size)
