"""Where a recorded sequence comes from: a video file, or a folder of colour (and depth)
images as capture tools write them.

A **video** (``.mp4 .avi .mkv .mov .webm``) is read with OpenCV's ``VideoCapture``; frame
``i``'s time is the decoder's position (``CAP_PROP_POS_MSEC``), or ``i / fps`` when the
container gives none. A video has no depth.

A **folder** holds image files (``.png .jpg .jpeg .tif .tiff .bmp``), directly or in
sub-folders (``color/``, ``depth/``...; one level). Each file's name is read as
``<stream><kind><number>``:

- *kind*: ``depth`` in the name or its folder's name makes it a depth image; ``color``,
  ``colour``, ``rgb`` or no kind at all a colour image; ``infrared``/``ir``/``confidence``
  images are other streams and left out.
- *number*, the last number of the name: realsense-viewer's snapshots
  (``<device>_Color_<ms since the epoch>.png``), rs-convert's (``<prefix>_Color_<n>.png``),
  ROS image_saver's (``frame0000.jpg``, ``left0000.png``) and bag exports
  (``<sec>.<nsec>.png``). A number of 12 or more integer digits is a time in milliseconds
  (RealSense), one with a fraction or of 9 to 11 digits a time in seconds (ROS), a shorter
  integer a frame index (no time, unless ``fps`` is given).
- *stream*: what is left (``left``, ``frame``, the device's serial...); colour images of
  several streams are told apart by it (``--stream``, or the stream named like the camera).

A depth image is the partner of the colour image with the same number; failing that, of the
one nearest in time within ``tolerance_s``. Frames are in time order (number order without
times).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from annotator.errors import UserError
from annotator.io.images import native_stderr_hidden, read_image

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".webm")
#: Default pairing tolerance between a colour image and its depth image (s).
PAIR_TOLERANCE_S = 0.02

_NUMBER = re.compile(r"(\d+(?:\.\d+)?)(?!.*\d)")
_KIND = re.compile(r"(depth|colou?r|rgb|infrared|confidence|(?<![a-z])ir(?![a-z]))", re.I)
_OTHER_KINDS = ("infrared", "confidence", "ir")


@dataclass(frozen=True)
class SourceFrame:
    """One frame of a source: its position in the source (``index``), what it was read
    from (``label``: the colour file relative to the source folder, or the video's frame
    index), its time (s, None when the source does not tell) and its depth partner."""

    index: int
    label: str | int
    time_s: float | None
    colour: Path | None = None
    depth: Path | None = None


@dataclass(frozen=True)
class _Named:
    """An image file's name read as stream, kind, number (see the module docstring)."""

    path: Path
    stream: str
    depth: bool
    key: str  # the number as written
    number: float | None
    time_s: float | None


class Source:
    """A video or an image folder: :attr:`frames` (in order) and their pixels
    (:meth:`read`, frames in increasing order for a video)."""

    def __init__(self, path: Path, frames: list[SourceFrame], *, video: bool) -> None:
        self.path = path
        self.frames = frames
        self.video = video
        self.has_depth = any(f.depth is not None for f in frames)

    def describe(self) -> str:
        """``video`` or ``image folder`` (what the summary says)."""
        return "video" if self.video else "image folder"

    def read(self, frames: list[SourceFrame]) -> Iterator[tuple[SourceFrame, np.ndarray]]:
        """The colour image of each of ``frames`` (as stored: BGR or grey, 8/16-bit)."""
        if not self.video:
            for f in frames:
                assert f.colour is not None
                yield f, read_image(f.colour)
            return
        yield from _video_frames(self.path, frames)


def open_source(
    path: str | Path,
    *,
    stream: str | None = None,
    depth: bool = True,
    tolerance_s: float = PAIR_TOLERANCE_S,
    fps: float | None = None,
) -> Source:
    """The frames of a video file or an image folder (module docstring).

    Args:
        path: The video file or the folder.
        stream: The colour stream to take when a folder holds several (``left``...).
        depth: Pair the folder's depth images with the colour ones (False: leave them out).
        tolerance_s: How far apart in time a colour image and its depth image may be.
        fps: The frame rate of a folder whose names are frame indices (their times).

    Raises:
        UserError: (one line naming the file or folder) an unreadable video, a folder
            without images, several colour streams and none chosen, a colour image without
            a depth partner when the folder has depth images.
    """
    path = Path(path)
    if path.is_file():
        if path.suffix.lower() not in VIDEO_SUFFIXES:
            raise UserError(
                f"is not a video ({', '.join(VIDEO_SUFFIXES)}) nor a folder of images", path=path
            )
        return Source(path, _video_index(path), video=True)
    if not path.is_dir():
        raise UserError("no such video file or image folder", path=path)
    return Source(path, _folder_frames(path, stream, depth, tolerance_s, fps), video=False)


def _open_video(path: Path) -> Any:
    """An opened ``cv2.VideoCapture`` of the file (UserError if it is not a video)."""
    import cv2

    with native_stderr_hidden():  # FFmpeg's own lines about a broken file
        cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise UserError("not a readable video", path=path)
    return cap


def _video_index(path: Path) -> list[SourceFrame]:
    """Every frame of the video with its time, by decoding it once (containers' frame
    counts can be wrong)."""
    import cv2

    cap = _open_video(path)
    fps = cap.get(cv2.CAP_PROP_FPS) or 0.0
    frames: list[SourceFrame] = []
    try:
        while cap.grab():
            i = len(frames)
            ms = cap.get(cv2.CAP_PROP_POS_MSEC)
            t = ms / 1000.0 if (ms > 0 or i == 0) else (i / fps if fps > 0 else None)
            frames.append(SourceFrame(i, i, t))
    finally:
        cap.release()
    if not frames:
        raise UserError("not a readable video (no frame could be decoded)", path=path)
    return frames


