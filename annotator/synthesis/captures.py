"""``annotator synth --calibration``'s work as a library function: board shots for
``annotator calibrate`` rendered into a new folder (:func:`synthesize_captures`), with a
summary whose ``to_json()`` is the command's ``--json``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from annotator.calibration.board import BoardSpec
from annotator.io.output_folder import check_output_folder
from annotator.markers.dictionary import resolve_dictionary
from annotator.synthesis.board import CaptureSettings, write_captures

__all__ = ["CapturesSummary", "calibration_board", "synthesize_captures"]


@dataclass(frozen=True)
class CapturesSummary:
    """What :func:`synthesize_captures` wrote.

    >>> s = CapturesSummary("shots", 8, ["left", "right"], {}, "7x5 ChArUco")
    >>> print(s.text())  # doctest: +NORMALIZE_WHITESPACE
    synth --calibration: 8 shots of a 7x5 ChArUco board seen by left, right, written to shots
    (board.yaml, truth.yaml)
    >>> s.counts()
    {'shots': 8, 'cameras': 2}
    """

    out: str
    shots: int
    cameras: list[str]
    board: dict[str, Any]
    board_text: str

    def counts(self) -> dict[str, int]:
        return {"shots": self.shots, "cameras": len(self.cameras)}

    def warnings(self) -> list[str]:
        return []  # a shot that fails to render fails the whole run (UserError)

    def written_paths(self) -> list[Path]:
        return [Path(self.out)]

    def exit_status(self) -> int:
        return 0

    def to_json(self) -> dict[str, Any]:
        """The summary as plain JSON values (``annotator synth --calibration --json``)."""
        return {"out": self.out, "shots": self.shots, "cameras": self.cameras, "board": self.board}

    def text(self) -> str:
        return (
            f"synth --calibration: {self.shots} shots of a {self.board_text} board seen by "
            f"{', '.join(self.cameras)}, written to {self.out} (board.yaml, truth.yaml)"
        )


def calibration_board(kind: str = "charuco", dictionary: str | None = None) -> BoardSpec:
    """The board of ``synth --calibration``: a 9 x 6 plain chessboard of 30 mm squares, or
    the default ChArUco board (of ``dictionary``, a predefined name or a file)."""
    if kind == "chessboard":
        return BoardSpec(9, 6, 30.0, kind="chessboard")
    return BoardSpec(dictionary=resolve_dictionary(dictionary or BoardSpec.dictionary, Path.cwd()))


def synthesize_captures(
    out: str | Path,
    settings: CaptureSettings,
    *,
    workers: int = 1,
    quiet: bool = True,
    video: bool = False,
    overwrite: bool = False,
) -> CapturesSummary:
    """Render ``settings.shots`` shots of the board seen by the synthetic rig into the new
    folder ``out`` (``<camera>/<shot>.png``, or one video per camera with ``video``;
    board.yaml, truth.yaml), written whole or not at all.

    >>> import tempfile
    >>> from pathlib import Path
    >>> out = Path(tempfile.mkdtemp()) / "shots"
    >>> s = synthesize_captures(out, CaptureSettings(shots=2, size=(320, 256)))
    >>> s.shots, (out / "board.yaml").is_file()
    (2, True)

    Raises:
        UserError: ``out`` may not be written (exists, not ours, without ``overwrite``), or
            a shot failed to render (nothing is written).
    """
    out = Path(out)
    check_output_folder(out, command="synth", overwrite=overwrite)
    plan = write_captures(settings, out, workers=workers, quiet=quiet, video=video)
    return CapturesSummary(
        str(out),
        len(plan.shot_names),
        [c.name for c in plan.rig.cameras],
        settings.board.to_yaml(),
        settings.board.describe(),
    )
