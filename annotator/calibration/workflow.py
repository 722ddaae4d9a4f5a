"""A rig calibrated from a captures folder, the whole ``annotator calibrate`` run short of
printing and asking: :func:`calibrate_rig` (captures -> detection -> the joint solve and its
distortion model -> the checks -> the report folder -> ``dataset.yaml``).

The single solve is :func:`annotator.calibration.model_choice.calibrate_and_assess` (over
:func:`annotator.calibration.rig.solve_rig`); this module finds what it starts from (the
board, the captures in rig order, the depth section, the detections) and what becomes of
its result (:class:`CalibrationSummary`).
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from annotator.calibration.board import BOARD_FILE, BoardSpec, read_board_yaml
from annotator.calibration.caliscope import find_session, read_board_toml
from annotator.calibration.captures import (
    IMAGE_SUFFIXES,
    REPORT_FOLDER,
    Captures,
    find_rig_captures,
)
from annotator.calibration.checks import what_to_try
from annotator.calibration.detect import CapturesDetection, detect_captures
from annotator.calibration.model_choice import CANDIDATES, calibrate_and_assess
from annotator.calibration.outputs import DatasetUpdate, dataset_update, write_report_folder
from annotator.calibration.records import Calibration, CalibrationSettings, View
from annotator.calibration.report import report_dict, summary_lines
from annotator.calibration.rig_yaml import existing_rig, read_dataset_doc
from annotator.dataset.model import DepthSpec
from annotator.errors import UserError
from annotator.io.atomic import write_text

#: The distortion models ``dist_coeffs`` may name; ``auto``: the held-out error's choice.
DistCoeffs = Literal["auto", "2", "4", "5", "8"]


@dataclass
class CalibrationSummary:
    """What :func:`calibrate_rig` found and wrote; :meth:`to_json` is ``annotator calibrate
    --json``.

    Attributes:
        calibration: The calibration (cameras, shots, held-out error, readings, problems:
            why the rig must not be written, empty if it may).
        board: The board.
        captures: The captures, in rig order.
        detection: Every camera's detection in every shot.
        depth: The depth section written with the rig (None: none).
        report: The report folder (report.json, coverage pictures, rig.yaml).
        dataset_yaml: The dataset.yaml the rig goes into (None: only the report).
        update: Its new text and diff (None: no dataset, or a rig that does not hold
            together).
        written: Whether dataset.yaml was written; ``declined``: the user said no.

    :func:`calibrate_rig`'s example makes one from synthetic shots (a calibration takes
    seconds); every summary answers the one protocol:

    >>> from annotator.summary import StageSummary
    >>> issubclass(CalibrationSummary, StageSummary)
    True
    """

    calibration: Calibration
    board: BoardSpec
    captures: Captures
    detection: CapturesDetection
    depth: DepthSpec | None
    report: Path
    dataset_yaml: Path | None = None
    update: DatasetUpdate | None = None
    written: bool = False
    declined: bool = False
    details: dict[str, Any] = field(default_factory=dict)

    @property
    def holds(self) -> bool:
        """Whether the rig holds together (:mod:`annotator.calibration.checks`)."""
        return not self.calibration.problems

    @property
    def advice(self) -> str:
        """One line of what to try, for a rig that does not hold together."""
        return what_to_try(self.calibration.problems, self.captures.cameras)

    def write(self, *, confirm: Callable[[Path], bool] | None = None) -> None:
        """Write the rig into dataset.yaml (if ``confirm``, given its path, says yes);
        nothing when it already has this rig or the rig does not hold together."""
        if self.update is None or not self.update.diff:
            return
        if confirm is None or confirm(self.update.path):
            write_text(self.update.path, self.update.text)
            self.written = True
        else:
            self.declined = True

    def preview(self) -> str:
        """What is shown before asking to write: the calibration's summary, then the diff of
        dataset.yaml (or that it already has this rig)."""
        lines = summary_lines(self.calibration)
        if self.holds and self.update is not None:
            diff = self.update.diff
            lines.append(
                diff.removesuffix("\n")
                if diff
                else f"{self.update.path} already has this rig: nothing to write"
            )
        return "\n".join(lines)

    def counts(self) -> dict[str, int]:
        return {
            "cameras": len(self.calibration.cameras),
            "problems": len(self.calibration.problems),
            "written": int(self.written),
        }

    def warnings(self) -> list[str]:
        """For a rig that does not hold together: each check that failed, then what to try."""
        if self.holds:
            return []
        path = self.dataset_yaml
        where = f"{path}: not written: " if path is not None else ""
        return [f"error: {where}{p}" for p in self.calibration.problems] + [f"error: {self.advice}"]

    def written_paths(self) -> list[Path]:
        paths = [self.report]
        return paths + [self.update.path] if self.written and self.update is not None else paths

    def exit_status(self) -> int:
        return 1 if not self.holds or self.declined else 0

    def text(self) -> str:
        """The last line: the RMS, the held-out transfer error, where the rig went."""
        cal = self.calibration
        held = cal.held_out
        transfer = (
            ""
            if held is None or len(cal.cameras) < 2 or held.median_px != held.median_px
            else f", held-out transfer error {held.median_px:.2f} px median"
        )
        head = f"calibrate: RMS {cal.rms_px:.3f} px{transfer}; report in {self.report}; "
        if not self.holds:
            path = self.dataset_yaml
            return (
                head
                + "the rig does not hold together: "
                + (f"{path} not written" if path is not None else "no rig.yaml")
            )
        if self.update is None:
            return head + (
                f"rig section in {self.report / 'rig.yaml'} (use --dataset DS to write it)"
            )
        if self.written:
            return head + f"wrote the rig into {self.update.path}"
        return head + ("dataset.yaml not written" if self.update.diff else "dataset.yaml unchanged")

    def to_json(self) -> dict[str, Any]:
        result = dict(self.details)
        if not self.holds:
            result.update(written=False, advice=self.advice)
            if self.dataset_yaml is not None:
                result["dataset_yaml"] = str(self.dataset_yaml)
        elif self.update is not None:
            result.update(
                dataset_yaml=str(self.update.path), diff=self.update.diff, written=self.written
            )
        return result


def calibrate_rig(
    captures: str | Path,
    *,
    dataset: str | Path | None = None,
    report: str | Path | None = None,
    board: str | Path | None = None,
    board_fields: Mapping[str, Any] | None = None,
    cameras: list[str] | None = None,
    depth_camera: str | None = None,
    depth_scale: float | None = None,
    dist_coeffs: DistCoeffs = "auto",
    folds: int = 5,
    stride: int | None = None,
    min_shots: int = 6,
    write: bool = True,
    quiet: bool = True,
    tell: Callable[[str], None] | None = None,
    warn: Callable[[str], None] | None = None,
) -> CalibrationSummary:
    """Calibrate the rig from the synchronised board shots in ``captures``
    (``CAPTURES/<camera>/<shot>.png``, or one video per camera), write the report into
    ``report`` (default ``CAPTURES/calibration_report``) and, with ``dataset``, the rig into
    ``dataset/dataset.yaml`` (created if missing, its other sections kept; with ``write``
    False it is left for :meth:`CalibrationSummary.write`). A rig that does not hold
    together is never written (``summary.holds``; the report is).

    >>> import tempfile
    >>> from pathlib import Path
    >>> from annotator.synthesis.board import CaptureSettings, write_captures
    >>> captures = Path(tempfile.mkdtemp()) / "captures"  # rendered ChArUco shots, 2 cameras
    >>> _ = write_captures(CaptureSettings(shots=8, size=(640, 480), supersample=1), captures)
    >>> rig = calibrate_rig(captures, write=False)  # write=True: into --dataset's dataset.yaml
    >>> [c["name"] for c in rig.to_json()["cameras"]], rig.to_json()["rms_px"] < 0.5
    (['left', 'right'], True)
    >>> rig.exit_status(), rig.warnings(), rig.text().startswith("calibrate: RMS")
    (0, [], True)

    Args:
        board: The board description (YAML; default ``CAPTURES/board.yaml``).
        board_fields: :class:`~annotator.calibration.board.BoardSpec` fields that override
            the file's.
        cameras: Camera folders to use, in rig order (default: the existing rig's order,
            else sorted); the first is the rig frame.
        depth_camera, depth_scale: The depth section (default: kept from the dataset).
        dist_coeffs: The distortion model's coefficients, or ``auto`` (4 or 5, by the
            held-out error over ``folds`` folds).
        stride: Video captures: every ``stride``-th frame is a shot (default 10; a caliscope
            session's sync indices: 1).
        min_shots: Usable shots each camera needs.
        tell: Given the lines worth saying as the work goes (the videos' pairing, inverted
            boards, how boards that read only flipped were read).
        warn: Given a warning (the rig frame moves to another camera); default: ignored.

    Raises:
        UserError: bad captures, board or options; the board in no image; too few shots.

    Over 80 lines: the documentation of the options `annotator calibrate` passes through,
    and its example; the steps themselves are each a function.
    """
    say = tell or (lambda line: None)
    root = Path(captures)
    report_dir = Path(report) if report else root / REPORT_FOLDER
    if report:
        _check_report_dir(report_dir, root)
    session = find_session(root) if root.is_dir() else None
    spec = resolve_board(
        root, board, board_fields or {}, session.board if session is not None else None
    )
    ds_yaml, old_text, old_doc, old_rig = _target(dataset)
    caps = find_rig_captures(
        root,
        cameras=cameras,
        rig_cameras=old_rig["cameras"],
        ignore=[report_dir],
        stride=stride,
        rig_source=ds_yaml,
    )
    rig_cameras = old_rig["cameras"]
    if rig_cameras and cameras is not None and caps.cameras[0] != rig_cameras[0] and warn:
        warn(
            f"the rig frame changes from camera {rig_cameras[0]} to {caps.cameras[0]}: poses "
            f"already in {dataset} (gt.json, annotation.json) stay in the old frame"
        )
    depth = _depth(depth_camera, depth_scale, caps.cameras, old_rig, ds_yaml)
    found = _detect(caps, spec, old_rig["sizes"], ds_yaml, quiet=quiet)
    for line in capture_lines(caps, found):
        say(line)
    auto = dist_coeffs == "auto"
    cal = calibrate_and_assess(
        found.views,
        cameras=caps.cameras,
        sizes=found.sizes,
        shots=caps.shots,
        board=spec,
        options=CalibrationSettings(
            min_shots=min_shots, dist_coeffs=5 if auto else int(dist_coeffs)
        ),
        candidates=CANDIDATES if auto else (int(dist_coeffs),),
        folds=folds,
        where={c: caps.folder(c) for c in caps.cameras},
    )
    for reading in cal.readings.cameras if cal.readings is not None else []:
        if reading.reason:
            say(reading.reason)
    flipped = list(cal.readings.mirrored) if cal.readings is not None else []
    rig = write_report_folder(
        report_dir, cal, spec, captures=caps, depth=depth, flipped=flipped, old_doc=old_doc
    )
    details = report_dict(cal, spec, captures=caps, flipped=flipped)
    details["report"] = str(report_dir)
    summary = CalibrationSummary(
        cal, spec, caps, found, depth, report_dir, ds_yaml, details=details
    )
    if ds_yaml is not None and summary.holds:
        summary.update = dataset_update(ds_yaml, old_text, rig)
        if write:
            summary.write()
    return summary


def _target(
    dataset: str | Path | None,
) -> tuple[Path | None, str | None, dict[str, Any] | None, dict[str, Any]]:
    """``dataset``'s dataset.yaml (None: no dataset), its text and mapping if it exists, and
    its rig's cameras, sizes and depth."""
    ds_yaml = Path(dataset) / "dataset.yaml" if dataset else None
    if ds_yaml is not None and Path(dataset).exists() and not Path(dataset).is_dir():  # type: ignore[arg-type]
        raise UserError("exists and is not a folder", path=dataset)
    old_text, old_doc = read_dataset_doc(ds_yaml) if ds_yaml else (None, None)
    return ds_yaml, old_text, old_doc, existing_rig(old_doc)


def _check_report_dir(report: Path, root: Path) -> None:
    """--report must not be the captures folder, a camera folder or inside one, nor a file
    of the captures: a report there would be read as captures next time, or drop a camera
    (a folder given as --report is not read as a camera)."""
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


def capture_lines(captures: Captures, found: CapturesDetection) -> list[str]:
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
    if captures.times:
        spread = max(
            max(captures.times[(c, s)] for c in captures.cameras)
            - min(captures.times[(c, s)] for c in captures.cameras)
            for s in captures.shots
        )
        text += f", the cameras' frames of a shot up to {1000 * spread:.0f} ms apart"
    if captures.unpaired:
        shown = ", ".join(str(f) for f in captures.unpaired[:6])
        text += (
            f"; {len(captures.unpaired)} frames of {ref} had no partner in every video and were "
            f"left out ({shown}{', ...' if len(captures.unpaired) > 6 else ''})"
        )
    return text + " (report.json lists each shot's frames)"


def resolve_board(
    root: Path,
    file: str | Path | None,
    overrides: Mapping[str, Any],
    recorded: Path | None = None,
) -> BoardSpec:
    """The board from ``file`` (else CAPTURES/board.yaml, else ``recorded``: the board file
    the recording came with, caliscope's charuco.toml) and ``overrides`` (which win)."""
    fields: dict[str, Any] = {}
    path = Path(file) if file else root / BOARD_FILE
    if file is None and not path.is_file() and recorded is not None:
        fields = {**read_board_toml(recorded), **overrides}
        try:
            return BoardSpec(**fields)
        except UserError as exc:
            raise UserError(exc.message, path=exc.path or recorded) from None
    if file or path.is_file():
        spec = read_board_yaml(path)
        fields = {k: getattr(spec, k) for k in BoardSpec.__dataclass_fields__}
        if not spec.has_markers:
            fields.pop("marker_mm")
    fields.update(overrides)
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
    depth_camera: str | None,
    depth_scale: float | None,
    cameras: tuple[str, ...],
    old_rig: dict[str, Any],
    ds_yaml: Path | None,
) -> DepthSpec | None:
    """The depth section to write: kept from the dataset, changed by the options."""
    if depth_camera is not None and depth_camera not in cameras:
        raise UserError(
            f"--depth-camera {depth_camera!r} is not one of the cameras ({', '.join(cameras)})"
        )
    if depth_scale is not None and not depth_scale > 0:
        raise UserError(f"--depth-scale must be positive (mm per unit), got {depth_scale}")
    old: dict[str, Any] = old_rig["depth"] or {}
    scale = depth_scale if depth_scale is not None else old.get("scale")
    if scale is None:
        if depth_camera is not None:
            raise UserError(
                "--depth-camera needs the depth maps' scale: add --depth-scale MM (mm per depth "
                "unit)" + (f"; {ds_yaml} has none" if ds_yaml else "")
            )
        return None
    camera = depth_camera or (old["camera"] if old.get("camera") in cameras else cameras[0])
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

    def bar(it: Iterator) -> Iterator:
        from tqdm import tqdm

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
