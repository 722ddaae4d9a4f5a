"""Evaluation of a dataset's files as ``annotator evaluate`` does it: the ground truth read in
its format (ours, BOP, Siléane), the results read (or, on ours, the auto-annotation taken as
results), then every score asked for or called for by the inputs, each as
:mod:`.scores` registers it: the paper's AP (a synthetic twin's beside it), BOP's scores of
2019 (:mod:`.bop19`), of 2024-25 (:mod:`.bop24`) and of 2D detection (:mod:`.coco`), the
auto-annotation's own errors and the physics of the estimates (:mod:`annotator.physics`).

:func:`evaluate_dataset` returns them in one :class:`EvaluationSummary`, whose
:meth:`~EvaluationSummary.text` is what the command prints. Heavy libraries are imported only
where a score needs them, so that a run on the paper's files takes a fraction of a second.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

from annotator.errors import UserError
from annotator.evaluation.evaluate import EvaluationReport, EvaluationSettings
from annotator.evaluation.scores import SCORES, Inputs, check_request
from annotator.formats import detect_format
from annotator.formats.base import GroundTruth, PoseResults

if TYPE_CHECKING:
    from annotator.evaluation.bop19 import Bop19Scores
    from annotator.evaluation.bop24 import Bop24Scores
    from annotator.evaluation.coco import CocoScores
    from annotator.physics.results import ResultsPhysics

__all__ = ["EvaluationSummary", "evaluate_dataset"]


@dataclass
class EvaluationSummary:
    """What :func:`evaluate_dataset` found, a :class:`~annotator.summary.StageSummary`.

    Attributes:
        inputs: What was scored against what, and how it is printed
            (:class:`~annotator.evaluation.scores.Inputs`: the ground truth and the results
            as read, None when only 2D detections were scored).
        scores: Each score computed, by its name in :data:`~annotator.evaluation.scores.SCORES`
            (``paper``, ``bop19``, ``bop24``, ``coco``, ``annotation_errors``, ``physics``);
            the properties below read them.

    >>> s = evaluate_dataset("sample_scenes")
    >>> sorted(s.scores), s.counts()
    (['annotation_errors', 'paper'], {'tp': 35, 'fp': 1, 'fn': 0})
    """

    inputs: Inputs
    scores: dict[str, Any] = field(default_factory=dict)

    @property
    def gt_path(self) -> str:
        """The ground truth, as given."""
        return self.inputs.given

    @property
    def format_name(self) -> str:
        """The ground truth's format: ``ours``, ``bop``, ``sileane``."""
        return self.inputs.format_name

    @property
    def source(self) -> str:
        """Where the results come from, in words."""
        return self.inputs.source

    @property
    def settings(self) -> EvaluationSettings:
        """The paper's AP's settings."""
        return self.inputs.settings

    @property
    def gt(self) -> GroundTruth | None:
        return self.inputs.gt

    @property
    def results(self) -> PoseResults | None:
        return self.inputs.found

    @property
    def report(self) -> EvaluationReport | None:
        """The paper's AP (None when only 2D detections were scored)."""
        paper = self.scores.get("paper")
        return None if paper is None else paper.report

    @property
    def twin(self) -> EvaluationReport | None:
        """The synthetic twin's report, scored alike."""
        paper = self.scores.get("paper")
        return None if paper is None else paper.twin

    @property
    def bop19(self) -> Bop19Scores | None:
        return self.scores.get("bop19")

    @property
    def bop24(self) -> Bop24Scores | None:
        return self.scores.get("bop24")

    @property
    def coco(self) -> list[CocoScores]:
        return self.scores.get("coco", [])

    @property
    def physics(self) -> ResultsPhysics | None:
        return self.scores.get("physics")

    @property
    def annotation_errors(self) -> list[dict[str, Any]]:
        """On our datasets without results: each posed instance's error against gt.json
        (:func:`~annotator.evaluation.evaluate.per_instance_errors`)."""
        return self.scores.get("annotation_errors", [])

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        if self.report is not None:
            overall = self.report.overall
            out.update(tp=overall.tp, fp=overall.fp, fn=overall.fn)
        return out

    def warnings(self) -> list[str]:
        """What the user must know before the figures."""
        unknown = self.results.unknown_scenes if self.results is not None else []
        if not unknown:
            return []
        more = ", ..." if len(unknown) > 5 else ""
        return [
            f"warning: {len(unknown)} result scenes have no ground truth and are not scored: "
            f"{', '.join(unknown[:5])}{more}"
        ]

    def written_paths(self) -> list[Path]:
        return []  # the command writes --json and --plot where it is told

    def text(self) -> str:
        """The report: each score's lines, in the order of the registry."""
        lines = []
        for score in SCORES:
            if score.name in self.scores:
                lines += score.lines(self.scores[score.name], self.inputs)
        return "\n".join(lines)

    def exit_status(self) -> int:
        return 0

    def to_json(self) -> dict[str, Any]:
        """The report as ``--json`` writes it (BOP's key names for BOP's scores)."""
        doc: dict[str, Any] = {}
        for score in SCORES:
            if score.name in self.scores:
                doc.update(score.to_json(self.scores[score.name]))
        return doc


