"""Outputs never destroy inputs: when a command may write a folder or a file.

Folders a command creates as a whole (``export``, ``synth``, ``markers``), whatever the flags:

- OUT may not be what the command reads (the dataset, a mesh), nor lie inside it, nor contain
  it: replacing OUT would delete the user's data.
- An existing, non-empty OUT is replaced only with ``--overwrite``, and only if a previous run
  of the same command wrote it. Such folders carry a small manifest, ``.annotator-output.json``
  (``{"written_by": "annotator export"}``); anything else is refused.

The folder itself is then built with :func:`annotator.io.atomic.atomic_folder`, and
:func:`write_manifest` marks it before it takes OUT's place.

Files a command writes (``estimate OUT.csv``, ``evaluate --json``/``--plot``), checked by
:func:`check_output_files` before anything is read or computed:

- a file may not be one the command reads (``--results``), nor lie inside a folder it reads
  (a results folder), nor be an existing file of a dataset it reads (``dataset.yaml``, an
  image), nor lie in a dataset's ``scenes/`` or ``objects/`` (where a new file would be read
  as the dataset's own: a ``gt.json``, say);
- two outputs of one command may not be the same file;
- a file that exists already is replaced only with ``--overwrite``.

A new file beside a dataset's own files (``DS/ppf.csv``) is allowed.
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


def check_output_files(
    outputs: Sequence[tuple[str, str | Path | None]],
    *,
    inputs: Sequence[str | Path | None] = (),
    datasets: Sequence[str | Path | None] = (),
    overwrite: bool = False,
) -> None:
    """Raise a one-line UserError (naming the file) unless every output file may be written
    without touching what the command reads (the rules in the module docstring).

    Args:
        outputs: (option, path) of each file the command will write (``("--json",
            "r.json")``); a None path is not written and not checked.
        inputs: Files or folders the command reads (None: not given).
        datasets: Dataset folders the command reads (ours, BOP, Siléane; None: not given).
        overwrite: The user's ``--overwrite``: without it an existing file is refused (a
            results file of the user's is never replaced unasked).

    >>> check_output_files([("OUT", "sample_scenes/dataset.yaml")], datasets=["sample_scenes"])
    Traceback (most recent call last):
    ...
    annotator.errors.UserError: sample_scenes/dataset.yaml: OUT would write over a file of the dataset sample_scenes; choose a new file outside it
    """
    seen: dict[Path, str] = {}
    for option, out in outputs:
        if out is None:
            continue
        real = Path(os.path.realpath(out))
        if real in seen:
            raise UserError(f"{option} is also {seen[real]}: give each its own file", path=out)
        seen[real] = option
        for p in inputs:
            if p is None:
                continue
            keep = Path(os.path.realpath(p))
            if real == keep:
                raise UserError(f"{option} is the input {p} itself; choose another file", path=out)
            if keep in real.parents:
                raise UserError(
                    f"{option} lies inside the input {p}; choose a file outside it", path=out
                )
        for d in datasets:
            if d is None:
                continue
            root = Path(os.path.realpath(d))
            if real == root:
                raise UserError(f"{option} is the dataset {d} itself; give a file name", path=out)
            if root not in real.parents:
                continue
            if real.exists() or real.is_symlink():
                raise UserError(
                    f"{option} would write over a file of the dataset {d}; choose a new file "
                    "outside it",
                    path=out,
                )
            inside = real.relative_to(root).parts[0]
            if inside in ("scenes", "objects"):
                raise UserError(
                    f"{option} lies in {d}/{inside}, where the dataset's own files are; "
                    "choose a file outside it",
                    path=out,
                )
        if not overwrite and (real.exists() or Path(out).is_symlink()) and not real.is_dir():
            raise UserError(f"{option} exists already (pass --overwrite to replace it)", path=out)


def check_pictures_folder(out: str | Path, *, option: str, datasets: Sequence[str | Path]) -> None:
    """Raise a one-line UserError if pictures written into ``out`` could land among a
    dataset's own files: ``out`` is a dataset read, or lies in its ``scenes/`` or
    ``objects/`` (a scene folder holds ``<camera>.png`` files a picture could replace)."""
    real = Path(os.path.realpath(out))
    for d in datasets:
        root = Path(os.path.realpath(d))
        if real == root:
            raise UserError(
                f"{option} is the dataset {d} itself; choose a folder of its own", path=out
            )
        if root in real.parents and real.relative_to(root).parts[0] in ("scenes", "objects"):
            raise UserError(
                f"{option} lies in {d}/{real.relative_to(root).parts[0]}, where the dataset's "
                "own files are; choose a folder outside it",
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
