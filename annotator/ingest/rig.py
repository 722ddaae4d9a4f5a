"""The rig a recording's own calibration describes (``ingest --rig-from-source``), and the
check that a recording was made with the rig a dataset already has.

A new dataset gets ``rig: {moving: true}`` with one camera, the file's colour camera (its
K, distortion and size), depth on that camera when the file has depth, the ArUco dictionary
asked for and no objects yet (FORMAT.md). An existing rig camera must match the file's
colour camera: the same size and K within :data:`K_TOLERANCE` (focal lengths relative to
themselves, the principal point relative to the image size).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from annotator.dataset.model import DepthSpec, Rig
from annotator.dataset.write import write_dataset_yaml
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.ingest.recording import Calibration

#: How far the file's intrinsics may be from the rig camera's (a fraction).
K_TOLERANCE = 0.01
#: rig.depth.scale of a rig written from a recording: mm per unit of depth.png.
DEPTH_SCALE_MM = 0.1
DEFAULT_DICTIONARY = "DICT_4X4_1000"


def rig_from_calibration(cal: Calibration, name: str, *, depth: bool) -> Rig:
    """A moving rig of the file's colour camera, called ``name`` (depth on it if ``depth``)."""
    cam = Camera(name, cal.colour.width, cal.colour.height, cal.colour.K, cal.colour.dist)
    spec = DepthSpec(name, DEPTH_SCALE_MM) if depth and cal.depth is not None else None
    return Rig(cameras=(cam,), depth=spec, moving=True)


def write_new_dataset(root: Path, rig: Rig, dictionary: str, source: Path) -> None:
    """dataset.yaml of a new dataset at ``root`` holding ``rig`` and no objects yet."""
    write_dataset_yaml(
        root,
        name=root.name,
        dictionary=dictionary,
        rig=rig,
        objects=[],
        rig_source=str(source.resolve()),
    )


def describe(cam: Camera) -> str:
    """``fx 612.3 fy 612.1 cx 319.8 cy 241.0 (640x480)``."""
    K = cam.K
    return (
        f"fx {K[0, 0]:.1f} fy {K[1, 1]:.1f} cx {K[0, 2]:.1f} cy {K[1, 2]:.1f} "
        f"({cam.width}x{cam.height})"
    )


def mismatch(rig_cam: Camera, file_cam: Camera, tolerance: float = K_TOLERANCE) -> float | None:
    """How far the file's camera is from the rig's (the worst relative difference), or None
    when within ``tolerance`` and of the same size (inf when the sizes differ).

    >>> a = Camera("a", 640, 480, np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]]))
    >>> b = Camera("b", 640, 480, np.array([[603.0, 0, 320], [0, 600, 240], [0, 0, 1]]))
    >>> c = Camera("c", 640, 480, np.array([[609.0, 0, 320], [0, 600, 240], [0, 0, 1]]))
    >>> mismatch(a, b) is None, round(mismatch(a, c), 3)
    (True, 0.015)
    """
    if rig_cam.size != file_cam.size:
        return float("inf")
    a, b = rig_cam.K, file_cam.K
    worst = max(
        abs(b[0, 0] - a[0, 0]) / abs(a[0, 0]),
        abs(b[1, 1] - a[1, 1]) / abs(a[1, 1]),
        abs(b[0, 2] - a[0, 2]) / rig_cam.width,
        abs(b[1, 2] - a[1, 2]) / rig_cam.height,
    )
    return None if worst <= tolerance else float(worst)


def check_rig_matches(rig_cam: Camera, cal: Calibration, where: Path, source: Path) -> None:
    """Refuse (one line naming both) a recording whose colour camera is not the rig's."""
    off = mismatch(rig_cam, cal.colour)
    if off is None:
        return
    how = "another size" if np.isinf(off) else f"{off:.1%} apart, more than {K_TOLERANCE:.0%}"
    raise UserError(
        f"the recording's camera ({describe(cal.colour)}, from {source.name}'s "
        f"{cal.origin}) is not rig camera {rig_cam.name}'s ({describe(rig_cam)}): {how}; "
        "ingest it into a dataset of that camera",
        path=where,
    )
