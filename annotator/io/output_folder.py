"""Folders a command creates as a whole (``export``, ``synth``, ``markers``): when one may be
written, and when ``--overwrite`` may replace it.

Rules, whatever the flags:

- OUT may not be what the command reads (the dataset, a mesh), nor lie inside it, nor contain
  it: replacing OUT would delete the user's data.
- An existing, non-empty OUT is replaced only with ``--overwrite``, and only if a previous run
  of the same command wrote it. Such folders carry a small manifest, ``.annotator-output.json``
  (``{"written_by": "annotator export"}``); anything else is refused.

The folder itself is then built with :func:`annotator.io.atomic.atomic_folder`, and
:func:`write_manifest` marks it before it takes OUT's place.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path

from annotator.errors import UserError
from annotator.io.atomic import write_json

MANIFEST = ".annotator-output.json"


def check_output_folder(
    out: str | Path, *, command: str, overwrite: bool, protect: Sequence[str | Path] = ()
) -> None:
    """Raise a one-line UserError unless ``annotator <command>`` may write ``out``.

    Args:
        out: The folder to create or replace.
        command: The subcommand writing it (``export``...), recorded in its manifest.
        overwrite: The user's ``--overwrite``.
        protect: Inputs that must survive (the dataset, a mesh): ``out`` may be none of them,
            nor inside one, nor contain one.
    """
    out = Path(out)
    real = Path(os.path.realpath(out))
    for p in protect:
        keep = Path(os.path.realpath(p))
        if real == keep:
            raise UserError(f"is the input {p} itself; choose another output folder", path=out)
        if keep in real.parents:
            raise UserError(f"lies inside the input {p}; choose a folder outside it", path=out)
        if real in keep.parents:
            raise UserError(f"contains the input {p}; choose a folder beside it", path=out)
    if not (out.exists() or out.is_symlink()):
        return
    if not out.is_dir():
        raise UserError("exists and is not a folder", path=out)
    if not any(out.iterdir()):
        return
    if not overwrite:
        raise UserError("exists and is not empty (use --overwrite to replace it)", path=out)
    owner = _written_by(out)
    if owner != f"annotator {command}":
        found = f"it was written by {owner}" if owner else f"it has no {MANIFEST}"
        raise UserError(
            f"--overwrite replaces only a folder that `annotator {command}` wrote, and {found}; "
            "remove it yourself or choose another folder",
            path=out,
        )


def write_manifest(folder: str | Path, *, command: str) -> None:
    """Mark ``folder`` as written by ``annotator <command>`` (see :func:`check_output_folder`)."""
    # No date in it: the same inputs must give the same bytes (``synth`` promises that).
    write_json(Path(folder) / MANIFEST, {"written_by": f"annotator {command}"})


def _written_by(folder: Path) -> str | None:
    try:
        doc = json.loads((folder / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    owner = doc.get("written_by") if isinstance(doc, dict) else None
    return owner if isinstance(owner, str) else None
