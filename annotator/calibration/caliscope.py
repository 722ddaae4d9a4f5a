"""A calibration session as caliscope (github.com/mprib/caliscope) records it, read as it is.

Layout (the session folder, or its ``calibration/extrinsic`` folder given directly)::

    SESSION/
      charuco.toml                      # the board: columns, rows, square size, markers, ...
      calibration/extrinsic/
        cam_0.mp4 cam_1.mp4 ...         # one video per camera, cam_<cam_id>
        timestamps.csv                  # [sync_index,] cam_id, frame_time: one row per frame

The recorder writes one row per frame: its camera and ``frame_time`` (s), and in sessions
of caliscope before 0.11 a ``sync_index`` (the frames of one sync index were taken at about
the same moment; the cameras are not hardware-synchronised, so each frame's own time says
when). A camera's rows in the order of their ``frame_time`` are the frames of its video in
order (caliscope reads them so). With sync indices, every sync index that every camera has a
frame of is one shot; without, the frames are paired by time (as
:mod:`annotator.calibration.captures` pairs videos with timestamps files).

``charuco.toml`` (caliscope's board): ``columns`` and ``rows`` are the squares,
``square_size_override_cm`` the square as printed (else the largest square that fits
``board_width`` x ``board_height`` in ``units``, inch or cm), ``aruco_scale`` the marker's
fraction of the square, ``dictionary``, ``inverted`` (printed colour-inverted) and
``legacy_pattern``.
"""

from __future__ import annotations

import csv
import io
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from annotator.errors import UserError
from annotator.io.documents import read_text

BOARD_FILE = "charuco.toml"
TIMESTAMPS_FILE = "timestamps.csv"
EXTRINSIC = Path("calibration") / "extrinsic"
_CM_PER_INCH = 2.54


@dataclass(frozen=True)
class Session:
    """Where a caliscope session's files are.

    Attributes:
        videos: The folder of the videos and ``timestamps.csv``.
        timestamps: ``timestamps.csv``.
        board: ``charuco.toml``, or None when there is none.
    """

    videos: Path
    timestamps: Path
    board: Path | None


def find_session(root: Path) -> Session | None:
    """The caliscope session at ``root`` (the session folder or its extrinsic folder), or
    None when ``root`` is not laid out as one."""
    for videos, top in ((root / EXTRINSIC, root), (root, root.parent.parent)):
        stamps = videos / TIMESTAMPS_FILE
        if stamps.is_file() and any(videos.glob("cam_*.*")):
            board = top / BOARD_FILE
            return Session(videos, stamps, board if board.is_file() else None)
    return None


def read_frame_times(path: Path) -> dict[str, list[tuple[int | None, float]]]:
    """``timestamps.csv``: per camera (``cam_<cam_id>``), its frames' ``(sync_index,
    frame_time)`` in the order of their times (the order of the video's frames); the sync
    index is None in a file without that column."""
    text = read_text(path)
    reader = csv.DictReader(io.StringIO(text))
    columns = set(reader.fieldnames or [])
    if not {"cam_id", "frame_time"} <= columns:
        raise UserError(
            f"expected the columns cam_id, frame_time (and sync_index), as caliscope writes "
            f"them, found {', '.join(reader.fieldnames or []) or 'none'}",
            path=path,
        )
    synced = "sync_index" in columns
    frames: dict[str, list[tuple[int | None, float]]] = {}
    for line, row in enumerate(reader, start=2):
        try:
            sync = int(row["sync_index"]) if synced else None
            cam, time = int(row["cam_id"]), float(row["frame_time"])
        except (TypeError, ValueError):
            raise UserError(
                f"line {line}: sync_index and cam_id must be whole numbers and frame_time a "
                "number (seconds)",
                path=path,
            ) from None
        if not math.isfinite(time):
            raise UserError(f"line {line}: frame_time is not a finite number", path=path)
        frames.setdefault(f"cam_{cam}", []).append((sync, time))
    if not frames:
        raise UserError("no frame listed", path=path)
    for name, rows in frames.items():
        rows.sort(key=lambda r: (r[1], r[0] or 0))
        syncs = [s for s, _ in rows]
        if synced and len(set(syncs)) != len(syncs):
            raise UserError(f"camera {name} has two frames of one sync_index", path=path)
        if len({t for _, t in rows}) != len(rows):
            raise UserError(f"camera {name} has two frames of one frame_time", path=path)
    return frames


def read_board_toml(path: Path) -> dict[str, Any]:
    """The :class:`~annotator.calibration.board.BoardSpec` fields of caliscope's
    ``charuco.toml``."""
    try:
        doc = tomllib.loads(read_text(path))
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"not readable TOML ({exc})", path=path) from None
    doc = doc.get("charuco", doc)  # config.toml holds the same table under [charuco]
    missing = [k for k in ("columns", "rows") if k not in doc]
    if missing:
        raise UserError(f"missing board field(s) {', '.join(missing)}", path=path)
    try:
        columns, rows = int(doc["columns"]), int(doc["rows"])
        square_cm = doc.get("square_size_override_cm")
        if not square_cm:
            per_cm = 1.0 if str(doc.get("units", "inch")) == "cm" else _CM_PER_INCH
            height = float(doc["board_height"]) * per_cm
            width = float(doc["board_width"]) * per_cm
            square_cm = min(height / rows, width / columns)
        square_mm = 10.0 * float(square_cm)
        marker_mm = square_mm * float(doc.get("aruco_scale", 0.75))
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(
            f"cannot tell the square size ({exc}): give square_size_override_cm, or "
            "board_width, board_height and units",
            path=path,
        ) from None
    return {
        "squares_x": columns,
        "squares_y": rows,
        "square_mm": square_mm,
        "marker_mm": marker_mm,
        "dictionary": str(doc.get("dictionary", "DICT_4X4_50")),
        "legacy_pattern": bool(doc.get("legacy_pattern", False)),
        "inverted": bool(doc["inverted"]) if "inverted" in doc else None,
    }
