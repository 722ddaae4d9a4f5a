"""The captures folder: one sub-folder of images per camera, one image per camera per shot;
or one video per camera.

Layout::

    CAPTURES/
      board.yaml                 # optional: the board (annotator.calibration.board)
      <camera>/<shot>.png        # .png, .jpg, .jpeg, .tif, .tiff or .bmp; 8/16-bit, grey or colour
      calibration_report/        # written by `annotator calibrate` (ignored when reading)

The shots of all cameras are taken together (synchronised) and share their names:
``left/017.png`` and ``right/017.png`` are the same board pose. Every camera must have an
image of every shot, all images of a camera the same size. Problems are reported as one
:class:`~annotator.errors.UserError` naming the offending file or folder.

Videos instead (no camera folders)::

    CAPTURES/
      cam_0.mp4, cam_1.mp4 ...   # .mp4 .avi .mkv .mov: one video per camera, named as the camera
      cam_0.timestamps.txt ...   # optional, for every camera or none: one time (s) per frame

Every ``stride``-th frame of the first camera is a shot (named ``f<frame>``). Without
timestamps, the other cameras' frames of the same index are its partners (videos started
together); with them, each camera's frame nearest in time, if within half that camera's
median frame interval (else the shot is left out and reported as unpaired).

A session as caliscope records it (:mod:`.caliscope`: ``charuco.toml``,
``calibration/extrinsic/cam_N.mp4`` and ``timestamps.csv``) is read as it is: every
``stride``-th sync index that every camera has a frame of is a shot (named ``s<sync
index>``; the default stride there is 1, the recorder having already thinned the frames),
and each frame keeps its own time.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from annotator.calibration import caliscope
from annotator.errors import UserError
from annotator.io.images import read_image

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov")
TIMESTAMPS_SUFFIX = ".timestamps.txt"
#: Default stride between the frames of a video that become shots.
DEFAULT_STRIDE = 10
REPORT_FOLDER = "calibration_report"


@dataclass(frozen=True)
class Captures:
    """A checked captures folder.

    Attributes:
        root: The folder.
        cameras: Camera names (sub-folder names), in rig order.
        shots: Shot names (file stems), sorted.
        files: ``(camera, shot) -> image path`` (image captures).
        videos: ``camera -> video path`` (video captures).
        frames: ``(camera, shot) -> frame index`` in its video (video captures).
        pairing: How the videos' frames were paired (``frame index``, ``timestamps`` or
            ``sync index``).
        unpaired: Frames of the first camera left out: no partner in some other video.
        times: ``(camera, shot) -> time`` (s) of its frame, when the recording says (video
            captures with timestamps).
        board_file: A board description the recording came with (caliscope's
            ``charuco.toml``), or None.
    """

    root: Path
    cameras: tuple[str, ...]
    shots: tuple[str, ...]
    files: Mapping[tuple[str, str], Path]
    videos: Mapping[str, Path] = field(default_factory=dict)
    frames: Mapping[tuple[str, str], int] = field(default_factory=dict)
    pairing: str = ""
    unpaired: tuple[int, ...] = ()
    times: Mapping[tuple[str, str], float] = field(default_factory=dict)
    board_file: Path | None = None

    def folder(self, camera: str) -> Path:
        """The folder of a camera's images (its video, for video captures)."""
        return self.videos.get(camera, self.root / camera)


def find_captures(
    root: str | Path,
    *,
    cameras: Sequence[str] | None = None,
    ignore: Sequence[Path] = (),
    stride: int | None = None,
) -> Captures:
    """List and check a captures folder.

    Args:
        root: The captures folder.
        cameras: Camera folders to use, in rig order; default: every sub-folder, sorted.
        ignore: Sub-folders that are not cameras (a report folder inside ``root``), besides
            ``calibration_report`` and hidden folders.
        stride: For video captures: every ``stride``-th frame is a shot (default 10; a
            caliscope session's sync indices: 1).

    Raises:
        UserError: a missing folder, no camera folders, images outside camera folders, a
            camera folder without images, two images for one shot, or a shot that some camera
            has no image of.
    """
    root = Path(root)
    if not root.is_dir():
        raise UserError("captures folder does not exist", path=root)
    session = caliscope.find_session(root)
    if session is not None:
        return find_session_captures(root, session, cameras=cameras, stride=stride or 1)
    folders = _camera_folders(root, ignore)
    videos = _files_with(root, VIDEO_SUFFIXES)
    if videos and not folders:
        return find_video_captures(root, videos, cameras=cameras, stride=stride or DEFAULT_STRIDE)
    _check_no_loose_images(root, _files_with(root, IMAGE_SUFFIXES), folders)
    names = _camera_names(root, folders, cameras)
    files = _shot_images(root, names)
    return Captures(root, tuple(names), tuple(_common_shots(root, names, files)), files)


