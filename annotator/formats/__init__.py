"""Dataset formats: ours (docs/FORMAT.md), BOP, and the paper's own (Siléane).

One module per format, each with the same functions, found by name in :data:`FORMATS`:

- ``detect(path) -> bool``: is this folder in the format?
- ``read_ground_truth(path, *, symmetry=None) -> GroundTruth``: true poses, occlusion rates
  and the objects' pose spaces, in millimetres;
- ``read_results(path, gt) -> PoseResults``: results to score, in millimetres.

Each module also holds its format's symmetry mapping. Adding a format is adding a module here
(and, to export to it, a writer in :mod:`annotator.export`).
"""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

from annotator.errors import UserError
from annotator.formats import bop, ours, sileane
from annotator.formats.base import GroundTruth, PoseResults
from annotator.values import of_type

FORMATS: dict[str, ModuleType] = {m.NAME: m for m in (ours, bop, sileane)}


def get_format(name: str) -> ModuleType:
    """The format module called ``name`` (UserError listing the known ones otherwise)."""
    if name not in FORMATS:
        raise UserError(f"unknown format {name!r} (expected one of {', '.join(FORMATS)})")
    return FORMATS[name]


def detect_format(path: str | Path) -> ModuleType:
    """The format of the dataset folder ``path`` (UserError if none matches)."""
    path = Path(of_type(path, (str, Path), name="path", what="a dataset folder (str or Path)"))
    if not path.is_dir():
        raise UserError("dataset folder does not exist", path=path)
    for module in FORMATS.values():
        if module.detect(path):
            return module
    raise UserError(
        "not a dataset: no dataset.yaml (ours), models/models_info.json (BOP) or gt/ (Siléane)",
        path=path,
    )


def read_ground_truth(path: str | Path, *, symmetry: str | None = None) -> GroundTruth:
    """The true poses of the dataset at ``path``, whatever its format (:func:`detect_format`):
    ours, BOP or the paper's. ``symmetry``: the class for a Siléane folder with only a mesh.

    >>> gt = read_ground_truth("sample_scenes")
    >>> gt.unit, sorted(gt.scenes)
    ('mm', ['000000', '000001', '000002', '000003'])
    """
    return detect_format(path).read_ground_truth(Path(path), symmetry=symmetry)


def read_results(path: str | Path, gt: GroundTruth) -> PoseResults:
    """Results to score against ``gt``: a BOP CSV or a folder of per-scene JSON lists, in
    ``gt``'s unit.

    >>> import json, tempfile
    >>> gt = read_ground_truth("sample_scenes")
    >>> folder = Path(tempfile.mkdtemp())
    >>> pose = {"object": "brick", "R": [1, 0, 0, 0, 1, 0, 0, 0, 1], "t": [0, 0, 500], "score": 1}
    >>> _ = (folder / "000000.json").write_text(json.dumps([pose]))
    >>> sorted(read_results(folder, gt).scenes)
    ['000000']
    """
    of_type(path, (str, Path), name="path", what="a results file or folder (str or Path)")
    of_type(gt, GroundTruth, name="gt", what="a GroundTruth (annotator.read_ground_truth)")
    return get_format(gt.format).read_results(Path(path), gt)
