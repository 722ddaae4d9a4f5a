"""The captures folder: one sub-folder of images per camera, one image per camera per shot.

Layout::

    CAPTURES/
      board.yaml                 # optional: the board (annotator.calibration.board)
      <camera>/<shot>.png        # .png, .jpg, .jpeg, .tif, .tiff or .bmp; 8/16-bit, grey or colour
      calibration_report/        # written by `annotator calibrate` (ignored when reading)

The shots of all cameras are taken together (synchronised) and share their names:
``left/017.png`` and ``right/017.png`` are the same board pose. Every camera must have an
image of every shot, all images of a camera the same size. Problems are reported as one
:class:`~annotator.errors.UserError` naming the offending file or folder.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from annotator.errors import UserError
from annotator.io.images import read_image

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
REPORT_FOLDER = "calibration_report"


@dataclass(frozen=True)
class Captures:
    """A checked captures folder.

    Attributes:
        root: The folder.
        cameras: Camera names (sub-folder names), in rig order.
        shots: Shot names (file stems), sorted.
        files: ``(camera, shot) -> image path``.
    """

    root: Path
    cameras: tuple[str, ...]
    shots: tuple[str, ...]
    files: Mapping[tuple[str, str], Path]

    def folder(self, camera: str) -> Path:
        """The folder of a camera's images."""
        return self.root / camera


def find_captures(
    root: str | Path,
    *,
    cameras: Sequence[str] | None = None,
    ignore: Sequence[Path] = (),
) -> Captures:
    """List and check a captures folder.

    Args:
        root: The captures folder.
        cameras: Camera folders to use, in rig order; default: every sub-folder, sorted.
        ignore: Sub-folders that are not cameras (a report folder inside ``root``), besides
            ``calibration_report`` and hidden folders.

    Raises:
        UserError: a missing folder, no camera folders, images outside camera folders, a
            camera folder without images, two images for one shot, or a shot that some camera
            has no image of.
    """
    root = Path(root)
    if not root.is_dir():
        raise UserError("captures folder does not exist", path=root)
    skip = {p.resolve() for p in ignore}
    folders = sorted(
        p
        for p in root.iterdir()
        if p.is_dir()
        and not p.name.startswith(".")
        and p.name != REPORT_FOLDER
        and p.resolve() not in skip
    )
    loose = [
        p for p in sorted(root.iterdir()) if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    ]
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

    files: dict[tuple[str, str], Path] = {}
    shots_of: dict[str, set[str]] = {}
    for name in names:
        stems: dict[str, Path] = {}
        for p in sorted((root / name).iterdir()):
            if not p.is_file() or p.name.startswith(".") or p.suffix.lower() not in IMAGE_SUFFIXES:
                continue
            if p.stem in stems:
                raise UserError(f"two images of shot {p.stem!r} ({stems[p.stem].name})", path=p)
            stems[p.stem] = p
        if not stems:
            raise UserError(
                f"camera folder has no images ({', '.join(IMAGE_SUFFIXES)})", path=root / name
            )
        shots_of[name] = set(stems)
        files.update({(name, s): p for s, p in stems.items()})
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
    return Captures(root, tuple(names), tuple(every), files)


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
    for c, s in it:
        cam = captures.cameras[c]
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
