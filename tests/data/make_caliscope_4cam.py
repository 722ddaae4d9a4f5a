"""Writes ``caliscope-4cam/`` beside this file: a trimmed copy of caliscope's four-webcam test
session (github.com/mprib/caliscope, tests/sessions/4_cam_recording), the sync indices
FIRST..LAST of its extrinsic videos (default 436..463: 28 frames, 4.7 s at 6 fps, every
camera seeing the board), re-encoded with x264 (CRF 23) to keep the copy small;
``timestamps.csv`` cut to the same rows, ``charuco.toml``, ``camera_array.toml`` (caliscope's
own calibration, a peer result) and the LICENSE copied as they are::

    python tests/data/make_caliscope_4cam.py SESSION [FIRST LAST]
"""

from __future__ import annotations

import csv
import shutil
import sys
from pathlib import Path

import av

OUT = Path(__file__).resolve().parent / "caliscope-4cam"
EXTRINSIC = Path("calibration") / "extrinsic"


def _trim_video(src: Path, dst: Path, frames: set[int]) -> None:
    """The given frames of ``src`` (0-based), re-encoded into ``dst``."""
    with av.open(str(src)) as inp, av.open(str(dst), "w") as out:
        stream = out.add_stream("libx264", rate=6)
        stream.width, stream.height, stream.pix_fmt = 1280, 720, "yuv420p"
        stream.options = {"crf": "23", "preset": "slow"}
        for k, frame in enumerate(inp.decode(video=0)):
            if k in frames:
                rgb = av.VideoFrame.from_ndarray(frame.to_ndarray(format="rgb24"), format="rgb24")
                for packet in stream.encode(rgb):
                    out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)


def main(session: Path, first: int = 436, last: int = 463) -> None:
    (OUT / EXTRINSIC).mkdir(parents=True, exist_ok=True)
    with open(session / EXTRINSIC / "timestamps.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    with open(OUT / EXTRINSIC / "timestamps.csv", "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(["sync_index", "cam_id", "frame_time"])
        for r in rows:
            if first <= int(r["sync_index"]) <= last:
                out.writerow([r["sync_index"], r["cam_id"], r["frame_time"]])
    for cam in sorted({r["cam_id"] for r in rows}):
        syncs = sorted(int(r["sync_index"]) for r in rows if r["cam_id"] == cam)
        keep = {k for k, s in enumerate(syncs) if first <= s <= last}
        name = f"cam_{cam}.mp4"
        _trim_video(session / EXTRINSIC / name, OUT / EXTRINSIC / name, keep)
    for name in ("LICENSE", "charuco.toml", "camera_array.toml"):
        shutil.copyfile(session / name, OUT / name)


if __name__ == "__main__":
    main(Path(sys.argv[1]), *(int(a) for a in sys.argv[2:4]))
