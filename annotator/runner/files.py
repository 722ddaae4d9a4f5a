"""Files as bytes: what travels between the driver and the Ray workers.

Paths are relative to a dataset folder and written with ``/``; a path that is absolute or
climbs out of the folder (``..``) is refused on both sides, so that a worker's answer can
never write outside the dataset.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from annotator.dataset import Dataset
from annotator.errors import UserError
from annotator.io.atomic import write_bytes
from annotator.markers.dictionary import PREDEFINED_PREFIX

#: Files by relative path; ``None`` (outputs only) = the file is to be deleted.
Files = dict[str, bytes]
Outputs = dict[str, bytes | None]


def relative(root: str | Path, rel: str) -> Path:
    """``root / rel`` for a relative path that stays inside ``root`` (ValueError otherwise)."""
    pure = PurePosixPath(rel)
    if not rel or pure.is_absolute() or ".." in pure.parts or "\\" in rel:
        raise ValueError(f"not a path inside the dataset folder: {rel!r}")
    return Path(root, *pure.parts)


def dictionary_files(ds: Dataset) -> list[Path]:
    """The dataset's marker dictionary file, when it names one rather than a predefined
    dictionary."""
    return [] if ds.dictionary.startswith(PREDEFINED_PREFIX) else [Path(ds.dictionary)]


def description_files(ds: Dataset) -> list[str]:
    """What every scene's work depends on besides the scene: dataset.yaml, a custom marker
    dictionary file, each object's object.yaml and mesh, and the empty bin's depth map
    (``rig.depth.background``)."""
    root = ds.root
    paths = [root / "dataset.yaml", *dictionary_files(ds)]
    for name in sorted(ds.objects):
        obj = ds.objects[name]
        paths += [obj.folder / "object.yaml", obj.mesh_path]
    if ds.rig.depth is not None and ds.rig.depth.background is not None:
        paths.append(root / ds.rig.depth.background)
    out = []
    for path in paths:
        rel = os.path.relpath(path, root)
        if rel.startswith(".."):
            raise UserError(
                "is outside the dataset folder: it cannot be sent to Ray workers "
                "(copy it into the dataset)",
                path=path,
            )
        out.append(PurePosixPath(Path(rel)).as_posix())
    return out


def read_files(root: str | Path, rels: Iterable[str]) -> Files:
    """The files among ``rels`` that exist under ``root``, as bytes (missing ones left out).

    Raises UserError naming a file that exists but cannot be read."""
    files: Files = {}
    for rel in rels:
        path = relative(root, rel)
        try:
            files[rel] = path.read_bytes()
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
            continue
        except OSError as exc:
            raise UserError(f"cannot read ({exc.strerror or exc})", path=path) from None
    return files


@dataclass(frozen=True)
class Bundle:
    """Files shipped once and unpacked once per worker, named by a digest of their content."""

    files: Files
    digest: str

    @classmethod
    def read(cls, root: str | Path, rels: Iterable[str]) -> Bundle:
        """Read ``rels`` under ``root``; a missing file is an error here (the description
        was loaded from them a moment ago)."""
        rels = list(rels)
        files = read_files(root, rels)
        for rel in rels:
            if rel not in files:
                raise UserError("file is missing", path=relative(root, rel))
        return cls(files, digest(files))


def digest(files: Mapping[str, bytes]) -> str:
    """SHA-256 of the files' paths and contents."""
    h = hashlib.sha256()
    for rel in sorted(files):
        h.update(rel.encode() + b"\0")
        h.update(hashlib.sha256(files[rel]).digest())
    return h.hexdigest()


def materialise(root: Path, files: Mapping[str, bytes]) -> None:
    """Write ``files`` under ``root`` (a worker's private folder: plain writes)."""
    for rel, data in files.items():
        path = relative(root, rel)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)


def collect(root: Path, specs: Iterable[str]) -> Outputs:
    """The outputs ``specs`` name (see :meth:`DistributableJob.output_files`) as found under
    ``root``: bytes, or None for a file that is not there; ``folder/`` gives every file
    under it, in sorted order."""
    out: Outputs = {}
    for spec in specs:
        if spec.endswith("/"):
            folder = relative(root, spec.rstrip("/"))
            if folder.is_dir():
                for path in sorted(p for p in folder.rglob("*") if p.is_file()):
                    out[path.relative_to(root).as_posix()] = path.read_bytes()
            continue
        path = relative(root, spec)
        out[spec] = path.read_bytes() if path.is_file() else None
    return out


def write_outputs(root: str | Path, outputs: Mapping[str, bytes | None]) -> None:
    """Write a task's outputs under ``root`` atomically, in their order, then delete the files
    marked None (so that a file naming another, like annotation.json its mask, is in place
    before the old one goes). Raises UserError (WriteError) naming a file it cannot write."""
    for rel, data in outputs.items():
        if data is not None:
            write_bytes(relative(root, rel), data)
    for rel, data in outputs.items():
        if data is None:
            path = relative(root, rel)
            try:
                path.unlink(missing_ok=True)
            except OSError as exc:
                raise UserError(f"cannot delete ({exc.strerror or exc})", path=path) from None