def find_rig_captures(
    root: str | Path,
    *,
    cameras: Sequence[str] | None,
    rig_cameras: Sequence[str],
    ignore: Sequence[Path] = (),
    stride: int | None = None,
    rig_source: Path | None = None,
) -> Captures:
    """:func:`find_captures` for a rig that exists already (``rig_cameras``, read from
    ``rig_source``; empty: none): the captures must be of its cameras, and keep its camera
    order unless ``cameras`` chooses one.

    Raises:
        UserError: besides :func:`find_captures`' errors, captures of other cameras.
    """
    captures = find_captures(root, cameras=cameras, ignore=ignore, stride=stride)
    if not rig_cameras:
        return captures
    if sorted(rig_cameras) != sorted(captures.cameras):
        raise UserError(
            f"its rig has cameras {', '.join(rig_cameras)} but the captures in "
            f"{root} have {', '.join(captures.cameras)}: name the capture folders after the "
            "rig's cameras (or choose them with --cameras)",
            path=rig_source,
        )
    if cameras is None:
        return find_captures(root, cameras=rig_cameras, ignore=ignore, stride=stride)
    return captures


def _camera_folders(root: Path, ignore: Sequence[Path]) -> list[Path]:
    """The sub-folders that may be cameras: not hidden, not a report folder."""
    skip = {p.resolve() for p in ignore}
    return sorted(
        p
        for p in root.iterdir()
        if p.is_dir()
        and not p.name.startswith(".")
        and p.name != REPORT_FOLDER
        and p.resolve() not in skip
    )


def _files_with(root: Path, suffixes: Sequence[str]) -> list[Path]:
    """The files directly in ``root`` with one of ``suffixes`` (any case), sorted."""
    return [p for p in sorted(root.iterdir()) if p.is_file() and p.suffix.lower() in suffixes]


def _check_no_loose_images(root: Path, loose: list[Path], folders: list[Path]) -> None:
    """Images belong in camera folders; one outside them is an error (two wordings: no
    camera folders at all is the likelier mistake)."""
    if loose and not folders:
        raise UserError(
            f"{len(loose)} images lie directly in the captures folder: put each camera's images "
            "in a folder named after the camera (CAPTURES/<camera>/<shot>.png)",
            path=root,
        )
    if loose:
        raise UserError(
            "image outside the camera folders (expected CAPTURES/<camera>/<shot>.png)",
            path=loose[0],
        )


def _camera_names(root: Path, folders: list[Path], cameras: Sequence[str] | None) -> list[str]:
    """The cameras: the ones asked for (each must have a folder), else every folder."""
    if cameras is None:
        names = [p.name for p in folders]
        if not names:
            raise UserError("no camera folders (expected CAPTURES/<camera>/<shot>.png)", path=root)
    else:
        names = list(cameras)
        for name in names:
            if not (root / name).is_dir():
                raise UserError(f"no folder for camera {name!r}", path=root / name)
    if len(set(names)) != len(names):
        raise UserError(f"a camera is named twice in {', '.join(names)}", path=root)
    return names


def _shot_images(root: Path, names: list[str]) -> dict[tuple[str, str], Path]:
    """(camera, shot) -> image, for every camera folder."""
    files: dict[tuple[str, str], Path] = {}
    for name in names:
        files.update({(name, s): p for s, p in _camera_images(root / name).items()})
    return files


def _camera_images(folder: Path) -> dict[str, Path]:
    """shot -> image of one camera folder; at least one, and one per shot."""
    stems: dict[str, Path] = {}
    for p in sorted(folder.iterdir()):
        if not p.is_file() or p.name.startswith(".") or p.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        if p.stem in stems:
            raise UserError(f"two images of shot {p.stem!r} ({stems[p.stem].name})", path=p)
        stems[p.stem] = p
    if not stems:
        raise UserError(f"camera folder has no images ({', '.join(IMAGE_SUFFIXES)})", path=folder)
    return stems


