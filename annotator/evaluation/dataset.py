"""Evaluation of a dataset's files as ``annotator evaluate`` does it: the ground truth read in
its format (ours, BOP, Siléane), the results read (or, on ours, the auto-annotation taken as
results), the paper's AP, and beside it what was asked for: BOP's scores of 2019
(:mod:`.bop19`), of 2024-25 (:mod:`.bop24`) and of 2D detection (:mod:`.coco`), a
synthetic twin scored alike, and the physics of the estimates (:mod:`annotator.physics`).

:func:`evaluate_dataset` returns them in one :class:`EvaluationSummary`; :mod:`.text` writes
it as the command prints it. Heavy libraries are imported only where a part needs them, so
that a run on the paper's files takes a fraction of a second.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

from annotator.errors import UserError
from annotator.evaluation.evaluate import EvaluationReport, EvaluationSettings, evaluate
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
    """What :func:`evaluate_dataset` found.

    Attributes:
        gt_path, format_name: The ground truth (as given) and its format (``ours``, ``bop``,
            ``sileane``).
        source: Where the results come from, in words.
        settings: The paper's AP's settings.
        gt, results: As read (None when only 2D detections were scored).
        report: The paper's AP (None when only 2D detections were scored).
        twin: The synthetic twin's report, scored alike.
        bop19, bop24, coco: BOP's scores, where asked for.
        physics: The estimates' physics, where asked for.
        annotation_errors: On our datasets without results: each posed instance's error
            against gt.json (:func:`~annotator.evaluation.evaluate.per_instance_errors`).
    """

    gt_path: str
    format_name: str
    source: str
    settings: EvaluationSettings
    gt: GroundTruth | None = None
    results: PoseResults | None = None
    report: EvaluationReport | None = None
    twin: EvaluationReport | None = None
    bop19: Bop19Scores | None = None
    bop24: Bop24Scores | None = None
    coco: list[CocoScores] = field(default_factory=list)
    physics: ResultsPhysics | None = None
    annotation_errors: list[dict[str, Any]] = field(default_factory=list)
    #: Whether :meth:`text` has a row per object even for one object.
    per_object: bool = False

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        if self.report is not None:
            out.update(tp=self.report.overall.tp, fp=self.report.overall.fp)
            out["fn"] = self.report.overall.fn
        return out

    def warnings(self) -> list[str]:
        from annotator.evaluation.text import summary_warnings

        return summary_warnings(self)

    def written_paths(self) -> list[Path]:
        return []  # the command writes --json and --plot where it is told

    def text(self) -> str:
        from annotator.evaluation.text import summary_text

        return summary_text(self, per_object=self.per_object)

    def exit_status(self) -> int:
        return 0

    def to_json(self) -> dict[str, Any]:
        """The report as ``--json`` writes it (BOP's key names for BOP's scores)."""
        doc: dict[str, Any] = {}
        if self.report is not None:
            doc = self.report.to_json()
            if self.twin is not None:
                doc = {"real": doc, "twin": self.twin.to_json()}
        if self.bop19 is not None:
            doc["bop19"] = self.bop19.to_json()
        if self.bop24 is not None:
            doc["bop24"] = self.bop24.to_json()
        for c in self.coco:
            doc[f"bop22_coco_{c.ann_type}"] = c.to_json()
        if self.physics is not None:
            doc["physics"] = self.physics.to_json()
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

    Raises:
        UserError: A combination that cannot work, or a file that cannot be read.

    >>> s = evaluate_dataset("sample_scenes")
    >>> s.format_name, s.source
    ('ours', 'annotation.json (auto-annotation vs gt.json)')
    >>> round(s.report.overall.ap, 3), s.report.overall.tp
    (1.0, 35)
    """
    settings = settings if settings is not None else EvaluationSettings()
    given, gt_path = str(gt_path), Path(gt_path)
    fmt = detect_format(gt_path)
    if coco_results is not None and results is None:
        return EvaluationSummary(
            given, fmt.NAME, str(coco_results), settings, coco=_coco(gt_path, coco_results)
        )
    for flag, on in (("bop19", bop19), ("bop24", bop24)):
        if on:
            _check_bop_scored(flag, fmt.NAME, gt_path, results)
    gt = fmt.read_ground_truth(gt_path, symmetry=symmetry)
    found, source = _scored(fmt, gt_path, gt, results)
    report = evaluate(gt, found, settings)
    out = EvaluationSummary(given, fmt.NAME, source, settings, gt, found, report)
    if bop19 and results is not None:
        out.bop19 = _bop19(gt_path, Path(results), gt)
    if bop24 and results is not None:
        out.bop24 = _bop24(gt_path, Path(results), gt)
    if coco_results is not None:
        out.coco = _coco(gt_path, coco_results)
    if twin is not None and twin_results is not None:
        twin_fmt = detect_format(Path(twin))
        twin_gt = twin_fmt.read_ground_truth(Path(twin), symmetry=symmetry)
        out.twin = evaluate(twin_gt, twin_fmt.read_results(Path(twin_results), twin_gt), settings)
    if results is None and fmt.NAME == "ours":
        from annotator.evaluation.evaluate import per_instance_errors

        out.annotation_errors = per_instance_errors(gt_path)
    if physics:
        from annotator.dataset import load_dataset
        from annotator.physics.results import results_physics

        n = max(settings.max_results)
        out.physics = results_physics(load_dataset(gt_path), gt, found, per_object=n)
    return out


