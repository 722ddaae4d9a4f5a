"""Synthetic calibration captures as videos: one lossless video per camera (FFV1), the
second camera's video one frame late, with timestamps files that pair the frames
(:func:`write_videos`, for ``annotator synth --calibration --video``)."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np

from annotator.calibration.captures import TIMESTAMPS_SUFFIX
from annotator.errors import UserError
from annotator.io.atomic import write_text
from annotator.synthesis.board_render import BACKGROUND

#: Frame rate written into the synthetic videos (and their timestamps).
VIDEO_FPS = 10.0


def write_videos(root: Path, cameras: list[str]) -> list[Path]:
    """Replace each camera's shot folder under ``root`` by a lossless video
    ``<camera>.mkv`` (FFV1, one frame per shot in shot order) and a timestamps file. Every
    camera after the first starts one frame (a frame without the board) earlier, so that only
    the timestamps pair the frames right."""
    out = []
    for k, name in enumerate(cameras):
        folder = root / name
        frames: list[np.ndarray] = []
        for p in sorted(folder.glob("*.png")):
            img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
            assert img is not None, p  # a shot this module has just written
            frames.append(img)
        h, w = frames[0].shape
        lead = [np.full((h, w), int(255 * BACKGROUND), np.uint8)] if k > 0 else []
        path = root / f"{name}.mkv"
        fourcc = cv2.VideoWriter_fourcc(*"FFV1")  # type: ignore[attr-defined]  # cv2 has it, its stubs not
        writer = cv2.VideoWriter(str(path), fourcc, VIDEO_FPS, (w, h), isColor=False)
        if not writer.isOpened():
            raise UserError("OpenCV cannot write FFV1 videos here", path=path)
        for img in lead + frames:
            writer.write(img)
        writer.release()
        # A camera's clock runs a little off the first's: 3 ms, well within half a frame.
        times = (np.arange(len(lead) + len(frames)) - len(lead)) / VIDEO_FPS + 0.003 * k
        write_text(root / f"{name}{TIMESTAMPS_SUFFIX}", "".join(f"{t:.6f}\n" for t in times))
        shutil.rmtree(folder)
        out.append(path)
    return out