def _common_shots(root: Path, names: list[str], files: dict[tuple[str, str], Path]) -> list[str]:
    """Every shot, sorted; an error naming the first image some camera lacks."""
    shots_of = {name: {s for (n, s) in files if n == name} for name in names}
    every = sorted(set().union(*shots_of.values()))
    for name in names:
        missing = [s for s in every if s not in shots_of[name]]
        if missing:
            s = missing[0]
            has = next(n for n in names if s in shots_of[n])
            more = f" ({len(missing)} shots in all)" if len(missing) > 1 else ""
            raise UserError(
                f"missing: shot {s!r} has an image from camera {has} but none from camera "
                f"{name}{more}; every camera needs one image of every shot",
                path=root / name / f"{s}{files[(has, s)].suffix}",
            )
    return every


@dataclass(frozen=True)
class _Pairing:
    """The shots of videos: their names, each camera's frame of each, and the frames of the
    first camera that some camera had no partner for."""

    shots: list[str]
    frames: dict[tuple[str, str], int]
    unpaired: list[int]


def find_video_captures(
    root: Path, videos: Sequence[Path], *, cameras: Sequence[str] | None, stride: int
) -> Captures:
    """Video captures (see the module docstring): the shots and each camera's frame of each."""
    if stride < 1:
        raise UserError(f"the frame stride must be at least 1, not {stride}")
    by_name = _videos_by_camera(videos)
    names = list(cameras) if cameras is not None else sorted(by_name)
    for name in names:
        if name not in by_name:
            raise UserError(
                f"no video for camera {name!r} ({', '.join(VIDEO_SUFFIXES)})", path=root / name
            )
    counts = {name: _frame_count(by_name[name]) for name in names}
    stamps = {name: _timestamps(by_name[name], counts[name]) for name in names}
    timed = _check_timestamps(names, stamps, by_name)
    pairing = _pair_frames(names, counts, stamps, stride)
    if not pairing.shots:
        raise UserError(
            f"no frame of camera {names[0]} has a partner in every other video "
            f"({'timestamps' if timed else 'frame index'}; frames: "
            + ", ".join(f"{n} {counts[n]}" for n in names)
            + ")",
            path=root,
        )
    return Captures(
        root,
        tuple(names),
        tuple(pairing.shots),
        {},
        videos={n: by_name[n] for n in names},
        frames=pairing.frames,
        pairing="timestamps" if timed else "frame index",
        unpaired=tuple(pairing.unpaired),
        times={
            (n, shot): float(t[f])
            for (n, shot), f in pairing.frames.items()
            if (t := stamps[n]) is not None
        },
    )


def _videos_by_camera(videos: Sequence[Path]) -> dict[str, Path]:
    """camera -> video, the camera named by the file's stem; one video per camera."""
    by_name: dict[str, Path] = {}
    for p in videos:
        if p.stem in by_name:
            raise UserError(f"two videos of camera {p.stem!r} ({by_name[p.stem].name})", path=p)
        by_name[p.stem] = p
    return by_name


def _check_timestamps(
    names: list[str], stamps: dict[str, np.ndarray | None], by_name: dict[str, Path]
) -> bool:
    """Whether the videos have timestamps: every one of them, or none (else an error)."""
    have = [n for n in names if stamps[n] is not None]
    if have and len(have) != len(names):
        lacking = next(n for n in names if stamps[n] is None)
        raise UserError(
            f"timestamps are given for camera {have[0]} but not for camera {lacking}: give a "
            f"{TIMESTAMPS_SUFFIX} file for every video or for none",
            path=by_name[lacking].with_name(lacking + TIMESTAMPS_SUFFIX),
        )
    return bool(have)


def _pair_frames(
    names: list[str],
    counts: dict[str, int],
    stamps: dict[str, np.ndarray | None],
    stride: int,
) -> _Pairing:
    """Every ``stride``-th frame of the first camera with its partner in every other video."""
    ref = names[0]
    pairing = _Pairing([], {}, [])
    digits = max(4, len(str(counts[ref])))
    for f in range(0, counts[ref], stride):
        partner = {ref: f}
        for name in names[1:]:
            g = _partner(f, stamps[ref], stamps[name], counts[name])
            if g is None:
                break
            partner[name] = g
        if len(partner) < len(names):
            pairing.unpaired.append(f)
            continue
        shot = f"f{f:0{digits}d}"
        pairing.shots.append(shot)
        pairing.frames.update({(name, shot): g for name, g in partner.items()})
    return pairing


