"""Ground-truth 6D poses for bin-picking scenes, and their symmetry-aware evaluation.

``import annotator`` gives what a script needs; each name is imported on first use, so that
importing the package costs nothing. The ``annotator`` command is a thin layer over these
same functions: the same options give the same numbers.

>>> import annotator
>>> ds = annotator.load_dataset("sample_scenes")
>>> sorted(ds.objects)
['bracket', 'brick', 'cylinder']

The records are dataclasses (:class:`Dataset`, :class:`SceneAnnotation`,
:class:`GroundTruth`, :class:`EvaluationReport`...); lengths are millimetres and a pose maps
model to camera, ``x_cam = R @ x_model + t`` (docs/FORMAT.md).

The public names are those ``__init__.pyi`` imports, the one list of them: the stub gives a
type checker their types (it ships with ``py.typed``) and gives this module, which reads it
once, where each name lives, for the lazy import here and ``__all__``. A name is made public
by adding it to the stub.
"""

from __future__ import annotations

import ast
import importlib
import warnings
from pathlib import Path
from typing import Any


def _public_names() -> dict[str, str]:
    """Public name -> the module that defines it, as ``__init__.pyi`` imports them (``from
    module import (name as name, ...)``)."""
    stub = ast.parse(Path(__file__).with_suffix(".pyi").read_text(encoding="utf-8"))
    return {
        alias.asname or alias.name: node.module
        for node in stub.body
        if isinstance(node, ast.ImportFrom) and node.module
        for alias in node.names
    }


#: Public name -> the module that defines it.
_HOMES = _public_names()

#: Names of an earlier release -> their new name (they still work, with a DeprecationWarning).
_RENAMED = {
    "Settings": "AnnotateSettings",
    "Options": "EvaluationSettings",
    "EvaluationOptions": "EvaluationSettings",
    "Report": "EvaluationReport",
    "Results": "PoseResults",
    "SynthConfig": "SynthSettings",
    "ingest_scene": "ingest_recording",
}

__all__ = sorted(_HOMES)


def __getattr__(name: str) -> Any:
    if name in _RENAMED or name == "FLAGS":
        new = _RENAMED.get(name, "Flag")
        warnings.warn(
            f"annotator.{name} is now annotator.{new}"
            + (" (list(annotator.Flag) for every flag)" if name == "FLAGS" else ""),
            DeprecationWarning,
            stacklevel=2,
        )
        value = __getattr__(new)
        return tuple(value) if name == "FLAGS" else value
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'annotator' has no attribute {name!r}")
    value = getattr(importlib.import_module(home), name)
    globals()[name] = value  # the next access does not come here
    return value


def __dir__() -> list[str]:
    return list(__all__)
