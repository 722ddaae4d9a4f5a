"""The calibration board: its description and OpenCV's object for it.

Two kinds of board (``kind``):

- ``charuco`` (the default): a chessboard of ``squares_x`` x ``squares_y`` squares whose white
  squares carry ArUco markers of ``dictionary`` (ids 0, 1, ... in reading order). Partial
  views count, and the markers tell a mirrored image from a proper one.
- ``chessboard``: a plain chessboard of ``squares_x`` x ``squares_y`` squares, the square at
  the board's origin black. Only whole views are found (OpenCV's
  ``findChessboardCorners``). Turned half a turn, a chessboard with ``squares_x +
  squares_y`` even looks the same, so two cameras could number its corners differently in
  one shot: such boards are refused (use e.g. 9x6 squares, not 8x6 or 7x7); with one odd and
  one even count, the colour of the outer corner squares tells the two ways apart.

What calibration measures are the *chessboard corners*, the ``(squares_x - 1) * (squares_y -
1)`` inner corners where two black squares touch; corner ``id`` is ``(row, column) =
divmod(id, squares_x - 1)``.

Board frame (OpenCV's, 4.6 and later): origin at the outer top-left corner of the
chessboard as printed, x along a row of ``squares_x`` squares, y down the ``squares_y``
rows, z into the board (away from a viewer looking at the printed face); millimetres. Corner
``(row, column)`` is at ``((column + 1) * square_mm, (row + 1) * square_mm, 0)``.

The board is described by a small YAML file (``board.yaml``, written by ``annotator synth
--calibration``) or by the options of ``annotator calibrate``::

    kind: charuco         # or chessboard (then no marker_mm, dictionary)
    squares_x: 7          # squares along the board's x (columns)
    squares_y: 5          # squares along its y (rows)
    square_mm: 30.0       # side of a chessboard square, as printed
    marker_mm: 22.0       # side of a marker (outer black border), as printed
    dictionary: DICT_4X4_50   # or the path of a dictionary file, relative to board.yaml
    legacy_pattern: false # true for boards made by OpenCV < 4.6 with an even number of rows
    inverted: auto        # true: printed colour-inverted (white markers on black); auto: either

``inverted: auto`` looks for the board as printed and colour-inverted. A plain chessboard
inverted is the same chessboard turned half a turn, which changes nothing for calibration.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from annotator.errors import UserError
from annotator.io.atomic import write_text
from annotator.io.documents import read_yaml
from annotator.markers.dictionary import resolve_dictionary

BOARD_FILE = "board.yaml"


BOARD_KINDS = ("charuco", "chessboard")


@dataclass(frozen=True)
class BoardSpec:
    """A calibration board as printed (see the module docstring for its frame).

    Attributes:
        squares_x: Squares along the board's x axis (columns), at least 2.
        squares_y: Squares along its y axis (rows), at least 2.
        square_mm: Side of a chessboard square, mm.
        marker_mm: Side of an ArUco marker (outer black border included), mm; less than
            ``square_mm`` (ChArUco boards only).
        dictionary: Dictionary of the markers: an OpenCV predefined name or the absolute path
            of a dictionary file (:mod:`annotator.markers.dictionary`).
        legacy_pattern: The chessboard pattern of OpenCV before 4.6 (differs from today's
            only for an even number of rows).
        kind: ``charuco`` or ``chessboard``.
        inverted: True if printed colour-inverted, False if not, None to try both.
    """

    squares_x: int = 7
    squares_y: int = 5
    square_mm: float = 30.0
    marker_mm: float = 22.0
    dictionary: str = "DICT_4X4_50"
    legacy_pattern: bool = False
    kind: str = "charuco"
    inverted: bool | None = None

    def __post_init__(self) -> None:
        from annotator.markers.dictionary import dictionary_size

        if self.kind not in BOARD_KINDS:
            raise UserError(f"board kind must be charuco or chessboard, not {self.kind!r}")
        if self.kind == "chessboard":
            if self.squares_x < 3 or self.squares_y < 3:
                raise UserError(
                    f"a chessboard needs at least 3 squares each way, got "
                    f"{self.squares_x}x{self.squares_y}"
                )
            if (self.squares_x + self.squares_y) % 2 == 0:
                raise UserError(
                    f"a {self.squares_x}x{self.squares_y} chessboard looks the same turned half "
                    "a turn, so its corners cannot be numbered alike in every camera: use one "
                    "with an odd number of squares one way and an even number the other (e.g. "
                    "9x6), or a ChArUco board"
                )
            if not self.square_mm > 0:
                raise UserError(f"square_mm must be positive, got {self.square_mm:g}")
            return
        if self.squares_x < 2 or self.squares_y < 2 or self.squares_x * self.squares_y < 6:
            raise UserError(
                f"a ChArUco board needs at least 2 squares each way and 6 in all, got "
                f"{self.squares_x}x{self.squares_y}"
            )
        if not (self.square_mm > 0 and 0 < self.marker_mm < self.square_mm):
            raise UserError(
                f"board sizes must satisfy 0 < marker_mm < square_mm, got marker_mm="
                f"{self.marker_mm:g}, square_mm={self.square_mm:g}"
            )
        available = dictionary_size(self.dictionary)  # UserError if unknown
        if self.marker_count > available:
            raise UserError(
                f"a {self.squares_x}x{self.squares_y} board needs {self.marker_count} markers, "
                f"{self.dictionary} has {available}"
            )

    @property
    def has_markers(self) -> bool:
        """True for a ChArUco board."""
        return self.kind == "charuco"

    @property
    def marker_count(self) -> int:
        """Markers on the board (one per white square of a ChArUco board)."""
        return self.squares_x * self.squares_y // 2 if self.has_markers else 0

    @property
    def corner_count(self) -> int:
        """Chessboard corners, the points calibration measures."""
        return (self.squares_x - 1) * (self.squares_y - 1)

    @property
    def size_mm(self) -> tuple[float, float]:
        """Width and height of the chessboard (without white margin), mm."""
        return self.squares_x * self.square_mm, self.squares_y * self.square_mm

    def describe(self) -> str:
        """One line for messages: ``7x5 ChArUco, 30 mm squares, 22 mm markers, DICT_4X4_50``."""
        inverted = ", inverted" if self.inverted else ""
        if not self.has_markers:
            return f"{self.squares_x}x{self.squares_y} chessboard, {self.square_mm:g} mm squares{inverted}"
        legacy = ", legacy pattern" if self.legacy_pattern else ""
        return (
            f"{self.squares_x}x{self.squares_y} ChArUco, {self.square_mm:g} mm squares, "
            f"{self.marker_mm:g} mm markers, {self.dictionary}{legacy}{inverted}"
        )

    @property
    def cv_board(self) -> cv2.aruco.CharucoBoard:
        """OpenCV's board object (``cv2.aruco.CharucoBoard``, OpenCV 4.7 and later), made once
        per board description."""
        return _cv_board(self)

    @property
    def corners(self) -> np.ndarray:
        """(corner_count, 3) chessboard corners in the board frame, mm, indexed by corner id."""
        return _corners(self)

    def to_yaml(self) -> dict[str, Any]:
        """The mapping of board.yaml."""
        out: dict[str, Any] = {"kind": self.kind, **asdict(self)}
        out["square_mm"] = float(self.square_mm)
        out["marker_mm"] = float(self.marker_mm)
        out["inverted"] = "auto" if self.inverted is None else bool(self.inverted)
        if not self.has_markers:
            for key in ("marker_mm", "dictionary", "legacy_pattern"):
                del out[key]
        return out


def read_board_yaml(path: str | Path) -> BoardSpec:
    """Read a board description; UserError naming the file for anything wrong in it."""
    path = Path(path)
    if not path.exists():
        raise UserError("board file is missing", path=path)
    try:
        doc = read_yaml(path)
    except UserError as exc:
        raise UserError(
            f"not a readable YAML board description ({exc.message})", path=path
        ) from None
    if not isinstance(doc, dict):
        raise UserError("must be a YAML mapping (squares_x, squares_y, ...)", path=path)
    known = set(BoardSpec.__dataclass_fields__)
    unknown = sorted(set(doc) - known)
    if unknown:
        raise UserError(
            f"unknown board field(s) {', '.join(map(str, unknown))} (known: {', '.join(sorted(known))})",
            path=path,
        )
    kind = doc.get("kind", "charuco")
    needed = ("squares_x", "squares_y", "square_mm") + (
        ("marker_mm",) if kind != "chessboard" else ()
    )
    missing = [k for k in needed if k not in doc]
    if missing:
        raise UserError(f"missing board field(s) {', '.join(missing)}", path=path)
    try:
        kwargs: dict[str, Any] = {
            "squares_x": _integer(doc["squares_x"], "squares_x"),
            "squares_y": _integer(doc["squares_y"], "squares_y"),
            "square_mm": _number(doc["square_mm"], "square_mm"),
            "kind": str(kind),
            "inverted": inverted_field(doc.get("inverted", "auto")),
        }
        if kind != "chessboard":
            kwargs.update(
                marker_mm=_number(doc["marker_mm"], "marker_mm"),
                dictionary=resolve_dictionary(
                    str(doc.get("dictionary", BoardSpec.dictionary)), path.parent
                ),
                legacy_pattern=bool(doc.get("legacy_pattern", False)),
            )
        return BoardSpec(**kwargs)
    except UserError as exc:
        where = f" ({exc.path})" if exc.path is not None else ""
        raise UserError(exc.message + where, path=path) from None


def inverted_field(value: Any) -> bool | None:
    """``inverted`` of board.yaml (or ``--inverted``): true, false or auto (None)."""
    if value is None or (isinstance(value, str) and value.lower() == "auto"):
        return None
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value.lower() in ("true", "false", "yes", "no"):
        return value.lower() in ("true", "yes")
    raise UserError(f"inverted must be true, false or auto, got {value!r}")


def write_board_yaml(path: str | Path, spec: BoardSpec) -> None:
    """Write a board description atomically."""
    write_text(path, yaml.safe_dump(spec.to_yaml(), sort_keys=False))


@lru_cache(maxsize=8)
def _cv_board(spec: BoardSpec) -> cv2.aruco.CharucoBoard:
    # Cached here rather than on the (picklable) spec: OpenCV objects do not pickle.
    from annotator.markers.dictionary import dictionary

    if not spec.has_markers:
        raise ValueError("a plain chessboard has no OpenCV ChArUco board")

    board = cv2.aruco.CharucoBoard(
        (spec.squares_x, spec.squares_y),
        float(spec.square_mm),
        float(spec.marker_mm),
        dictionary(spec.dictionary),
    )
    board.setLegacyPattern(bool(spec.legacy_pattern))
    return board


@lru_cache(maxsize=8)
def _corners(spec: BoardSpec) -> np.ndarray:
    rows, cols = np.divmod(np.arange(spec.corner_count), spec.squares_x - 1)
    pts = np.column_stack([(cols + 1) * spec.square_mm, (rows + 1) * spec.square_mm, 0 * rows])
    pts = pts.astype(np.float64)
    if spec.has_markers:  # OpenCV's own, which the ChArUco detector numbers
        pts = np.asarray(_cv_board(spec).getChessboardCorners(), np.float64).reshape(-1, 3)
    pts.setflags(write=False)
    return pts


def _integer(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise UserError(f"{name} must be a whole number, got {value!r}")
    return value


def _number(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise UserError(f"{name} must be a number (mm), got {value!r}")
    return float(value)
