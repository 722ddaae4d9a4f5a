"""Where a recorded sequence comes from (:func:`open_recording`): whatever wrote it, the
reader of :mod:`annotator.ingest.readers` that recognises it opens it, and the calibration it
carries is checked before anything is written.

The readers: a **ROS bag** (``.bag``, a ROS 2 bag folder, ``.mcap``, ``.db3``;
:mod:`.readers.rosbag`), an **Azure Kinect** ``.mkv`` carrying ``calibration.json``
(:mod:`.readers.kinect`) and a **Record3D** ``.r3d`` (:mod:`.readers.record3d`), each with
its cameras' calibration and depth; a plain **video** (``.mp4 .avi .mkv .mov .webm``,
:mod:`.readers.video`), whose frame ``i``'s time is its presentation time and which has no
depth; a **folder** of colour and depth images as capture tools write them
(:mod:`.readers.folder`).
"""

from __future__ import annotations

from pathlib import Path

from annotator.ingest.readers import PAIR_TOLERANCE_S, OpenOptions, open_with_reader
from annotator.ingest.recording import Recording, check_calibration

__all__ = ["PAIR_TOLERANCE_S", "open_recording"]


def open_recording(
    path: str | Path,
    *,
    stream: str | None = None,
    depth: bool = True,
    tolerance_s: float = PAIR_TOLERANCE_S,
    fps: float | None = None,
    color_topic: str | None = None,
    depth_topic: str | None = None,
    depth_unit_mm: float | None = None,
) -> Recording:
    """The recording at ``path``, whatever wrote it (module docstring; the arguments are
    :class:`~annotator.ingest.readers.OpenOptions`'s).

    Raises:
        UserError: one line naming the file, for anything that cannot be read, and for a
            calibration no camera has (zero or non-finite focal lengths, no size).
    """
    path = Path(path)
    options = OpenOptions(stream, depth, tolerance_s, fps, color_topic, depth_topic, depth_unit_mm)
    rec = open_with_reader(path, options)
    if rec.calibration is not None:
        check_calibration(rec.calibration, path)
    return rec
