"""Exporting accepted scenes of one of our datasets into another format:
:func:`export_dataset`, what ``annotator export`` runs.

Which scenes go is decided by the reviews (:mod:`annotator.export.selection`); the writers
are :mod:`annotator.export.bop` and :mod:`annotator.export.sileane`, into a temporary folder
renamed at the end (never half an export). A scene whose inputs cannot be read is left out and named; the others are written.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from annotator.dataset import Dataset, as_dataset
from annotator.dataset.frames import frames_line
from annotator.errors import UserError
from annotator.export.fill import METHODS as FILLS
from annotator.export.options import (
    EXPORTS,
    LAYOUTS,
    POSES_FROM,
    ExportFormat,
    Layout,
    PosesFrom,
)
from annotator.export.selection import Selection, select_scenes
from annotator.io.atomic import atomic_folder
from annotator.io.output_folder import check_output_folder, write_manifest
from annotator.summary import failure_lines
from annotator.values import of_type


@dataclass
class ExportSummary:
    """What :func:`export_dataset` wrote; :meth:`to_json` is ``annotator export --json``.

    Attributes:
        format, out: The format and the folder written.
        exported: Scenes written.
        left_out: Scene id -> why it was left out by the reviews (pending, rejected...).
        failures: Scene id -> why it could not be read.
        markers_filled: With ``remove_markers``, the markers filled in over every exported
            image (a marker seen by two cameras counts twice); None without.
        markers_found_beyond: Markers a detector found reaching beyond where the exported
            poses put markers (a part without a pose, posed elsewhere, a marker glued off its
            site), masked and filled whole; None without.
        frames_left_out: An exported sequence's frames not exported -> why (not posed, with
            annotate's flags; rejected by a reviewer).

    >>> from pathlib import Path
    >>> s = ExportSummary("bop", Path("out"), exported=3, left_out={"000004": "pending"})
    >>> s.text()
    'export: 3 scenes written to out (bop); left out: 1 pending'
    >>> s.counts(), s.exit_status()
    ({'exported': 3, 'pending': 1}, 0)
    """

    format: str
    out: Path
    exported: int
    left_out: dict[str, str] = field(default_factory=dict)
    failures: dict[str, str] = field(default_factory=dict)
    markers_filled: int | None = None
    markers_found_beyond: int | None = None
    frames_left_out: dict[str, dict[str, str]] = field(default_factory=dict)

    def reasons(self) -> dict[str, int]:
        """How many scenes were left out for each reason (``unreadable`` for failures)."""
        out: dict[str, int] = {}
        for r in self.left_out.values():
            out[r] = out.get(r, 0) + 1
        if self.failures:
            out["unreadable"] = len(self.failures)
        return out

    def counts(self) -> dict[str, int]:
        return {"exported": self.exported, **self.reasons()}

    def warnings(self) -> list[str]:
        """The scenes that could not be read, then each sequence's frames left out."""
        return failure_lines(self.failures) + [
            f"scene {sid}: {frames_line(frames)}"
            for sid, frames in sorted(self.frames_left_out.items())
        ]

    def written_paths(self) -> list[Path]:
        return [self.out]

    def exit_status(self) -> int:
        return 1 if self.failures else 0

    def text(self) -> str:
        why = "; ".join(f"{n} {r}" for r, n in sorted(self.reasons().items()))
        filled = (
            f", {self.markers_filled} markers filled in"
            f" ({self.markers_found_beyond} beyond where the poses put them)"
            if self.markers_filled is not None
            else ""
        )
        return f"export: {self.exported} scenes written to {self.out} ({self.format}){filled}" + (
            f"; left out: {why}" if why else ""
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "format": self.format,
            "out": str(self.out),
            "exported": self.exported,
            "left_out": self.reasons(),
            "scenes_left_out": self.left_out,
            "failures": dict(sorted(self.failures.items())),
            "markers_filled": self.markers_filled,
            "markers_found_beyond": self.markers_found_beyond,
            "frames_left_out": self.frames_left_out,
        }


