"""``annotator calibrate CAPTURES``: the rig's intrinsics and extrinsics from ChArUco shots.

Synthetic captures for it come from ``annotator synth --calibration OUT``: synthetic captures of
a board in random poses seen by the synthetic rig, with the truth beside them.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tqdm import tqdm

from annotator.commands import confirm, number, whole
from annotator.errors import UserError

if TYPE_CHECKING:  # imported when the command runs, so that `annotator --help` stays fast
    from annotator.calibration.board import BoardSpec
    from annotator.calibration.captures import Captures
    from annotator.calibration.detect import CapturesDetection
    from annotator.calibration.records import Calibration, View
    from annotator.dataset.model import DepthSpec

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
    _add_board_options(parser)
    _add_rig_options(parser)
    _add_model_options(parser)
    _add_output_options(parser)


def _add_board_options(parser: argparse.ArgumentParser) -> None:
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


def _add_rig_options(parser: argparse.ArgumentParser) -> None:
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


def _add_model_options(parser: argparse.ArgumentParser) -> None:
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
        default=10,
        help="video captures: every N-th frame is a shot (default 10)",
    )
    model.add_argument(
        "--min-shots",
        type=whole(low=1),
        default=6,
        help="usable shots each camera needs (default 6)",
    )


def _add_output_options(parser: argparse.ArgumentParser) -> None:
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


@dataclass(frozen=True)
class _Target:
    """The dataset the rig goes into (``path`` None: none, only the report), as it is now."""

    path: Path | None
    old_text: str | None
    old_doc: dict[str, Any] | None
    old_rig: dict[str, Any]


@dataclass(frozen=True)
class _Inputs:
    """What the calibration starts from, and where its report goes."""

    board: BoardSpec
    captures: Captures
    found: CapturesDetection
    depth: DepthSpec | None
    report_dir: Path


def run(args: argparse.Namespace) -> int:
    inputs, target = _inputs(args)
    if not args.json:
        for line in _capture_lines(inputs.captures, inputs.found):
            print(line)
    cal = _calibrate(args, inputs)
    if not args.json and cal.readings is not None:
        for reading in cal.readings.cameras:
            if reading.reason:
                print(reading.reason)
    return _output(args, cal, inputs, target)


def _flipped(cal: Calibration) -> list[str]:
    """The mirrored cameras (flip: horizontal)."""
    return list(cal.readings.mirrored) if cal.readings is not None else []


def _inputs(args: argparse.Namespace) -> tuple[_Inputs, _Target]:
    """The board, the dataset, the captures in rig order, the depth section, the detections."""
    from annotator.calibration.captures import REPORT_FOLDER

    root = Path(args.captures)
    report_dir = Path(args.report) if args.report else root / REPORT_FOLDER
    if args.report:
        _check_report_dir(report_dir, root)
    board = _board(args, root)
    target = _target(args)
    captures = _captures(args, root, report_dir, target)
    depth = _depth(args, captures.cameras, target.old_rig, target.path)
    found = _detect(captures, board, target.old_rig["sizes"], target.path, quiet=args.quiet)
    return _Inputs(board, captures, found, depth, report_dir), target


def _check_report_dir(report: Path, root: Path) -> None:
    """--report must not be the captures folder, a camera folder or inside one, nor a file
    of the captures: a report there would be read as captures next time, or drop a camera
    (a folder given as --report is not read as a camera)."""
    from annotator.calibration.captures import IMAGE_SUFFIXES

    if report.exists() and not report.is_dir():
        raise UserError("--report exists and is not a folder", path=report)
    if not root.is_dir():
        return
    rep, top = report.resolve(), root.resolve()
    if rep == top:
        raise UserError(
            "--report is the captures folder itself: its pictures would be read as loose "
            "images next time; give a folder of its own",
            path=report,
        )
    if top not in rep.parents:
        return
    first = top / rep.relative_to(top).parts[0]
    if first.is_dir() and any(
        p.suffix.lower() in IMAGE_SUFFIXES for p in first.iterdir() if p.is_file()
    ):
        where = "is" if first == rep else "lies inside"
        raise UserError(
            f"--report {where} the camera folder {first.name} of the captures {root}: that "
            "camera would be left out and its images mixed with the report; give a folder "
            "of its own",
            path=report,
        )


def _target(args: argparse.Namespace) -> _Target:
    """``--dataset``'s dataset.yaml, read if it exists."""
    from annotator.calibration.rig_yaml import existing_rig, read_dataset_doc

    ds_yaml = Path(args.dataset) / "dataset.yaml" if args.dataset else None
    if ds_yaml is not None and Path(args.dataset).exists() and not Path(args.dataset).is_dir():
        raise UserError("exists and is not a folder", path=args.dataset)
    old_text, old_doc = read_dataset_doc(ds_yaml) if ds_yaml else (None, None)
    return _Target(ds_yaml, old_text, old_doc, existing_rig(old_doc))


