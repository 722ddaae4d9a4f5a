"""What an export reads from one scene, all of it before it writes anything of that scene.

A scene whose image or depth map is missing, corrupt or mis-sized raises a one-line
:class:`~annotator.errors.UserError` here; the export leaves that scene out, names it, and goes
on with the others (exit status 1), so one bad file never costs the whole export and never
leaves half a scene behind.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from annotator.dataset import Dataset
from annotator.dataset.model import Capture
from annotator.export.undistort import undistort_depth, undistort_image


@dataclass
class SceneInputs:
    """One scene's images and depth, undistorted to the pinhole cameras of the export.

    Attributes:
        images: Per exported camera name, the image as stored (8/16-bit, grey or colour).
        depth: Depth in mm (NaN = none) on the depth camera's grid, or None.
    """

    images: dict[str, np.ndarray]
    depth: np.ndarray | None


def read_scene_inputs(
    ds: Dataset, scene: Capture, cameras: Sequence[str], *, depth: bool = True
) -> SceneInputs:
    """Read and undistort the images of ``cameras`` and (with ``depth``) the depth map of
    a scene, or of one frame of a sequence."""
    images = {}
    for name in cameras:
        cam = ds.rig.camera(name)
        images[name] = undistort_image(scene.read_image(cam), cam)
    d = scene.read_depth(ds.rig) if depth else None
    if d is not None:
        depth_cam = ds.rig.depth_camera
        assert depth_cam is not None  # a depth map is read only when the rig has depth
        d = undistort_depth(d, depth_cam)
    return SceneInputs(images, d)
