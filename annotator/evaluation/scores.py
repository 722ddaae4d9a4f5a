"""The scores ``annotator evaluate`` computes, each registered once in :data:`SCORES`.

A :class:`Score` says what it is called, the option that asks for it (none: computed whenever
its inputs are there), what it needs (:data:`NEEDS`: a result CSV, a BOP dataset, one of our
datasets, no twin), how it is computed from the evaluation's :class:`Inputs`, how it is
printed and what it adds to the ``--json`` report. :func:`check_request` holds every rule of
which option needs which input, and :func:`~annotator.evaluation.dataset.evaluate_dataset`
calls it before anything is read; the command adds an option for each score that has one.
Adding a score is adding an entry here (its arithmetic may live in a module of its own, as
BOP's do in :mod:`.bop19`, :mod:`.bop24` and :mod:`.coco`).

The scores run, print and enter the JSON report in the order of :data:`SCORES`: the paper's
AP first (the others read its ground truth and results), then BOP 2019, BOP 2024-25, COCO,
the auto-annotation's own errors and the estimates' physics.

>>> [s.name for s in SCORES]
['paper', 'bop19', 'bop24', 'coco', 'annotation_errors', 'physics']
>>> [s.option for s in SCORES if s.option]
['--bop19', '--bop24', '--coco-results', '--physics']
>>> check_request("sample_scenes", asked={"bop19": True})
Traceback (most recent call last):
...
annotator.errors.UserError: --bop19 scores a BOP dataset against a result CSV (--results); export ours first with `annotator export DATASET OUT --format bop`
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from annotator.errors import UserError
from annotator.evaluation.evaluate import EvaluationReport, EvaluationSettings, evaluate
from annotator.formats import detect_format
from annotator.formats.base import GroundTruth, PoseResults

if TYPE_CHECKING:
    from annotator.evaluation.bop19 import Bop19Scores
    from annotator.evaluation.bop24 import Bop24Scores
    from annotator.evaluation.coco import CocoScores
    from annotator.physics.results import ResultsPhysics

__all__ = ["NEEDS", "SCORES", "Inputs", "Need", "PaperScores", "Score", "check_request"]

#: What BOP's scores tell a user of our datasets to do first.
EXPORT_FIRST = "export ours first with `annotator export DATASET OUT --format bop`"


@dataclass
class Inputs:
    """What the scores are computed from, and how they are printed.

    Attributes:
        gt_path: The ground truth's folder; ``format_name`` its format (``ours``, ``bop``,
            ``sileane``); ``given``: the path as the user wrote it.
        settings: The paper's AP's settings (the others read ``max_results``).
        results: The results file given (None: on ours, the auto-annotation is scored).
        twin, twin_results: A synthetic twin and the results on it.
        symmetry: The symmetry class of a Siléane folder with only mesh.ply.
        per_object: A row per object in the paper's table even for one object.
        gt, found: The ground truth and the results as read (None when only 2D detections
            are scored); ``source``: what the results are, in words.
        computed: The scores computed so far, by name (a later score may print beside an
            earlier one: BOP 2019's table has the paper's AP per object).
    """

    gt_path: Path
    format_name: str
    settings: EvaluationSettings
    given: str = ""
    results: Path | None = None
    twin: Path | None = None
    twin_results: Path | None = None
    symmetry: str | None = None
    per_object: bool = False
    gt: GroundTruth | None = None
    found: PoseResults | None = None
    source: str = ""
    computed: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Need:
    """An input a score cannot do without: whether it is there, and the one line that
    refuses the score otherwise (``{option}`` and ``{what}`` are the score's)."""

    there: Callable[[Inputs], bool]
    refusal: str
    #: Whether the refusal names the ground truth's path.
    at_gt: bool = False


#: Every input a score may need, by name.
NEEDS: dict[str, Need] = {
    "result_csv": Need(
        lambda i: i.results is not None,
        "{option} scores {what} against a result CSV (--results); " + EXPORT_FIRST,
    ),
    "no_twin": Need(lambda i: i.twin is None, "{option} and --twin cannot be combined"),
    "bop": Need(
        lambda i: i.format_name == "bop", "{option} scores {what}; " + EXPORT_FIRST, at_gt=True
    ),
    "ours": Need(
        lambda i: i.format_name == "ours", "{option} needs {what} of one of our datasets", True
    ),
}


@dataclass(frozen=True)
class Score:
    """One score of ``annotator evaluate``.

    Attributes:
        name: Its key (in :attr:`EvaluationSummary.scores`, and the keyword of
            ``evaluate_dataset(asked=...)``).
        compute: Its value from the inputs and what was asked (True, or the file given).
        lines: Its lines in the printed report.
        to_json: What it adds to the ``--json`` report.
        option: The command's option asking for it; None: computed whenever ``when`` says.
        metavar: The option takes a file (shown so); None: a flag.
        help: The option's help.
        needs: Names in :data:`NEEDS`, checked in this order.
        what: What it scores, in the refusals' words.
        when: For a score without an option: whether the inputs call for it.
    """

    name: str
    compute: Callable[[Inputs, Any], Any]
    lines: Callable[[Any, Inputs], list[str]]
    to_json: Callable[[Any], dict[str, Any]]
    option: str | None = None
    metavar: str | None = None
    help: str = ""
    needs: tuple[str, ...] = ()
    what: str = ""
    when: Callable[[Inputs], bool] | None = None

    @property
    def dest(self) -> str:
        """The option's attribute in argparse's namespace (``--coco-results``:
        ``coco_results``)."""
        return (self.option or "").lstrip("-").replace("-", "_")

    def wanted(self, inputs: Inputs, asked: Mapping[str, Any]) -> bool:
        """Whether to compute it: asked for, or called for by the inputs."""
        if self.option is not None:
            return bool(asked.get(self.name))
        return self.when is not None and self.when(inputs)


def check_request(
    gt_path: str | Path,
    *,
    results: str | Path | None = None,
    twin: str | Path | None = None,
    twin_results: str | Path | None = None,
    asked: Mapping[str, Any] | None = None,
) -> None:
    """Refuse, in one line, a combination that cannot work, before anything is read: the
    twin's three inputs go together, and each score asked for has what it needs.

    Raises:
        UserError: The first rule broken.
    """
    if (twin or twin_results) and not (twin and twin_results and results):
        raise UserError("--twin needs --twin-results, and --results for GT")
    asked = asked or {}
    inputs = Inputs(
        Path(gt_path),
        "",
        EvaluationSettings(),
        results=None if results is None else Path(results),
        twin=None if twin is None else Path(twin),
    )
    unknown = sorted(set(asked) - {s.name for s in SCORES if s.option})
    if unknown:
        raise UserError(f"no such score: {', '.join(unknown)}")
    for score in SCORES:
        if not score.wanted(inputs, asked):
            continue
        for name in score.needs:
            need = NEEDS[name]
            if name in ("bop", "ours") and not inputs.format_name:
                inputs.format_name = detect_format(inputs.gt_path).NAME
            if not need.there(inputs):
                line = need.refusal.format(option=score.option, what=score.what)
                raise UserError(line, path=gt_path if need.at_gt else None)


# -- the paper's AP (and the twin's beside it) ---------------------------------------------


@dataclass
class PaperScores:
    """The paper's AP of the results, and of the twin's results where there is a twin."""

    report: EvaluationReport
    twin: EvaluationReport | None = None


def _paper(inputs: Inputs, _: Any) -> PaperScores:
    assert inputs.gt is not None and inputs.found is not None
    out = PaperScores(evaluate(inputs.gt, inputs.found, inputs.settings))
    if inputs.twin is not None and inputs.twin_results is not None:
        fmt = detect_format(inputs.twin)
        gt = fmt.read_ground_truth(inputs.twin, symmetry=inputs.symmetry)
        out.twin = evaluate(gt, fmt.read_results(inputs.twin_results, gt), inputs.settings)
    return out


def _paper_lines(paper: PaperScores, inputs: Inputs) -> list[str]:
    from annotator.evaluation.evaluate import format_table

    per_object = inputs.per_object or len(paper.report.per_object) > 1
    others = {"real": paper.report, "twin": paper.twin} if paper.twin is not None else None
    table = format_table(paper.report, per_object=per_object, others=others)
    return _header(paper.report, inputs) + [table]


def _paper_json(paper: PaperScores) -> dict[str, Any]:
    doc = paper.report.to_json()
    return doc if paper.twin is None else {"real": doc, "twin": paper.twin.to_json()}


def _header(report: EvaluationReport, inputs: Inputs) -> list[str]:
    """What is scored against what, at which threshold, and the notes of the files read."""
    from annotator.symmetry.space import MATCH_THRESHOLD_FRACTION

    gt, found, o = inputs.gt, inputs.found, inputs.settings
    assert gt is not None and found is not None
    if o.threshold_mm is not None:
        thr = f"{o.threshold_mm:g} mm"
    elif o.threshold_fraction is None and gt.thresholds:
        thr = "the dataset's own (poseutils.json distance_threshold)"
    else:
        fraction = o.threshold_fraction or MATCH_THRESHOLD_FRACTION
        thr = f"{fraction:g} x diameter of the enclosing sphere centred on the surface centroid"
    lines = [
        f"evaluating {inputs.source} against {inputs.given} "
        f"({inputs.format_name}); threshold: {thr}; instances to find: occlusion <= "
        f"{o.max_occlusion:g}; the authors' definitions"
    ]
    lines += [f"note: {note}" for note in gt.notes + found.notes]
    if report.unscored_scenes:
        lines.append(
            f"note: {len(report.unscored_scenes)} ground-truth scenes have no results and "
            "are not scored (--only-scenes-with-results)"
        )
    elif not found.scenes >= set(gt.scenes) and found.scenes:
        missing = len(set(gt.scenes) - found.scenes)
        lines.append(
            f"note: {missing} ground-truth scenes have no results: counted as nothing found"
        )
    return lines


def _score(v: float | None) -> str:
    """A score in the tables (``-`` where there is none)."""
    return "   -  " if v is None else f"{v:.4f}"


def _object_name(gt: GroundTruth, oid: int) -> str:
    return gt.object_ids.get(oid, f"obj_{oid:06d}")


# -- BOP 2019: VSD, MSSD, MSPD ---------------------------------------------------------------


def _bop19(inputs: Inputs, _: Any) -> Bop19Scores:
    from tqdm import tqdm

    from annotator.evaluation.bop19 import bop19_scores
    from annotator.evaluation.forked import process_count
    from annotator.evaluation.vsd_render import model_depth, prepare
    from annotator.formats.bop_images import read_bop_split

    assert inputs.gt is not None and inputs.results is not None
    split = read_bop_split(inputs.gt_path, inputs.results, inputs.gt)
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
            render=model_depth,
            delta=split.delta,
            progress=progress,
            processes=process_count(),
            prepare=lambda: prepare(o.mesh for o in split.objects.values() if o.mesh),
        )
    scores.notes[:0] = split.notes
    return scores