def find_session_captures(
    root: Path,
    session: caliscope.Session,
    *,
    cameras: Sequence[str] | None,
    stride: int,
) -> Captures:
    """A caliscope session (:mod:`.caliscope`): every ``stride``-th sync index that every
    camera has a frame of is a shot, each frame with its own time."""
    if stride < 1:
        raise UserError(f"the frame stride must be at least 1, not {stride}")
    by_name = _videos_by_camera(_files_with(session.videos, VIDEO_SUFFIXES))
    listed = caliscope.read_frame_times(session.timestamps)
    names = list(cameras) if cameras is not None else sorted(by_name, key=_camera_number)
    for name in names:
        if name not in by_name:
            raise UserError(
                f"no video for camera {name!r} ({', '.join(VIDEO_SUFFIXES)})",
                path=session.videos / name,
            )
        if name not in listed:
            raise UserError(f"no frame of camera {name} is listed", path=session.timestamps)
    rows = {n: listed[n] for n in names}
    for n in names:
        count = _frame_count(by_name[n])
        if count != len(rows[n]):
            raise UserError(
                f"lists {len(rows[n])} frames of camera {n} but its video has {count}: the "
                "rows and the frames no longer match (an edited or cut file?)",
                path=session.timestamps,
            )
    if any(sync is None for n in names for sync, _ in rows[n]):
        return _session_paired_by_time(root, session, names, by_name, rows, stride)
    index = {n: {int(sync or 0): k for k, (sync, _) in enumerate(rows[n])} for n in names}
    common = sorted(set.intersection(*(set(index[n]) for n in names)))[::stride]
    if not common:
        raise UserError(
            f"no sync_index has a frame of every camera ({', '.join(names)})",
            path=session.timestamps,
        )
    digits = max(4, len(str(common[-1])))
    frames: dict[tuple[str, str], int] = {}
    times: dict[tuple[str, str], float] = {}
    shots = []
    for sync in common:
        shot = f"s{sync:0{digits}d}"
        shots.append(shot)
        for n in names:
            frames[(n, shot)] = index[n][sync]
            times[(n, shot)] = rows[n][index[n][sync]][1]
    every = set.intersection(*(set(index[n]) for n in names))
    ref = names[0]
    return Captures(
        root,
        tuple(names),
        tuple(shots),
        {},
        videos={n: by_name[n] for n in names},
        frames=frames,
        pairing="sync index",
        unpaired=tuple(k for sync, k in index[ref].items() if sync not in every),
        times=times,
        board_file=session.board,
    )


def _session_paired_by_time(
    root: Path,
    session: caliscope.Session,
    names: list[str],
    by_name: dict[str, Path],
    rows: dict[str, list[tuple[int | None, float]]],
    stride: int,
) -> Captures:
    """A caliscope session whose timestamps.csv has no sync indices (caliscope 0.11 and
    later): every ``stride``-th frame of the first camera, paired by time."""
    stamps: dict[str, np.ndarray | None] = {
        n: np.array([t for _, t in rows[n]], np.float64) for n in names
    }
    pairing = _pair_frames(names, {n: len(rows[n]) for n in names}, stamps, stride)
    if not pairing.shots:
        raise UserError(
            f"no frame of camera {names[0]} has a partner in time in every other video",
            path=session.timestamps,
        )
    return Captures(
        root,
        tuple(names),
        tuple(pairing.shots),
        {},
        videos={n: by_name[n] for n in names},
        frames=pairing.frames,
        pairing="timestamps",
        unpaired=tuple(pairing.unpaired),
        times={(n, shot): rows[n][f][1] for (n, shot), f in pairing.frames.items()},
        board_file=session.board,
    )


def _camera_number(name: str) -> tuple[int, str]:
    """Sort key of caliscope's camera names: ``cam_2`` before ``cam_10``."""
    tail = name.rpartition("_")[2]
    return (int(tail), name) if tail.isdigit() else (1 << 30, name)