def _captures(args: argparse.Namespace, root: Path, report_dir: Path, target: _Target) -> Captures:
    """The captures, in the existing rig's camera order unless --cameras sets one (which
    may move the rig frame: a warning)."""
    from annotator.calibration.captures import find_rig_captures

    cameras = None
    if args.cameras:
        cameras = [c.strip() for c in args.cameras.split(",") if c.strip()]
    rig_cameras = target.old_rig["cameras"]
    captures = find_rig_captures(
        root,
        cameras=cameras,
        rig_cameras=rig_cameras,
        ignore=[report_dir],
        stride=args.stride,
        rig_source=target.path,
    )
    if rig_cameras and cameras is not None and captures.cameras[0] != rig_cameras[0]:
        print(
            f"warning: the rig frame changes from camera {rig_cameras[0]} to "
            f"{captures.cameras[0]}: poses already in {args.dataset} (gt.json, "
            "annotation.json) stay in the old frame",
            file=sys.stderr,
        )
    return captures


def _calibrate(args: argparse.Namespace, inputs: _Inputs) -> Calibration:
    """The calibration, its distortion model from --dist-coeffs (auto: the held-out choice)."""
    from annotator.calibration.model_choice import CANDIDATES, calibrate_and_assess
    from annotator.calibration.records import CalibrationSettings

    auto = args.dist_coeffs == "auto"
    captures = inputs.captures
    return calibrate_and_assess(
        inputs.found.views,
        cameras=captures.cameras,
        sizes=inputs.found.sizes,
        shots=captures.shots,
        board=inputs.board,
        options=CalibrationSettings(
            min_shots=args.min_shots, dist_coeffs=5 if auto else int(args.dist_coeffs)
        ),
        candidates=CANDIDATES if auto else (int(args.dist_coeffs),),
        folds=args.folds,
        where={c: captures.folder(c) for c in captures.cameras},
    )


def _capture_lines(captures: Captures, found: CapturesDetection) -> list[str]:
    """What the detection found worth saying: videos' pairing, inverted boards (one line
    each; how flipped boards were read is said after the calibration)."""
    lines = []
    if captures.videos:
        lines.append(_pairing_line(captures))
    for c, name in enumerate(captures.cameras):
        n = sum(1 for v in found.views if v.camera == c and len(v.ids))
        if found.inverted[c]:
            lines.append(
                f"camera {name}: the board reads colour-inverted in {found.inverted[c]} of its "
                f"{n} shots with the board"
            )
    return lines


def _pairing_line(captures: Captures) -> str:
    """Which frames of the videos became shots."""
    ref = captures.cameras[0]
    first, last = (captures.frames[(ref, s)] for s in (captures.shots[0], captures.shots[-1]))
    text = (
        f"videos: {len(captures.shots)} shots, frames {first}..{last} of {ref}, paired by "
        f"{captures.pairing}"
    )
    if captures.pairing == "timestamps":
        offsets = [
            captures.frames[(c, s)] - captures.frames[(ref, s)]
            for s in captures.shots
            for c in captures.cameras[1:]
        ]
        text += f" (frame offsets {min(offsets)}..{max(offsets)})" if offsets else ""
    if captures.unpaired:
        shown = ", ".join(str(f) for f in captures.unpaired[:6])
        text += (
            f"; {len(captures.unpaired)} frames of {ref} had no partner in every video and were "
            f"left out ({shown}{', ...' if len(captures.unpaired) > 6 else ''})"
        )
    return text + " (report.json lists each shot's frames)"