def _bop19_lines(bop: Bop19Scores, inputs: Inputs) -> list[str]:
    gt, report = inputs.gt, inputs.computed["paper"].report
    assert gt is not None
    lines = [
        f"BOP's scores (bop_toolkit's eval_bop19_pose.py: {bop.targets} instances to find, "
        f"{bop.estimates} estimates scored):",
        f"  {'object':<14} {'AR':>6} {'AR_VSD':>6} {'AR_MSSD':>7} {'AR_MSPD':>7}   paper AP",
    ]
    for oid, row in sorted(bop.per_object.items()):
        name = _object_name(gt, oid)
        ap = report.per_object.get(name)
        lines.append(
            f"  {name:<14} {_score(row['AR'])} {_score(row['vsd'])}  {_score(row['mssd'])}  "
            f"{_score(row['mspd'])}   {_score(ap.ap if ap else None)}"
        )
    m = bop.metrics
    lines.append(
        f"  {'all':<14} {_score(bop.ar)} {_score(m['vsd'])}  {_score(m['mssd'])}  "
        f"{_score(m['mspd'])}   {_score(report.overall.ap)}"
    )
    lines += [f"note: {note}" for note in bop.notes]
    for oid, row in sorted(bop.per_object.items()):
        name = _object_name(gt, oid)
        ap = report.per_object.get(name)
        if ap is None or row["mssd"] is None or abs(ap.ap - row["mssd"]) < 0.2:
            continue
        lines.append(
            f"note: {name}: the paper's AP {ap.ap:.4f} and BOP's AR_MSSD {row['mssd']:.4f} "
            "disagree: AR counts only the instances BOP lists as targets and the best "
            "estimates per target, with thresholds from 5 to 50 % of the diameter; AP "
            "counts every result, false ones too, at one threshold"
        )
    return lines


