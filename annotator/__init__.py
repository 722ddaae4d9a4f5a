"""Ground-truth 6D poses for bin-picking scenes, and their symmetry-aware evaluation.

``import annotator`` gives what a script needs; each name is imported on first use, so that
importing the package costs nothing. The ``annotator`` command is a thin layer over these
same functions: the same options give the same numbers.

>>> import annotator
>>> ds = annotator.load_dataset("sample_scenes")
>>> sorted(ds.objects)
['bracket', 'brick', 'cylinder']

The records are dataclasses (:class:`Dataset`, :class:`SceneAnnotation`,
:class:`GroundTruth`, :class:`Report`...); lengths are millimetres and a pose maps model to
camera, ``x_cam = R @ x_model + t`` (docs/FORMAT.md).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

#: Public name -> the module that defines it.
_HOMES = {
    # the dataset and its records
    "load_dataset": "annotator.dataset",
    "Dataset": "annotator.dataset",
    "Scene": "annotator.dataset",
    "ObjectModel": "annotator.dataset",
    "Rig": "annotator.dataset",
    "InstancePose": "annotator.dataset",
    "SceneAnnotation": "annotator.dataset.annotation",
    "InstanceAnnotation": "annotator.dataset.annotation",
    "SceneWarning": "annotator.dataset.annotation",
    "Flag": "annotator.dataset.annotation",
    "WarningKind": "annotator.dataset.annotation",
    "ReviewStatus": "annotator.dataset.review",
    "check_dataset": "annotator.dataset.check",
    # marker detection and auto-annotation
    "MarkerDetector": "annotator.detection",
    "annotate_scene": "annotator.annotation.scene",
    "Settings": "annotator.annotation.settings",
    "SceneResult": "annotator.annotation.scene",
    "annotate_dataset": "annotator.annotation.batch",
    "AnnotateSummary": "annotator.annotation.batch",
    "FLAGS": "annotator.annotation",
    # evaluation
    "read_ground_truth": "annotator.formats",
    "read_results": "annotator.formats",
    "annotations_as_results": "annotator.formats.ours",
    "GroundTruth": "annotator.formats.base",
    "Results": "annotator.formats.base",
    "evaluate": "annotator.evaluation.evaluate",
    "Options": "annotator.evaluation.evaluate",
    "Report": "annotator.evaluation.evaluate",
    # export
    "export_dataset": "annotator.formats.exporting",
    "ExportSummary": "annotator.formats.exporting",
    # errors
    "UserError": "annotator.errors",
}

__all__ = [
    "AnnotateSummary",
    "Dataset",
    "ExportSummary",
    "FLAGS",
    "Flag",
    "GroundTruth",
    "InstanceAnnotation",
    "InstancePose",
    "MarkerDetector",
    "ObjectModel",
    "Options",
    "Report",
    "Results",
    "ReviewStatus",
    "Rig",
    "Scene",
    "SceneAnnotation",
    "SceneResult",
    "SceneWarning",
    "Settings",
    "UserError",
    "WarningKind",
    "annotate_dataset",
    "annotate_scene",
    "annotations_as_results",
    "check_dataset",
    "evaluate",
    "export_dataset",
    "load_dataset",
    "read_ground_truth",
    "read_results",
]


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'annotator' has no attribute {name!r}")
    value = getattr(importlib.import_module(home), name)
    globals()[name] = value  # the next access does not come here
    return value


def __dir__() -> list[str]:
    return list(__all__)


if TYPE_CHECKING:
    from annotator.annotation import FLAGS
    from annotator.annotation.batch import AnnotateSummary, annotate_dataset
    from annotator.annotation.scene import SceneResult, annotate_scene
    from annotator.annotation.settings import Settings
    from annotator.dataset import Dataset, InstancePose, ObjectModel, Rig, Scene, load_dataset
    from annotator.dataset.annotation import (
        Flag,
        InstanceAnnotation,
        SceneAnnotation,
        SceneWarning,
        WarningKind,
    )
    from annotator.dataset.check import check_dataset
    from annotator.dataset.review import ReviewStatus
    from annotator.detection import MarkerDetector
    from annotator.errors import UserError
    from annotator.evaluation.evaluate import Options, Report, evaluate
    from annotator.formats import read_ground_truth, read_results
    from annotator.formats.base import GroundTruth, Results
    from annotator.formats.exporting import ExportSummary, export_dataset
    from annotator.formats.ours import annotations_as_results