def _board(args: argparse.Namespace, root: Path) -> BoardSpec:
    """The board from --board, CAPTURES/board.yaml and the board options (which win)."""
    from annotator.calibration.board import BOARD_FILE, BoardSpec, inverted_field, read_board_yaml
    from annotator.markers.dictionary import resolve_dictionary

    fields: dict[str, Any] = {}
    path = Path(args.board) if args.board else root / BOARD_FILE
    if args.board or path.is_file():
        spec = read_board_yaml(path)
        fields = {k: getattr(spec, k) for k in BoardSpec.__dataclass_fields__}
        if not spec.has_markers:
            fields.pop("marker_mm")
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
    needed = ("squares_x", "square_mm") + (
        ("marker_mm",) if fields.get("kind", "charuco") == "charuco" else ()
    )
    missing = [k for k in needed if k not in fields]
    if missing:
        raise UserError(
            "no board description: give --board FILE, put a board.yaml in the captures folder, "
            "or give --squares, --square-mm and --marker-mm (and --dictionary), or --kind "
            "chessboard --squares and --square-mm",
            path=path,
        )
    return BoardSpec(**fields)


def _depth(
    args: argparse.Namespace,
    cameras: tuple[str, ...],
    old_rig: dict[str, Any],
    ds_yaml: Path | None,
) -> DepthSpec | None:
    """The depth section to write: kept from the dataset, changed by the options."""
    from annotator.dataset.model import DepthSpec

    if args.depth_camera is not None and args.depth_camera not in cameras:
        raise UserError(
            f"--depth-camera {args.depth_camera!r} is not one of the cameras ({', '.join(cameras)})"
        )
    if args.depth_scale is not None and not args.depth_scale > 0:
        raise UserError(f"--depth-scale must be positive (mm per unit), got {args.depth_scale}")
    old: dict[str, Any] = old_rig["depth"] or {}
    scale = args.depth_scale if args.depth_scale is not None else old.get("scale")
    if scale is None:
        if args.depth_camera is not None:
            raise UserError(
                "--depth-camera needs the depth maps' scale: add --depth-scale MM (mm per depth "
                "unit)" + (f"; {ds_yaml} has none" if ds_yaml else "")
            )
        return None
    camera = args.depth_camera or (old["camera"] if old.get("camera") in cameras else cameras[0])
    return DepthSpec(camera=camera, scale=float(scale))


def _detect(
    captures: Captures,
    board: BoardSpec,
    expected_sizes: dict[str, tuple[int, int]],
    ds_yaml: Path | None,
    *,
    quiet: bool,
) -> CapturesDetection:
    """Every camera's detection in every shot, and each camera's image size."""
    from annotator.calibration.detect import detect_captures

    def bar(it: Iterator) -> Iterator:
        return tqdm(
            it,
            total=len(captures.cameras) * len(captures.shots),
            desc="detect",
            unit="image",
            disable=quiet or not sys.stderr.isatty(),
            file=sys.stderr,
        )

    found = detect_captures(
        captures, board, expected_sizes=expected_sizes, expected_source=ds_yaml, progress=bar
    )
    if not any(len(v.ids) for v in found.views):
        raise _board_not_found(found.views, found.foreign_markers, captures, board)
    return found


def _board_not_found(
    views: list[View], foreign: int, captures: Captures, board: BoardSpec
) -> UserError:
    """One clear line when the board is in no image at all (usually a wrong board
    description), rather than a complaint per camera."""
    markers = sum(v.markers for v in views)
    if not board.has_markers:
        hint = (
            f"the whole {board.squares_x}x{board.squares_y}-square chessboard must be in view: "
            "check --squares (squares, not inner corners)"
        )
    elif markers:
        hint = (
            f"{markers} of its markers were seen, but never two around a chessboard corner: "
            "check --squares (columns x rows) and --legacy-pattern"
        )
    elif foreign:
        hint = (
            f"{foreign} markers of {board.dictionary} were seen with ids outside the board's "
            f"0..{board.marker_count - 1}: check --squares"
        )
    else:
        hint = f"no marker of {board.dictionary} was seen: check --dictionary"
    return UserError(
        f"board not found: the {board.describe()} board is in none of the "
        f"{len(views)} images ({hint})",
        path=captures.root,
    )


