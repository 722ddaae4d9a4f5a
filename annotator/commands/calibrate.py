"""``annotator calibrate CAPTURES``: the rig's intrinsics and extrinsics from ChArUco shots.

Synthetic captures for it come from ``annotator synth --calibration OUT``: synthetic captures of
a board in random poses seen by the synthetic rig, with the truth beside them.
"""

from __future__ import annotations

import argparse
import sys

from annotator.commands import confirm, finish
from annotator.commands.calibrate_options import (
    add_board_options,
    add_model_options,
    add_output_options,
    add_rig_options,
    board_fields,
)

DESCRIPTION = """\
Calibrate the rig from synchronised shots of a ChArUco board or a plain chessboard: OpenCV's
detector, OpenCV's calibrateCamera per camera, then one joint refinement of every camera's
intrinsics (fx fy cx cy and the distortion) and pose in the rig and of every shot's board
pose; outlier corners and views are left out and reported. The distortion model (k1 k2 p1 p2,
or + k3) is chosen by the held-out error: k-fold over shots, the corners of each left-out
shot predicted from one camera into the others through the rig (px, per camera pair).

Captures layout: CAPTURES/<camera>/<shot>.png (or .jpg, .tif, .bmp), one folder per camera,
the same shot names in every folder (left/017.png and right/017.png are one board pose);
or one video per camera, CAPTURES/<camera>.mp4 (.avi .mkv .mov), every --stride-th frame a
shot, paired by frame index or by CAPTURES/<camera>.timestamps.txt. The board from
CAPTURES/board.yaml, --board FILE or the board options. Colour-inverted boards are found
(inverted: auto). A board that reads only in the flipped image is a mirrored camera (flip:
horizontal in the rig) or a board seen from behind, through the paper (an ordinary camera):
the other cameras' board poses decide, per camera; the summary says which and why.

A rig that does not hold together (the joint solve did not converge, a camera's RMS or
held-out error far above its own alone, an implausible focal length, a camera far beyond
the board distances) is never written: the report is, the reason goes to stderr, exit 1.

Writes the report (report.json, coverage_<camera>.png, rig.yaml) into
CAPTURES/calibration_report/ or --report DIR and, with --dataset DS, the rig section of
DS/dataset.yaml (created if missing; its other sections are kept as they are) after showing
the diff. The first camera (folder order, --cameras, or the existing rig's order) is the rig
frame; depth maps are registered to the first camera or --depth-camera.
"""


#: The argument naming the dataset this command writes into (its writer lock is held).
WRITES = "dataset"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = DESCRIPTION
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    # The order of the calls is the order of the usage line, which argparse errors print.
    parser.add_argument("captures", help="captures folder: CAPTURES/<camera>/<shot>.png")
    parser.add_argument(
        "--dataset",
        metavar="DS",
        help="write the rig into DS/dataset.yaml (created if missing); without it, only the report",
    )
    add_board_options(parser)
    add_rig_options(parser)
    add_model_options(parser)
    add_output_options(parser)


def run(args: argparse.Namespace) -> int:
    from annotator.calibration.workflow import calibrate_rig

    summary = calibrate_rig(
        args.captures,
        dataset=args.dataset,
        report=args.report,
        board=args.board,
        board_fields=board_fields(args),
        cameras=[c.strip() for c in args.cameras.split(",") if c.strip()] if args.cameras else None,
        depth_camera=args.depth_camera,
        depth_scale=args.depth_scale,
        dist_coeffs=args.dist_coeffs,
        folds=args.folds,
        stride=args.stride,
        min_shots=args.min_shots,
        write=False,
        quiet=args.quiet,
        tell=None if args.json else print,
        warn=lambda line: print(f"warning: {line}", file=sys.stderr),
    )
    if not args.json:
        print(summary.preview())
    if summary.holds and not args.dry_run:  # asked first on a terminal, unless --yes
        summary.write(confirm=None if args.yes or not sys.stdin.isatty() else confirm)
    return finish(summary, as_json=args.json)