def _check_bop_scored(flag: str, fmt: str, gt_path: Path, results: str | Path | None) -> None:
    """Raise UserError unless ``--flag`` (a BOP score) has a BOP dataset and a result CSV."""
    if results is None:
        raise UserError(
            f"--{flag} scores a BOP dataset against a result CSV (--results); export ours "
            "first with `annotator export DATASET OUT --format bop`"
        )
    if fmt != "bop":
        raise UserError(
            f"--{flag} scores a BOP dataset; export ours first with "
            "`annotator export DATASET OUT --format bop`",
            path=gt_path,
        )


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


def _bop19(gt_path: Path, results: Path, gt: GroundTruth) -> Bop19Scores:
    from tqdm import tqdm

    from annotator.evaluation.bop19 import bop19_scores
    from annotator.formats.bop_images import read_bop_split
    from annotator.rendering.raycast import render_depth

    split = read_bop_split(gt_path, results, gt)
    with tqdm(
        total=len(split.images),
        desc="BOP scores",
        unit="image",
        disable=not sys.stderr.isatty(),
        file=sys.stderr,
    ) as bar:
        progress: Callable[[], Any] = bar.update
        scores = bop19_scores(
            split.images,
            split.estimates,
            split.objects,
            render=render_depth,
            delta=split.delta,
            progress=progress,
        )
    scores.notes[:0] = split.notes
    return scores


def _bop24(gt_path: Path, results: Path, gt: GroundTruth) -> Bop24Scores:
    from annotator.evaluation.bop24 import bop24_scores, max_estimates_for
    from annotator.formats.bop_images import read_bop_split

    split = read_bop_split(gt_path, results, gt, task="detection")
    limit = max_estimates_for(results.name)
    scores = bop24_scores(
        split.images, split.estimates, split.objects, max_per_image=limit, times=split.times
    )
    scores.notes[:0] = split.notes
    if scores.dropped:
        scores.notes.append(
            f"{scores.dropped} estimates beyond the best {limit} of their image not scored"
        )
    if scores.ignored:
        scores.notes.append(
            f"{scores.ignored} estimates of instances under 10% visible ignored (at MSSD 0.05)"
        )
    return scores


def _coco(gt_path: Path, results: str | Path) -> list[CocoScores]:
    """COCO's scores of a results file, for boxes and masks as the results have them."""
    from annotator.evaluation.coco import coco_scores
    from annotator.formats.coco_results import (
        check_against_images,
        coco_result_kinds,
        read_coco_ground_truth,
        read_coco_results,
    )

    if detect_format(gt_path).NAME != "bop":
        raise UserError(
            "--coco-results scores 2D detections on a BOP dataset's scene_gt_coco files; "
            "export ours first with `annotator export DATASET OUT --format bop`",
            path=gt_path,
        )
    path = Path(results)
    types = coco_result_kinds(path)
    if not types:
        read_coco_results(path, "bbox")  # names what is wrong with the file
        raise UserError("no result has a 'bbox' or a 'segmentation' to score", path=path)
    gt = read_coco_ground_truth(gt_path)
    out: list[CocoScores] = []
    for t in types:
        rows = read_coco_results(path, t)
        notes = check_against_images(rows, gt, path, t)
        scores = coco_scores(gt, rows, t)
        # What is said of the results' scenes and images holds for both kinds: said once.
        said = {n for c in out for n in c.notes}
        scores.notes[:0] = [n for n in notes if n not in said]
        out.append(scores)
    return out