def _output(args: argparse.Namespace, cal: Calibration, inputs: _Inputs, target: _Target) -> int:
    """Write the report, show the diff, write dataset.yaml, print the summary."""
    from annotator.calibration.outputs import write_report_folder
    from annotator.calibration.report import report_dict

    flipped = _flipped(cal)
    rig = write_report_folder(
        inputs.report_dir,
        cal,
        inputs.board,
        captures=inputs.captures,
        depth=inputs.depth,
        flipped=flipped,
        old_doc=target.old_doc,
    )
    result: dict[str, Any] = report_dict(
        cal, inputs.board, captures=inputs.captures, flipped=flipped
    )
    result["report"] = str(inputs.report_dir)
    if cal.problems:
        return _refuse(args, cal, inputs, target, result)
    written = None
    if target.path is not None:
        written = _update_dataset(args, cal, target, rig)
        result.update(written.fields())
    elif not args.json:
        _print_summary(cal)
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        print(
            f"calibrate: RMS {cal.rms_px:.3f} px; report in {inputs.report_dir}; "
            + _what_became(written, inputs.report_dir)
        )
    return 1 if written is not None and written.declined else 0


def _refuse(
    args: argparse.Namespace,
    cal: Calibration,
    inputs: _Inputs,
    target: _Target,
    result: dict[str, Any],
) -> int:
    """A rig that does not hold together: the summary and the report, nothing written into
    the dataset, the checks that failed on stderr, exit 1."""
    from annotator.calibration.checks import what_to_try

    advice = what_to_try(cal.problems, inputs.captures.cameras)
    if args.json:
        result.update(written=False, advice=advice)
        if target.path is not None:
            result["dataset_yaml"] = str(target.path)
        print(json.dumps(result, indent=1))
    else:
        _print_summary(cal)
        print(
            f"calibrate: RMS {cal.rms_px:.3f} px; report in {inputs.report_dir}; the rig does "
            "not hold together: "
            + (f"{target.path} not written" if target.path is not None else "no rig.yaml")
        )
    where = f"{target.path}: not written: " if target.path is not None else ""
    for p in cal.problems:
        print(f"error: {where}{p}", file=sys.stderr)
    print(f"error: {advice}", file=sys.stderr)
    return 1


@dataclass(frozen=True)
class _Written:
    """What became of dataset.yaml: its diff, and whether it was written or the user
    declined."""

    path: Path
    diff: str
    written: bool
    declined: bool

    def fields(self) -> dict[str, Any]:
        """The --json fields about it."""
        return {"dataset_yaml": str(self.path), "diff": self.diff, "written": self.written}


def _update_dataset(
    args: argparse.Namespace, cal: Calibration, target: _Target, rig: dict[str, Any]
) -> _Written:
    """Show the summary and the diff of dataset.yaml, then write it (asking first on a
    terminal, unless --yes; never with --dry-run)."""
    from annotator.calibration.outputs import dataset_update
    from annotator.io.atomic import write_text

    assert target.path is not None
    update = dataset_update(target.path, target.old_text, rig)
    diff = update.diff
    if not args.json:
        _print_summary(cal)
        print(diff if diff else f"{update.path} already has this rig: nothing to write", end="")
        if diff and not diff.endswith("\n"):
            print()
    if not diff or args.dry_run:
        return _Written(update.path, diff, written=False, declined=False)
    if args.yes or not sys.stdin.isatty() or confirm(update.path):
        write_text(update.path, update.text)
        return _Written(update.path, diff, written=True, declined=False)
    return _Written(update.path, diff, written=False, declined=True)


def _print_summary(cal: Calibration) -> None:
    from annotator.calibration.report import summary_lines

    for line in summary_lines(cal):
        print(line)


def _what_became(written: _Written | None, report_dir: Path) -> str:
    """The end of the last line: where the rig went."""
    if written is None:
        return f"rig section in {report_dir / 'rig.yaml'} (use --dataset DS to write it)"
    if written.written:
        return f"wrote the rig into {written.path}"
    return "dataset.yaml not written" if written.diff else "dataset.yaml unchanged"
