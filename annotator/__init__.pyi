"""The public names of ``import annotator``, the one list of them, and their types:
``__init__.py`` reads this file for where each name lives. A name is made public here."""

from annotator.annotation.batch import (
    AnnotateSummary as AnnotateSummary,
    annotate_dataset as annotate_dataset,
)
from annotator.annotation.scene import (
    SceneResult as SceneResult,
    annotate_scene as annotate_scene,
)
from annotator.annotation.settings import (
    AnnotateSettings as AnnotateSettings,
)

# the other stages, each a dataset-level function and its summary
from annotator.calibration.workflow import (
    CalibrationSummary as CalibrationSummary,
    calibrate_rig as calibrate_rig,
)
from annotator.dataset import (
    Dataset as Dataset,
    InstancePose as InstancePose,
    ObjectModel as ObjectModel,
    Problem as Problem,
    Rig as Rig,
    Scene as Scene,
    load_dataset as load_dataset,
)
from annotator.dataset.check import (
    CheckReport as CheckReport,
    check_dataset as check_dataset,
)
from annotator.dataset.figures import (
    DepthCheck as DepthCheck,
    DepthRegion as DepthRegion,
    MarkerUse as MarkerUse,
    Occlusion as Occlusion,
    PhysicsCheck as PhysicsCheck,
    Reprojection as Reprojection,
    SceneWarning as SceneWarning,
)
from annotator.dataset.flags import Flag as Flag, WarningKind as WarningKind
from annotator.dataset.records import (
    InstanceAnnotation as InstanceAnnotation,
    SceneAnnotation as SceneAnnotation,
)
from annotator.dataset.review import (
    ReviewStatus as ReviewStatus,
)
from annotator.detection import (
    MarkerDetector as MarkerDetector,
)
from annotator.errors import (
    UserError as UserError,
)
from annotator.estimation.dataset import (
    EstimateSummary as EstimateSummary,
    estimate_dataset as estimate_dataset,
)
from annotator.evaluation.bop24 import (
    Bop24Scores as Bop24Scores,
)
from annotator.evaluation.coco import (
    CocoScores as CocoScores,
)
from annotator.evaluation.dataset import (
    EvaluationSummary as EvaluationSummary,
    evaluate_dataset as evaluate_dataset,
)
from annotator.evaluation.evaluate import (
    EvaluationReport as EvaluationReport,
    EvaluationSettings as EvaluationSettings,
    evaluate as evaluate,
)
from annotator.export.dataset import (
    ExportSummary as ExportSummary,
    export_dataset as export_dataset,
)
from annotator.export.fill import fill_markers as fill_markers
from annotator.export.markers import MarkerRegion as MarkerRegion, scene_markers as scene_markers
from annotator.formats import (
    read_ground_truth as read_ground_truth,
    read_results as read_results,
)
from annotator.formats.base import (
    GroundTruth as GroundTruth,
    PoseResults as PoseResults,
)
from annotator.formats.bop_images import (
    bop_symmetries as bop_symmetries,
)
from annotator.formats.ours import (
    annotations_as_results as annotations_as_results,
)
from annotator.ingest.scene import (
    IngestSettings as IngestSettings,
    IngestSummary as IngestSummary,
    ingest_recording as ingest_recording,
)
from annotator.occlusion.dataset import (
    OcclusionSummary as OcclusionSummary,
    compute_occlusion as compute_occlusion,
)
from annotator.parts.workflow import (
    DictionarySummary as DictionarySummary,
    MarkSettings as MarkSettings,
    MarkSummary as MarkSummary,
    mark_part as mark_part,
    write_custom_dictionary as write_custom_dictionary,
)
from annotator.physics.check import (
    PhysicsSettings as PhysicsSettings,
)
from annotator.physics.dataset import (
    PhysicsSummary as PhysicsSummary,
    physics_of_dataset as physics_of_dataset,
)
from annotator.sites.survey import (
    SitesSummary as SitesSummary,
    measure_sites as measure_sites,
)
from annotator.symmetry.classes import (
    symmetry_from_bop as symmetry_from_bop,
    symmetry_to_bop as symmetry_to_bop,
)
from annotator.synthesis.board import CaptureSettings as CaptureSettings
from annotator.synthesis.captures import (
    CapturesSummary as CapturesSummary,
    synthesize_captures as synthesize_captures,
)
from annotator.synthesis.generate import (
    SynthSettings as SynthSettings,
)
from annotator.synthesis.scenes import (
    SynthesisSummary as SynthesisSummary,
    synthesize_scenes as synthesize_scenes,
)
from annotator.synthesis.sequence import (
    SequenceSummary as SequenceSummary,
    synthesize_sequences as synthesize_sequences,
)
from annotator.twins.dataset import (
    TwinSummary as TwinSummary,
    synthesize_twins as synthesize_twins,
)
from annotator.values import (
    BadValue as BadValue,
)

__all__: list[str]