def _video_frames(
    path: Path, frames: list[SourceFrame]
) -> Iterator[tuple[SourceFrame, np.ndarray]]:
    """Decode the video once, yielding the wanted frames (increasing indices)."""
    cap = _open_video(path)
    try:
        at = 0
        for f in frames:
            while at < f.index:
                if not cap.grab():
                    raise UserError(f"cannot read frame {f.index} of the video", path=path)
                at += 1
            ok, img = cap.read()
            if not ok or img is None:
                raise UserError(f"cannot read frame {f.index} of the video", path=path)
            at += 1
            yield f, img
    finally:
        cap.release()


def read_name(path: Path, *, in_depth_folder: bool = False) -> tuple[str, str, str, float | None]:
    """``(stream, kind, number, time_s)`` of an image file's name: kind ``depth``,
    ``colour`` or ``other``; the number as written ('' if none); its time in seconds when it
    is one (module docstring).

    >>> read_name(Path("cam_Color_1596567890123.456.png"))
    ('cam', 'colour', '1596567890123.456', 1596567890.123456)
    >>> read_name(Path("left0012.png"))[:3], read_name(Path("1650000000.250000000.png"))[3]
    (('left', 'colour', '0012'), 1650000000.25)
    """
    stem = path.stem
    match = _NUMBER.search(stem)
    key = match.group(1) if match else ""
    rest = stem[: match.start()] if match else stem
    kinds = [k.lower() for k in _KIND.findall(rest)]
    if "depth" in kinds or in_depth_folder:
        kind = "depth"
    elif any(k in _OTHER_KINDS for k in kinds):
        kind = "other"
    else:
        kind = "colour"
    stream = _KIND.sub("", rest).rstrip("_-. ")
    if key:
        whole = key.split(".")[0]
        if len(whole) >= 12:
            return stream, kind, key, float(key) / 1000.0
        if "." in key or len(whole) >= 9:
            return stream, kind, key, float(key)
    return stream, kind, key, None


def _folder_files(root: Path) -> list[tuple[Path, bool]]:
    """Image files in ``root`` and in its sub-folders (one level), each with whether its
    folder's name says depth."""
    out: list[tuple[Path, bool]] = []
    for entry in sorted(root.iterdir()):
        if entry.name.startswith("."):
            continue
        if entry.is_dir():
            depth = "depth" in entry.name.lower()
            out += [
                (p, depth)
                for p in sorted(entry.iterdir())
                if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
            ]
        elif entry.is_file() and entry.suffix.lower() in IMAGE_SUFFIXES:
            out.append((entry, False))
    return out


def _folder_frames(
    root: Path, stream: str | None, with_depth: bool, tolerance_s: float, fps: float | None
) -> list[SourceFrame]:
    named = []
    for p, depth_folder in _folder_files(root):
        s, kind, key, t = read_name(p, in_depth_folder=depth_folder)
        if kind == "other":
            continue
        number = float(key) if key else None
        if t is None and number is not None and fps:
            t = number / fps
        named.append(_Named(p, s, kind == "depth", key, number, t))
    colour = [n for n in named if not n.depth]
    if not colour:
        raise UserError(
            f"no colour images found ({', '.join(IMAGE_SUFFIXES)}, directly or one folder down)",
            path=root,
        )
    colour = _one_stream(root, colour, stream)
    colour.sort(key=_order)
    depth = [n for n in named if n.depth] if with_depth else []
    by_key = {n.key: n for n in depth if n.key}
    frames = []
    for i, c in enumerate(colour):
        partner = None
        if depth:
            partner = by_key.get(c.key) if c.key else None
            if partner is None:
                partner = _nearest(c, depth, tolerance_s)
            if partner is None:
                raise UserError(
                    "has no depth partner (the same number, or a depth image within "
                    f"{tolerance_s * 1000:g} ms); give --tolerance-ms or --no-depth",
                    path=c.path,
                )
        label = c.path.relative_to(root).as_posix()
        frames.append(SourceFrame(i, label, c.time_s, c.path, partner.path if partner else None))
    return frames


def _one_stream(root: Path, colour: list[_Named], stream: str | None) -> list[_Named]:
    streams = sorted({c.stream for c in colour})
    if len(streams) == 1:
        return colour
    if stream is not None and stream in streams:
        return [c for c in colour if c.stream == stream]
    shown = ", ".join(repr(s) for s in streams)
    raise UserError(
        f"holds colour images of several streams ({shown}): choose one with --stream (or "
        "name the rig camera like it), or give a folder of one stream",
        path=root,
    )


def _order(n: _Named) -> tuple:
    """Time order; number order without times; name order without numbers."""
    if n.time_s is not None:
        return (0, n.time_s, n.path.name)
    if n.number is not None:
        return (1, n.number, n.path.name)
    return (2, 0.0, n.path.name)


def _nearest(c: _Named, depth: list[_Named], tolerance_s: float) -> _Named | None:
    """The depth image nearest in time to ``c`` within ``tolerance_s`` (None if none or no
    times)."""
    if c.time_s is None:
        return None
    timed = [d for d in depth if d.time_s is not None]
    if not timed:
        return None
    best = min(timed, key=lambda d: (abs(d.time_s - c.time_s), d.path.name))  # type: ignore[operator]
    assert best.time_s is not None
    return best if abs(best.time_s - c.time_s) <= tolerance_s else None