# -- BOP 2024-25: 6D detection mAP -----------------------------------------------------------


def _bop24(inputs: Inputs, _: Any) -> Bop24Scores:
    from annotator.evaluation.bop24 import bop24_scores, max_estimates_for
    from annotator.formats.bop_images import read_bop_split

    assert inputs.gt is not None and inputs.results is not None
    split = read_bop_split(inputs.gt_path, inputs.results, inputs.gt, task="detection")
    limit = max_estimates_for(inputs.results.name)
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


def _bop24_lines(bop: Bop24Scores, inputs: Inputs) -> list[str]:
    gt = inputs.gt
    assert gt is not None
    lines = [
        f"BOP's 6D detection scores (bop_toolkit's eval_bop24_pose.py: {bop.targets} instances "
        f"to find, {bop.estimates} estimates scored):",
        f"  {'object':<14} {'mAP_MSSD':>8} {'mAP_MSPD':>8} {'mAP_MSSD_mm':>11}",
    ]
    rows = [(_object_name(gt, o), r) for o, r in sorted(bop.per_object.items())]
    rows.append(("all", bop.maps))
    for name, row in rows:
        lines.append(
            f"  {name:<14} {_score(row['mssd']):>8} {_score(row['mspd']):>8} "
            f"{_score(row['mssd_mm']):>11}"
        )
    lines.append(
        f"  bop24_mAP {_score(bop.bop24_map)}  bop25_mAP {_score(bop.maps['mssd'])}  "
        f"bop25_mAP_mm {_score(bop.maps['mssd_mm'])}"
    )
    return lines + [f"note: {note}" for note in bop.notes]


