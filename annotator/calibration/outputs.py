"""What ``annotator calibrate`` writes: the report folder (``report.json``, the coverage
pictures, ``rig.yaml``) and the new text of ``dataset.yaml`` with its diff, which the command
shows before it writes."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from annotator.calibration.board import BoardSpec
from annotator.calibration.captures import Captures
from annotator.calibration.records import Calibration
from annotator.calibration.report import write_report
from annotator.calibration.rig_yaml import (
    keep_other_fields,
    rig_mapping,
    rig_yaml_text,
    updated_text,
)
from annotator.dataset.model import DepthSpec
from annotator.io.atomic import write_text
from annotator.io.documents import unified_diff


@dataclass(frozen=True)
class DatasetUpdate:
    """``dataset.yaml`` with the calibrated rig spliced in: its path, new text, and the diff
    from the old one (empty: the file already has this rig)."""

    path: Path
    text: str
    diff: str


def write_report_folder(
    folder: Path,
    cal: Calibration,
    board: BoardSpec,
    *,
    captures: Captures,
    depth: DepthSpec | None,
    flipped: Sequence[str],
    old_doc: dict[str, Any] | None,
) -> dict[str, Any]:
    """Write the report and ``rig.yaml`` into ``folder``; return the rig mapping (the old
    rig's other fields kept), for :func:`dataset_update`. A rig that does not hold together
    (``cal.problems``) gets no ``rig.yaml`` (one left by an earlier run is removed), so that
    none is copied from the report by mistake."""
    rig = keep_other_fields(rig_mapping(cal.rig_cameras, depth, flipped), old_doc)
    write_report(folder, cal, board, captures=captures, flipped=flipped)
    if cal.problems:
        (folder / "rig.yaml").unlink(missing_ok=True)
    else:
        write_text(folder / "rig.yaml", rig_yaml_text(rig))
    return rig


def dataset_update(path: Path, old_text: str | None, rig: dict[str, Any]) -> DatasetUpdate:
    """``path``'s text (``old_text``, None: no file yet) with ``rig`` as its rig block."""
    new_text = updated_text(old_text, rig, name=path.parent.resolve().name)
    return DatasetUpdate(path, new_text, unified_diff(old_text, new_text, path, label="calibrated"))