def export_dataset(
    ds: Dataset | str | Path,
    out: str | Path,
    *,
    format: ExportFormat,
    cameras: Sequence[str] | None = None,
    include_pending: bool = False,
    drop_rejected_instances: bool = False,
    poses: PosesFrom = "annotation",
    layout: Layout = "scenewise",
    overwrite: bool = False,
    progress: Callable[[int], Callable[[], None]] | None = None,
    remove_markers: bool = False,
    fill: str = "surface",
    sensors: bool = False,
) -> ExportSummary:
    """Export the accepted scenes of ``ds`` into the new folder ``out`` (or, with
    ``overwrite``, one an earlier export wrote).

    >>> import tempfile
    >>> out = Path(tempfile.mkdtemp()) / "bop"
    >>> s = export_dataset("sample_scenes", out, format="bop", include_pending=True, poses="gt")
    >>> s.exported, (out / "test_targets_bop19.json").is_file()
    (4, True)

    Args:
        format: ``bop`` or ``sileane``.
        cameras: Rig cameras to export (BOP; default all).
        include_pending: Also scenes not reviewed yet.
        drop_rejected_instances: Export scenes with rejected instances, without them.
        poses: ``annotation`` (annotation.json with the review's repairs) or ``gt``.
        layout: BOP only: ``scenewise``, ``imagewise`` or ``webdataset``.
        progress: Given the number of scenes, returns what to call after each.
        remove_markers: Write the intensity images with the markers filled in, and where
            they were (``mask_markers``; see :mod:`annotator.export.removal`). Depth is left
            as measured.
        fill: How marker regions are filled: ``surface`` (from the pixels of the same
            surface around them) or ``telea`` (OpenCV's inpainting); see
            :mod:`annotator.export.fill`.
        sensors: BOP only: every camera a sensor of BOP's multi-sensor layout
            (``gray_<camera>/``, ``scene_gt_<camera>.json``...), even a single one; see
            :func:`annotator.export.bop.export_bop`.

    Raises:
        UserError: a bad option, an output folder that may not be written, or no scene to
            export.
    """
    # What `annotator export` refuses, refused here in the same words.
    ds = as_dataset(ds, name="ds")
    of_type(out, (str, Path), name="out", what="a folder (str or Path)")
    chosen = _check_options(
        ds, format=format, poses=poses, layout=layout, sensors=sensors, fill=fill, cameras=cameras
    )
    out = Path(out)
    _check_writable(out, ds, overwrite)
    sel = select_scenes(
        ds,
        include_pending=include_pending,
        drop_rejected_instances=drop_rejected_instances,
        poses_from=poses,
    )
    if not sel.scenes:
        raise sel.nothing_error(ds, include_pending=include_pending, what="to export")
    tick = progress(len(sel.scenes)) if progress else None
    filled: list[tuple[int, int]] = []
    markers: dict[str, Any] = {"remove_markers": remove_markers, "fill": fill}
    markers["markers_filled"] = lambda n, elsewhere: filled.append((n, elsewhere))
    with atomic_folder(out) as tmp:
        write_manifest(tmp, command="export")
        unreadable = _write(format, ds, sel, tmp, chosen, tick, layout, sensors, markers)
    summary = _summary(format, out, sel, unreadable)
    if remove_markers:
        summary.markers_filled = sum(n for n, _ in filled)
        summary.markers_found_beyond = sum(e for _, e in filled)
    return summary


def _check_options(
    ds: Dataset,
    *,
    format: str,
    poses: str,
    layout: str,
    sensors: bool,
    fill: str,
    cameras: Sequence[str] | None,
) -> list[str]:
    """The cameras to export, once every option is known to fit ``ds`` and each other."""
    if format not in EXPORTS:
        raise UserError(f"unknown format {format!r} (expected one of {', '.join(EXPORTS)})")
    if poses not in POSES_FROM:
        raise UserError(f"unknown poses {poses!r} (expected one of {', '.join(POSES_FROM)})")
    if layout not in LAYOUTS:
        raise UserError(f"unknown layout {layout!r} (expected one of {', '.join(LAYOUTS)})")
    if layout != "scenewise" and format != "bop":
        raise UserError("--layout is for --format bop")
    if sensors and format != "bop":
        raise UserError("--sensors is for --format bop")
    if format == "sileane" and ds.rig.moving:
        raise UserError(
            "the Siléane format holds one shot per scene: export a moving rig's sequences "
            "with --format bop (one BOP image per frame)",
            path=ds.root,
        )
    if fill not in FILLS:
        raise UserError(f"unknown marker fill {fill!r} (expected one of {', '.join(FILLS)})")
    names = [c.name for c in ds.rig.cameras]
    chosen = list(cameras) if cameras else names
    unknown = [c for c in chosen if c not in names]
    if unknown:
        raise UserError(f"unknown camera(s) {', '.join(unknown)} (the rig has {', '.join(names)})")
    return chosen


def _write(
    format: str,
    ds: Dataset,
    sel: Selection,
    tmp: Path,
    cameras: list[str],
    progress: Callable[[], None] | None,
    layout: Layout,
    sensors: bool,
    markers: dict[str, Any],
) -> dict[str, str]:
    """Write the selected scenes into ``tmp`` with the format's writer; the scenes whose
    inputs could not be read, with why."""
    # Imported here: the writers load the renderer, which listing the formats need not.
    if format == "bop":
        from annotator.export.bop import export_bop

        return export_bop(
            ds,
            sel.scenes,
            tmp,
            cameras=cameras,
            progress=progress,
            layout=layout,
            sensors=sensors,
            **markers,
        )
    from annotator.export.sileane import export_sileane

    return export_sileane(ds, sel.scenes, tmp, cameras=cameras, progress=progress, **markers)


def _check_writable(out: Path, ds: Dataset, overwrite: bool) -> None:
    check_output_folder(out, command="export", overwrite=overwrite, protect=[ds.root])
    parent = out.resolve().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create the output folder ({exc.strerror})", path=out) from None
    if not os.access(parent, os.W_OK):
        raise UserError("the output folder is not writable", path=out)


def _summary(format: str, out: Path, sel: Selection, unreadable: dict[str, str]) -> ExportSummary:
    # Scenes that could not be read (corrupt annotation, review, image or depth) are named
    # and make the command's exit status 1; the rest of the export is complete.
    failures = {
        sid: r[len("error: ") :] for sid, r in sel.skipped.items() if r.startswith("error: ")
    }
    failures.update(unreadable)
    left_out = {sid: r for sid, r in sel.skipped.items() if sid not in failures}
    frames = {sid: f for sid, f in sel.frames_left.items() if sid not in failures}
    return ExportSummary(
        format,
        out,
        len(sel.scenes) - len(unreadable),
        left_out,
        failures,
        frames_left_out=frames,
    )