def _frame_count(path: Path) -> int:
    """Frames in a video, counted by reading it (the container's count can be wrong)."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise UserError("not a readable video", path=path)
    n = 0
    while cap.grab():
        n += 1
    cap.release()
    if n == 0:
        raise UserError("the video has no readable frame", path=path)
    return n


def _timestamps(video: Path, count: int) -> np.ndarray | None:
    """The frame times of a video's timestamps file (s), or None without one."""
    path = video.with_name(video.stem + TIMESTAMPS_SUFFIX)
    if not path.is_file():
        return None
    from annotator.io.documents import read_text

    try:
        t = np.array([float(x) for x in read_text(path).split()], np.float64)
    except ValueError:
        raise UserError("timestamps must be numbers (seconds), one per frame", path=path) from None
    if len(t) < count:
        raise UserError(f"{len(t)} timestamps for the video's {count} frames", path=path)
    if np.any(np.diff(t[:count]) <= 0) or not np.all(np.isfinite(t)):
        raise UserError("timestamps must increase from frame to frame", path=path)
    return t[:count]


def _partner(f: int, ref: np.ndarray | None, other: np.ndarray | None, count: int) -> int | None:
    """The frame of another video taken with frame ``f`` of the first one."""
    if ref is None or other is None:
        return f if f < count else None
    g = int(np.argmin(np.abs(other - ref[f])))
    period = float(np.median(np.diff(other))) if len(other) > 1 else np.inf
    return g if abs(other[g] - ref[f]) <= 0.5 * period else None


def read_images(
    captures: Captures,
    *,
    expected_sizes: Mapping[str, tuple[int, int]] | None = None,
    expected_source: Path | None = None,
    progress: Callable[[Iterator], Iterator] | None = None,
) -> Iterator[tuple[int, int, np.ndarray]]:
    """Yield ``(camera index, shot index, image)`` shot by shot, checking image sizes.

    Args:
        captures: The folder.
        expected_sizes: Sizes the images must have, per camera (from an existing rig).
        expected_source: The file those sizes come from, for the message.
        progress: Wraps the iteration (a progress bar).

    Raises:
        UserError: an unreadable image; an image whose size differs from the camera's other
            images or from ``expected_sizes``.
    """
    sizes: dict[str, tuple[tuple[int, int], Path]] = {}
    pairs = [(c, s) for s in range(len(captures.shots)) for c in range(len(captures.cameras))]
    it: Iterator = iter(pairs)
    if progress is not None:
        it = progress(it)
    frames = _VideoFrames(captures) if captures.videos else None
    for c, s in it:
        cam = captures.cameras[c]
        if frames is not None:
            path = captures.videos[cam]
            img = frames.read(cam, captures.frames[(cam, captures.shots[s])])
        else:
            path = captures.files[(cam, captures.shots[s])]
            img = read_image(path)
        size = (int(img.shape[1]), int(img.shape[0]))
        if cam not in sizes:
            want = (expected_sizes or {}).get(cam)
            if want is not None and tuple(want) != size:
                src = f" in {expected_source}" if expected_source else ""
                raise UserError(
                    f"image is {size[0]}x{size[1]} but camera {cam}{src} is {want[0]}x{want[1]}: "
                    "calibrate at the resolution of the scenes",
                    path=path,
                )
            sizes[cam] = (size, path)
        elif sizes[cam][0] != size:
            (w, h), first = sizes[cam]
            raise UserError(
                f"inconsistent image sizes: this image is {size[0]}x{size[1]}, camera {cam}'s "
                f"{first.name} is {w}x{h}",
                path=path,
            )
        yield c, s, img


class _VideoFrames:
    """Reads frames of the capture videos in increasing order, one decoder per video."""

    def __init__(self, captures: Captures) -> None:
        import cv2

        self._caps = {n: cv2.VideoCapture(str(p)) for n, p in captures.videos.items()}
        self._next = dict.fromkeys(captures.videos, 0)
        self._last: dict[str, tuple[int, np.ndarray]] = {}
        self._paths = captures.videos

    def read(self, camera: str, frame: int) -> np.ndarray:
        # Two shots may pair with one frame of a slower camera: the last frame is kept.
        last = self._last.get(camera)
        if last is not None and last[0] == frame:
            return last[1]
        cap = self._caps[camera]
        while self._next[camera] < frame:
            if not cap.grab():
                break
            self._next[camera] += 1
        ok, img = cap.read()
        if not ok or img is None or self._next[camera] != frame:
            raise UserError(f"cannot read frame {frame} of the video", path=self._paths[camera])
        self._next[camera] += 1
        self._last[camera] = (frame, img)
        return img
