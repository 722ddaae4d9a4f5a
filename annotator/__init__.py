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

The public names are the keys of ``_HOMES`` below, the one list of them: it drives the lazy
import here and ``__all__``, and ``__init__.pyi`` (the types a checker reads, shipped with
``py.typed``) must import the same names from the same modules (``tests/test_api.py``
checks it).
"""

from __future__ import annotations

import importlib
import warnings
from typing import Any

#: Public name -> the module that defines it.
_HOMES = {
    # the dataset and its records
    "load_dataset": "annotator.dataset",
    "Dataset": "annotator.dataset",
    "Scene": "annotator.dataset",
    "ObjectModel": "annotator.dataset",
    "Rig": "annotator.dataset",
    "InstancePose": "annotator.dataset",
    "SceneAnnotation": "annotator.dataset.records",
    "InstanceAnnotation": "annotator.dataset.records",
    "MarkerUse": "annotator.dataset.figures",
    "Reprojection": "annotator.dataset.figures",
    "DepthCheck": "annotator.dataset.figures",
    "Occlusion": "annotator.dataset.figures",
    "SceneWarning": "annotator.dataset.figures",
    "DepthRegion": "annotator.dataset.figures",
    "Flag": "annotator.dataset.flags",
    "WarningKind": "annotator.dataset.flags",
    "ReviewStatus": "annotator.dataset.review",
    "check_dataset": "annotator.dataset.check",
    "CheckReport": "annotator.dataset.check",
    "Problem": "annotator.dataset",
    # sequences: synthetic ones, and recorded ones into a moving rig's dataset
    "SynthSettings": "annotator.synthesis.generate",
    "synthesize_sequences": "annotator.synthesis.sequence",
    "SequenceSummary": "annotator.synthesis.sequence",
    "ingest_recording": "annotator.ingest.scene",
    "IngestSummary": "annotator.ingest.scene",
    # marker detection and auto-annotation
    "MarkerDetector": "annotator.detection",
    "annotate_scene": "annotator.annotation.scene",
    "AnnotateSettings": "annotator.annotation.settings",
    "SceneResult": "annotator.annotation.scene",
    "annotate_dataset": "annotator.annotation.batch",
    "AnnotateSummary": "annotator.annotation.batch",
    # evaluation
    "read_ground_truth": "annotator.formats",
    "read_results": "annotator.formats",
    "annotations_as_results": "annotator.formats.ours",
    "GroundTruth": "annotator.formats.base",
    "PoseResults": "annotator.formats.base",
    "evaluate": "annotator.evaluation.evaluate",
    "EvaluationOptions": "annotator.evaluation.evaluate",
    "EvaluationReport": "annotator.evaluation.evaluate",
    "evaluate_dataset": "annotator.evaluation.dataset",
    "EvaluationSummary": "annotator.evaluation.dataset",
    "Bop24Scores": "annotator.evaluation.bop24",
    "CocoScores": "annotator.evaluation.coco",
    "symmetry_to_bop": "annotator.symmetry.classes",
    "symmetry_from_bop": "annotator.symmetry.classes",
    "bop_symmetries": "annotator.formats.bop_images",
    # physics: is the pile possible?
    "physics_of_dataset": "annotator.physics.dataset",
    "PhysicsSummary": "annotator.physics.dataset",
    "PhysicsSettings": "annotator.physics.check",
    "PhysicsCheck": "annotator.dataset.figures",
    # export
    "export_dataset": "annotator.export.dataset",
    "ExportSummary": "annotator.export.dataset",
    "scene_markers": "annotator.export.markers",
    "MarkerRegion": "annotator.export.markers",
    "fill_markers": "annotator.export.fill",
    # the other stages, each a dataset-level function and its summary
    "calibrate_rig": "annotator.calibration.workflow",
    "CalibrationSummary": "annotator.calibration.workflow",
    "measure_sites": "annotator.sites.survey",
    "SitesSummary": "annotator.sites.survey",
    "synthesize_scenes": "annotator.synthesis.scenes",
    "SynthesisSummary": "annotator.synthesis.scenes",
    "synthesize_twins": "annotator.twins.dataset",
    "TwinSummary": "annotator.twins.dataset",
    "compute_occlusion": "annotator.occlusion.dataset",
    "OcclusionSummary": "annotator.occlusion.dataset",
    "estimate_dataset": "annotator.estimation.dataset",
    "EstimateSummary": "annotator.estimation.dataset",
    # errors
    "UserError": "annotator.errors",
    "BadValue": "annotator.values",
}

#: Names of an earlier release -> their new name (they still work, with a DeprecationWarning).
_RENAMED = {
    "Settings": "AnnotateSettings",
    "Options": "EvaluationOptions",
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
