"""``annotator synth --calibration OUT``: board shots for ``annotator calibrate`` instead of
scenes (:func:`annotator.synthesis.board.write_captures`); called by
:mod:`annotator.commands.synth`."""

from __future__ import annotations

import argparse

from annotator.commands import finish, number, number_pair
from annotator.errors import UserError
from annotator.synthesis.board import CaptureSettings
from annotator.synthesis.generate import SynthSettings


def add_calibration_options(parser: argparse.ArgumentParser) -> None:
    """``--calibration``: board shots instead of scenes, and how the board is seen."""
    calib = parser.add_argument_group("--calibration", "the board shots")
    calib.add_argument(
        "--calibration",
        action="store_true",
        help="instead of scenes, render a ChArUco board in --scenes random poses (use 30) seen "
        "by the rig, into OUT/<camera>/<shot>.png with board.yaml and truth.yaml "
        "(for `annotator calibrate`)",
    )
    calib.add_argument(
        "--board-kind",
        choices=("charuco", "chessboard"),
        default="charuco",
        help="a 7x5 ChArUco board (default) or a 9x6 plain chessboard, 30 mm squares",
    )
    calib.add_argument(
        "--board-dictionary",
        metavar="NAME|FILE",
        help="the ChArUco board's dictionary: a predefined name or a dictionary file, copied "
        "beside board.yaml (default DICT_4X4_50)",
    )
    _add_realism_options(calib)


def _add_realism_options(calib: argparse._ArgumentGroup) -> None:
    """How the board shots differ from ideal ones: the print, the cameras, the timing."""
    calib.add_argument("--inverted", action="store_true", help="the board printed colour-inverted")
    calib.add_argument(
        "--mirror",
        metavar="CAMERA",
        action="append",
        default=[],
        help="store this camera's images mirrored (a webcam in selfie mode); repeatable",
    )
    calib.add_argument(
        "--centre",
        type=number(low=0.1, high=1.0),
        default=1.0,
        metavar="F",
        help="keep the board within the central fraction F of every image (default 1: anywhere)",
    )
    calib.add_argument(
        "--distance",
        metavar="MIN-MAX",
        default="520-760",
        help="range of the board centre's depth in the first camera, mm (default 520-760)",
    )
    calib.add_argument(
        "--video",
        action="store_true",
        help="one video per camera (OUT/<camera>.mkv, lossless) with timestamps files, "
        "instead of image folders",
    )
    calib.add_argument(
        "--printed-mirrored",
        action="store_true",
        help="the board printed mirrored left to right (a printer's mirror setting): the "
        "cameras read it only flipped",
    )
    calib.add_argument(
        "--paper-blur",
        type=number(low=0),
        default=CaptureSettings.paper_blur,
        metavar="SIGMA",
        help="blur (px) the paper adds to a print seen through it, from behind (default 0)",
    )
    calib.add_argument(
        "--timing-ms",
        type=number(low=0),
        default=CaptureSettings.timing_ms,
        metavar="MS",
        help="cameras out of step (webcams): each camera takes its image of a shot up to MS "
        "before or after the shot's moment (default 0: all at once)",
    )
    calib.add_argument(
        "--rolling-ms",
        type=number(low=0),
        default=CaptureSettings.rolling_ms,
        metavar="MS",
        help="and camera k (rig order) k times MS later, cameras read one after another "
        "(default 0)",
    )
    calib.add_argument(
        "--speed",
        type=number_pair("MM_S,DEG_S", "40,5"),
        default=CaptureSettings.speed,
        metavar="MM_S,DEG_S",
        help="the board held by hand: its centre's largest speed (mm/s) and turn (deg/s) "
        "during a shot, each shot a random fraction of it (default 0,0: still)",
    )


def synth_calibration(args: argparse.Namespace, config: SynthSettings) -> int:
    """``annotator synth --calibration OUT``: a board in ``--scenes`` random poses seen by the
    synthetic rig of ``--seed`` (``--size``, ``--noise``, ``--blur`` apply), written by
    :func:`annotator.synthesis.captures.synthesize_captures`."""
    from annotator.synthesis.captures import calibration_board, synthesize_captures

    if args.ray is not None:
        raise UserError("--ray does not apply to --calibration (board shots are quick)")
    try:
        lo, _, hi = args.distance.partition("-")
        distance = (float(lo), float(hi))
    except ValueError:
        raise UserError(f"--distance must be MIN-MAX in mm, got {args.distance!r}") from None
    if not 0 < distance[0] <= distance[1]:
        raise UserError(f"--distance must satisfy 0 < MIN <= MAX, got {args.distance!r}")
    board = calibration_board(args.board_kind, args.board_dictionary)
    settings = CaptureSettings(
        shots=config.scenes,
        distance=distance,
        seed=config.seed,
        size=config.size,
        board=board,
        # A plain chessboard is only found whole.
        min_visible=1.0 if not board.has_markers else CaptureSettings.min_visible,
        noise=config.noise,
        blur=config.blur,
        inverted=args.inverted,
        mirrored=tuple(args.mirror),
        centre=args.centre,
        printed_mirrored=args.printed_mirrored,
        paper_blur=args.paper_blur,
        timing_ms=args.timing_ms,
        rolling_ms=args.rolling_ms,
        speed=args.speed,
    )
    summary = synthesize_captures(
        args.out,
        settings,
        workers=args.workers,
        quiet=args.quiet,
        video=args.video,
        overwrite=args.overwrite,
    )
    return finish(summary, as_json=args.json)
