"""The recorders' files ingest reads, one module each, found by what they hold.

Every module of this package that defines ``READERS`` (:class:`RecorderReader` records)
holds readers; each has its name, the file types it takes (for messages), how it recognises its files
(``sniff``) and how it opens one into a :class:`~annotator.ingest.recording.Recording`.
:func:`open_with_reader` asks them in ``order`` and opens the file with the first that
recognises it. A new recorder format is one new module here: nothing else names it.
"""

from __future__ import annotations

import functools
import importlib
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from annotator.errors import UserError
from annotator.ingest.recording import Recording

__all__ = ["OpenOptions", "RecorderReader", "open_with_reader", "readers"]

#: Default pairing tolerance between a colour frame and its depth frame (s).
PAIR_TOLERANCE_S = 0.02


@dataclass(frozen=True)
class OpenOptions:
    """What ingest asks of a reader (``annotator ingest``'s options of the same names).

    Attributes:
        stream: The colour stream of a folder of several (``left``...).
        depth: Read depth (False: colour only).
        tolerance_s: How far apart in time a colour frame and its depth partner may be.
        fps: The frame rate of an image folder whose names are frame indices.
        color_topic, depth_topic: A bag's topics, when they cannot be told.
        depth_unit_mm: Millimetres per unit of an image folder's depth images.
    """

    stream: str | None = None
    depth: bool = True
    tolerance_s: float = PAIR_TOLERANCE_S
    fps: float | None = None
    color_topic: str | None = None
    depth_topic: str | None = None
    depth_unit_mm: float | None = None


@dataclass(frozen=True)
class RecorderReader:
    """One recorder's file format.

    Attributes:
        name: What the files are, as messages say (``ROS bag``).
        suffixes: Their file types (``.bag``...; empty for a folder), as messages list them.
        sniff: Whether a path is one of its files (cheap: a suffix, a header, an attachment).
        open: The file opened (one-line UserErrors for what cannot be read).
        order: Asked before the readers of a higher order (an Azure Kinect ``.mkv`` before
            a plain video).
    """

    name: str
    suffixes: tuple[str, ...]
    sniff: Callable[[Path, OpenOptions], bool]
    open: Callable[[Path, OpenOptions], Recording]
    order: int = 50


@functools.cache
def readers() -> tuple[RecorderReader, ...]:
    """Every reader of this package, in the order they are asked."""
    found = []
    for info in pkgutil.iter_modules(__path__):
        module = importlib.import_module(f"{__name__}.{info.name}")
        found += [r for r in getattr(module, "READERS", ()) if isinstance(r, RecorderReader)]
    return tuple(sorted(found, key=lambda r: (r.order, r.name)))


def open_with_reader(path: Path, options: OpenOptions) -> Recording:
    """``path`` opened by the first reader that recognises it.

    Raises:
        UserError: no reader recognises it (the message lists what ingest reads).
    """
    if not (path.exists() or path.is_symlink()):
        raise UserError("no such video file or image folder", path=path)
    for reader in readers():
        if reader.sniff(path, options):
            return reader.open(path, options)
    kinds = [f"{r.name} ({', '.join(r.suffixes)})" if r.suffixes else r.name for r in readers()]
    raise UserError(f"is none of what ingest reads: {'; '.join(kinds)}", path=path)
