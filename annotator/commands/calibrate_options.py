"""``annotator calibrate``'s options: the board, the rig, the distortion model, the output
(:mod:`annotator.commands.calibrate`)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from annotator.commands import number, whole
from annotator.errors import UserError


def add_board_options(parser: argparse.ArgumentParser) -> None:
    """The board, when CAPTURES/board.yaml does not describe it (or to override it)."""
    board = parser.add_argument_group(
        "board", "the board (default: CAPTURES/board.yaml; options override its fields)"
    )
    board.add_argument("--board", metavar="FILE", help="board description (YAML)")
    board.add_argument(
        "--kind", choices=("charuco", "chessboard"), help="board kind (default charuco)"
    )
    board.add_argument(
        "--inverted",
        choices=("auto", "true", "false"),
        help="board printed colour-inverted (white markers on black); auto (default) tries both",
    )
    board.add_argument(
        "--squares", metavar="XxY", help="squares along the board's x and y, e.g. 7x5"
    )
    board.add_argument(
        "--square-mm", type=number(low=0, above=True), help="square side as printed, mm"
    )
    board.add_argument(
        "--marker-mm", type=number(low=0, above=True), help="marker side as printed, mm"
    )
    board.add_argument(
        "--dictionary",
        help="ArUco dictionary: a predefined name or a dictionary file (default DICT_4X4_50)",
    )
    board.add_argument(
        "--legacy-pattern",
        action="store_true",
        default=None,
        help="board printed by OpenCV < 4.6 (matters for an even number of rows)",
    )


def add_rig_options(parser: argparse.ArgumentParser) -> None:
    """The rig's cameras, their order, and its depth section."""
    rig = parser.add_argument_group("rig", "the cameras and the depth maps")
    rig.add_argument(
        "--cameras",
        metavar="A,B",
        help="camera folders to use, in rig order (default: the existing rig's order, else sorted)",
    )
    rig.add_argument(
        "--depth-camera",
        metavar="NAME",
        help="rig camera whose pixel grid the depth maps use (default: kept, else the first)",
    )
    rig.add_argument(
        "--depth-scale",
        type=number(low=0, above=True),
        metavar="MM",
        help="mm per depth unit (default: kept from the dataset; without either, no depth section)",
    )


def add_model_options(parser: argparse.ArgumentParser) -> None:
    """The distortion model, its held-out choice, and which shots count."""
    model = parser.add_argument_group("model", "the distortion model and the shots")
    model.add_argument(
        "--dist-coeffs",
        choices=("auto", "2", "4", "5", "8"),
        default="auto",
        help="distortion model: k1 k2 (2), + p1 p2 (4), + k3 (5), + k4 k5 k6 (8, OpenCV's "
        "rational model, for wide-angle lenses); auto (default): 4 or 5, whichever the "
        "held-out error supports",
    )
    model.add_argument(
        "--folds", type=whole(low=2), default=5, help="folds of the held-out error (default 5)"
    )
    model.add_argument(
        "--stride",
        type=whole(low=1),
        default=None,
        help="video captures: every N-th frame is a shot (default 10; a caliscope session's "
        "sync indices: 1)",
    )
    model.add_argument(
        "--min-shots",
        type=whole(low=1),
        default=6,
        help="usable shots each camera needs (default 6)",
    )


def add_output_options(parser: argparse.ArgumentParser) -> None:
    """Where the report goes, whether dataset.yaml is written, what is printed."""
    output = parser.add_argument_group("output")
    output.add_argument(
        "--report",
        metavar="DIR",
        help="report folder (default CAPTURES/calibration_report)",
    )
    output.add_argument("--yes", action="store_true", help="write dataset.yaml without asking")
    output.add_argument(
        "--dry-run", action="store_true", help="show the diff of dataset.yaml, write nothing there"
    )
    output.add_argument("--json", action="store_true", help="print the result as JSON")
    output.add_argument("--quiet", action="store_true", help="no progress bar")


def board_fields(args: argparse.Namespace) -> dict[str, Any]:
    """The board options given: BoardSpec fields that override the board file's."""
    from annotator.calibration.board import inverted_field
    from annotator.markers.dictionary import resolve_dictionary

    fields: dict[str, Any] = {}
    if args.squares:
        try:
            x, y = (int(v) for v in args.squares.lower().split("x"))
        except ValueError:
            raise UserError(f"--squares must be XxY (e.g. 7x5), got {args.squares!r}") from None
        fields.update(squares_x=x, squares_y=y)
    for key in ("square_mm", "marker_mm", "legacy_pattern", "kind"):
        if getattr(args, key) is not None:
            fields[key] = getattr(args, key)
    if args.dictionary is not None:
        fields["dictionary"] = resolve_dictionary(args.dictionary, Path.cwd())
    if args.inverted is not None:
        fields["inverted"] = inverted_field(args.inverted)
    return fields
