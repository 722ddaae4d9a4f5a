"""A folder of colour (and depth) images as capture tools write them.

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
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from annotator.errors import UserError
from annotator.ingest.readers import PAIR_TOLERANCE_S, OpenOptions, RecorderReader
from annotator.ingest.recording import Decoded, Recording
from annotator.io.images import read_image

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")

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
    """An image folder: :attr:`frames` (in order), each colour image with its depth image."""

    def __init__(self, path: Path, frames: list[SourceFrame]) -> None:
        self.path = path
        self.frames = frames
        self.has_depth = any(f.depth is not None for f in frames)


@dataclass
class _FolderRecording(Recording):
    """An image folder as a recording: colour images read as stored, depth images (uint16,
    ``unit_mm`` mm a unit, 0 = none) on the colour grid."""

    source: Source | None = None
    unit_mm: float = 1.0

    def decode(self, indices: Sequence[int], *, depth: bool) -> Iterator[Decoded]:
        assert self.source is not None
        for i in indices:
            f = self.source.frames[i]
            assert f.colour is not None
            img = read_image(f.colour)
            mm = None
            if depth and f.depth is not None:
                mm = read_depth_units(f.depth) * self.unit_mm
            yield Decoded(i, img, mm)

    def depth_unit(self) -> float:
        return self.unit_mm

    def depth_label(self, i: int) -> str | int | None:
        partner = self.depth_for[i]
        if self.source is None or partner is None:
            return partner
        f = self.source.frames[partner]
        return f.depth.relative_to(self.path).as_posix() if f.depth is not None else None

    def depth_where(self, i: int) -> Path | str:
        f = self.source.frames[i] if self.source is not None else None
        return Path(f.depth) if f is not None and f.depth is not None else super().depth_where(i)


def read_depth_units(path: Path) -> np.ndarray:
    """A depth image's units as float (NaN = no measurement): uint16, single channel."""
    raw = read_image(path)
    if raw.ndim == 3 and raw.shape[2] == 1:
        raw = raw[..., 0]
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise UserError(
            f"depth image must be single-channel uint16, got {raw.dtype} {raw.shape}", path=path
        )
    units = raw.astype(np.float64)
    units[raw == 0] = np.nan
    return units


def open_source(
    path: str | Path,
    *,
    stream: str | None = None,
    depth: bool = True,
    tolerance_s: float = PAIR_TOLERANCE_S,
    fps: float | None = None,
) -> Source:
    """The frames of an image folder (module docstring).

    Args:
        path: The folder.
        stream: The colour stream to take when a folder holds several (``left``...).
        depth: Pair the folder's depth images with the colour ones (False: leave them out).
        tolerance_s: How far apart in time a colour image and its depth image may be.
        fps: The frame rate of a folder whose names are frame indices (their times).

    Raises:
        UserError: (one line naming the folder or file) a folder without images, several
            colour streams and none chosen, a colour image without a depth partner when the
            folder has depth images.
    """
    path = Path(path)
    if not path.is_dir():
        raise UserError("no such video file or image folder", path=path)
    return Source(path, _folder_frames(path, stream, depth, tolerance_s, fps))


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


def _open(path: Path, options: OpenOptions) -> Recording:
    src = open_source(
        path,
        stream=options.stream,
        depth=options.depth,
        tolerance_s=options.tolerance_s,
        fps=options.fps,
    )
    return _FolderRecording(
        path=path,
        kind="image folder",
        times=[f.time_s for f in src.frames],
        labels=[f.label for f in src.frames],
        depth_for=[i if f.depth is not None else None for i, f in enumerate(src.frames)],
        streams={},
        source=src,
        unit_mm=1.0 if options.depth_unit_mm is None else options.depth_unit_mm,
    )


READERS = (
    RecorderReader("a folder of images", (), lambda path, _: path.is_dir(), _open, order=90),
)