# -- BOP 2022: COCO's 2D detection and segmentation ------------------------------------------


def _coco(inputs: Inputs, results: str | Path) -> list[CocoScores]:
    """COCO's scores of a results file, for boxes and masks as the results have them."""
    from annotator.evaluation.coco import coco_scores
    from annotator.formats.coco_results import (
        check_against_images,
        coco_result_kinds,
        read_coco_ground_truth,
        read_coco_results,
    )

    path = Path(results)
    types = coco_result_kinds(path)
    if not types:
        read_coco_results(path, "bbox")  # names what is wrong with the file
        raise UserError("no result has a 'bbox' or a 'segmentation' to score", path=path)
    gt = read_coco_ground_truth(inputs.gt_path)
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


def _coco_lines(scores: list[CocoScores], _: Inputs) -> list[str]:
    lines = []
    for c in scores:
        what = "2D detection (boxes)" if c.ann_type == "bbox" else "2D segmentation (masks)"
        stats = list(c.stats.items())
        lines += [
            f"BOP's {what} scores (bop_toolkit's eval_bop22_coco.py, COCO's AP and AR: "
            f"{c.annotations} true instances in {c.images} images, {c.results} results):",
            "  " + "  ".join(f"{k} {v:.4f}" for k, v in stats[:6]),
            "  " + "  ".join(f"{k} {v:.4f}" for k, v in stats[6:]),
        ]
        lines += [f"note: {note}" for note in c.notes]
    return lines


# -- the auto-annotation's own errors, and the estimates' physics ----------------------------


def _annotation_errors(inputs: Inputs, _: Any) -> list[dict[str, Any]]:
    from annotator.evaluation.evaluate import per_instance_errors

    return per_instance_errors(inputs.gt_path)