def evaluate_dataset(
    gt_path: str | Path,
    *,
    results: str | Path | None = None,
    settings: EvaluationSettings | None = None,
    symmetry: str | None = None,
    bop19: bool = False,
    bop24: bool = False,
    coco_results: str | Path | None = None,
    twin: str | Path | None = None,
    twin_results: str | Path | None = None,
    physics: bool = False,
    asked: Mapping[str, Any] | None = None,
    per_object: bool = False,
) -> EvaluationSummary:
    """Score ``results`` (a BOP CSV, a folder of per-scene JSON lists; None on our datasets:
    the auto-annotation against gt.json) against the ground truth at ``gt_path``.

    Args:
        settings: The paper's AP's settings (default :class:`EvaluationSettings`'s).
        symmetry: The symmetry class of a Siléane folder with only mesh.ply.
        bop19, bop24: Also BOP's scores (a BOP dataset and a result CSV).
        coco_results: Also BOP's 2D detection scores of this COCO results file (alone when
            ``results`` is None).
        twin, twin_results: A synthetic twin and the results on it, scored alike.
        physics: Also the estimates' physics in the real pile (our datasets).
        asked: The scores asked for by name (:data:`~annotator.evaluation.scores.SCORES`):
            True, or the file a score reads; ``bop19``, ``bop24``, ``coco_results`` and
            ``physics`` add to it.
        per_object: A row per object in the printed table even for one object.

    Raises:
        UserError: A combination that cannot work (:func:`~.scores.check_request`, before
            anything is read), or a file that cannot be read.

    >>> s = evaluate_dataset("sample_scenes")
    >>> s.format_name, s.source
    ('ours', 'annotation.json (auto-annotation vs gt.json)')
    >>> round(s.report.overall.ap, 3), s.report.overall.tp
    (1.0, 35)
    """
    wanted = dict(asked or {})
    for name, value in (("bop19", bop19), ("bop24", bop24), ("coco", coco_results)):
        if value:
            wanted[name] = value
    if physics:
        wanted["physics"] = True
    check_request(gt_path, results=results, twin=twin, twin_results=twin_results, asked=wanted)
    fmt = detect_format(Path(gt_path))
    inputs = Inputs(
        Path(gt_path),
        fmt.NAME,
        settings if settings is not None else EvaluationSettings(),
        given=str(gt_path),
        results=None if results is None else Path(results),
        twin=None if twin is None else Path(twin),
        twin_results=None if twin_results is None else Path(twin_results),
        symmetry=symmetry,
        per_object=per_object,
    )
    if wanted.get("coco") and results is None:
        inputs.source = str(wanted["coco"])  # only 2D detections: no poses read
    else:
        inputs.gt = fmt.read_ground_truth(inputs.gt_path, symmetry=symmetry)
        inputs.found, inputs.source = _scored(fmt, inputs.gt_path, inputs.gt, results)
    # One dict: a score printed beside an earlier one reads it from the inputs.
    out = EvaluationSummary(inputs, inputs.computed)
    for score in SCORES:
        if score.wanted(inputs, wanted):
            out.scores[score.name] = score.compute(inputs, wanted.get(score.name))
    return out


def _scored(
    fmt: ModuleType, gt_path: Path, gt: GroundTruth, results: str | Path | None
) -> tuple[PoseResults, str]:
    """The results to score (``results``' file, or on our datasets the auto-annotation) and
    what they are, as the summary says it."""
    if results is not None:
        unit = "metres" if gt.unit == "m" else "mm"
        return (
            fmt.read_results(Path(results), gt),
            f"{results} (lengths in {unit}, as the ground truth)",
        )
    if fmt.NAME != "ours":
        raise UserError("--results is required for BOP and Siléane ground truth")
    from annotator.formats.ours import annotations_as_results

    found = annotations_as_results(gt_path, gt)
    if not found.poses:
        raise UserError("no annotation.json to score and no --results given", path=gt_path)
    return found, "annotation.json (auto-annotation vs gt.json)"