def _annotation_errors_lines(errs: list[dict[str, Any]], _: Inputs) -> list[str]:
    if not errs:
        return []
    e = np.array([x["error_mm"] / x["diameter_mm"] for x in errs])
    unflagged = sum(1 for x in errs if x["error_mm"] > 0.05 * x["diameter_mm"] and not x["flags"])
    return [
        f"auto-annotation: {len(errs)} posed instances with known truth, median error "
        f"{100 * np.median(e):.3f}% of the diameter, {int(np.sum(e > 0.05))} above 5% "
        f"({unflagged} of them unflagged)"
    ]


def _physics(inputs: Inputs, _: Any) -> ResultsPhysics:
    from annotator.dataset import load_dataset
    from annotator.physics.results import results_physics

    assert inputs.gt is not None and inputs.found is not None
    n = max(inputs.settings.max_results)
    return results_physics(load_dataset(inputs.gt_path), inputs.gt, inputs.found, per_object=n)


def _physics_lines(found: ResultsPhysics, inputs: Inputs) -> list[str]:
    n = max(inputs.settings.max_results)
    lines = [
        f"physics: estimates physically impossible in the real pile (the best {n} per object "
        "and image; through a true part or the support, or resting on nothing)",
        f"  {'object':<14} {'checked':>7} {'through':>7} {'floating':>8} {'impossible':>10}",
    ]
    for obj, count in sorted(found.checked.items()):
        lines.append(
            f"  {obj:<14} {count:>7} {found.penetrating.get(obj, 0):>7} "
            f"{found.floating.get(obj, 0):>8} {found.share(obj):>10.1%}"
        )
    lines.append(
        f"  {'all':<14} {sum(found.checked.values()):>7} {'':>7} {'':>8} {found.share():>10.1%}"
    )
    if found.images_without_support:
        lines.append(
            f"note: {found.images_without_support} images have no depth: no support checked"
        )
    return lines


#: Every score, in the order they are computed, printed and written to the JSON report.
SCORES: list[Score] = [
    Score(
        "paper",
        _paper,
        _paper_lines,
        _paper_json,
        when=lambda i: i.gt is not None,
    ),
    Score(
        "bop19",
        _bop19,
        _bop19_lines,
        lambda s: {"bop19": s.to_json()},
        option="--bop19",
        help="also BOP's average recall (VSD when the depth images are there, MSSD, MSPD), "
        "as bop_toolkit's eval_bop19_pose.py computes it; BOP ground truth and a result CSV",
        needs=("result_csv", "no_twin", "bop"),
        what="a BOP dataset",
    ),
    Score(
        "bop24",
        _bop24,
        _bop24_lines,
        lambda s: {"bop24": s.to_json()},
        option="--bop24",
        help="also BOP's 6D detection scores: bop24_mAP (MSSD and MSPD), bop25_mAP (MSSD), "
        "bop25_mAP_mm (MSSD in mm), as bop_toolkit's eval_bop24_pose.py computes them "
        "(images of test_targets_bop24.json, instances under 10%% visible ignored, the best "
        "100 estimates per image); BOP ground truth and a result CSV",
        needs=("result_csv", "no_twin", "bop"),
        what="a BOP dataset",
    ),
    Score(
        "coco",
        _coco,
        _coco_lines,
        lambda cs: {f"bop22_coco_{c.ann_type}": c.to_json() for c in cs},
        option="--coco-results",
        metavar="RESULTS.json",
        help="also BOP's 2D detection and segmentation scores (COCO's AP and AR, as "
        "bop_toolkit's eval_bop22_coco.py) of a COCO results file, on a BOP dataset's "
        "scene_gt_coco files: boxes if every result has one, masks likewise; alone (without "
        "--results) only these",
        needs=("bop",),
        what="2D detections on a BOP dataset's scene_gt_coco files",
    ),
    Score(
        "annotation_errors",
        _annotation_errors,
        _annotation_errors_lines,
        lambda _: {},  # per instance, in the scenes' files: the report keeps to the scores
        when=lambda i: i.gt is not None and i.results is None and i.format_name == "ours",
    ),
    Score(
        "physics",
        _physics,
        _physics_lines,
        lambda p: {"physics": p.to_json()},
        option="--physics",
        help="also the share of estimates physically impossible in the real pile (through a "
        "true part or the support, or resting on nothing), per object; our datasets only",
        needs=("ours",),
        what="the parts' meshes and depth",
    ),
]
