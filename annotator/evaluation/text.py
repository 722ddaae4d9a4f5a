"""An :class:`~annotator.evaluation.dataset.EvaluationSummary` as ``annotator evaluate``
prints it: a header saying what is scored against what, the paper's table, then BOP's
scores, the auto-annotation's errors and the physics, where they were computed."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from annotator.evaluation.dataset import EvaluationSummary
from annotator.evaluation.evaluate import format_table

if TYPE_CHECKING:
    from annotator.evaluation.bop19 import Bop19Scores
    from annotator.evaluation.bop24 import Bop24Scores
    from annotator.evaluation.coco import CocoScores
    from annotator.evaluation.evaluate import EvaluationReport
    from annotator.formats.base import GroundTruth
    from annotator.physics.results import ResultsPhysics

__all__ = ["summary_text", "summary_warnings"]


def summary_warnings(s: EvaluationSummary) -> list[str]:
    """What the user must know before the figures (printed to stderr)."""
    unknown = s.results.unknown_scenes if s.results is not None else []
    if not unknown:
        return []
    more = ", ..." if len(unknown) > 5 else ""
    return [
        f"warning: {len(unknown)} result scenes have no ground truth and are not scored: "
        f"{', '.join(unknown[:5])}{more}"
    ]


def summary_text(s: EvaluationSummary, *, per_object: bool = False) -> str:
    """The report's lines (one row per object with ``per_object`` or several objects)."""
    lines = []
    if s.report is not None and s.gt is not None:
        lines += _header(s)
        per_object = per_object or len(s.report.per_object) > 1
        others = {"real": s.report, "twin": s.twin} if s.twin is not None else None
        lines.append(format_table(s.report, per_object=per_object, others=others))
        if s.bop19 is not None:
            lines += _bop19(s.bop19, s.report, s.gt)
        if s.bop24 is not None:
            lines += _bop24(s.bop24, s.gt)
    lines += _coco(s.coco)
    lines += _annotation_errors(s.annotation_errors)
    if s.physics is not None:
        lines += _physics(s.physics, max(s.settings.max_results))
    return "\n".join(lines)


def _header(s: EvaluationSummary) -> list[str]:
    from annotator.symmetry.space import MATCH_THRESHOLD_FRACTION

    assert s.gt is not None and s.results is not None and s.report is not None
    o = s.settings
    if o.threshold_mm is not None:
        thr = f"{o.threshold_mm:g} mm"
    elif o.threshold_fraction is None and s.gt.thresholds:
        thr = "the dataset's own (poseutils.json distance_threshold)"
    else:
        fraction = o.threshold_fraction or MATCH_THRESHOLD_FRACTION
        thr = f"{fraction:g} x diameter of the enclosing sphere centred on the surface centroid"
    lines = [
        f"evaluating {s.source} against {s.gt_path} ({s.format_name}); threshold: {thr}; "
        f"instances to find: occlusion <= {o.max_occlusion:g}; the authors' definitions"
    ]
    lines += [f"note: {note}" for note in s.gt.notes + s.results.notes]
    if s.report.unscored_scenes:
        lines.append(
            f"note: {len(s.report.unscored_scenes)} ground-truth scenes have no results and "
            "are not scored (--only-scenes-with-results)"
        )
    elif not s.results.scenes >= set(s.gt.scenes) and s.results.scenes:
        missing = len(set(s.gt.scenes) - s.results.scenes)
        lines.append(
            f"note: {missing} ground-truth scenes have no results: counted as nothing found"
        )
    return lines


def _score(v: float | None) -> str:
    """A score in the tables (``-`` where there is none)."""
    return "   -  " if v is None else f"{v:.4f}"


def _bop19(bop: Bop19Scores, report: EvaluationReport, gt: GroundTruth) -> list[str]:
    lines = [
        f"BOP's scores (bop_toolkit's eval_bop19_pose.py: {bop.targets} instances to find, "
        f"{bop.estimates} estimates scored):",
        f"  {'object':<14} {'AR':>6} {'AR_VSD':>6} {'AR_MSSD':>7} {'AR_MSPD':>7}   paper AP",
    ]
    for oid, row in sorted(bop.per_object.items()):
        name = gt.object_ids.get(oid, f"obj_{oid:06d}")
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
        name = gt.object_ids.get(oid, f"obj_{oid:06d}")
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


def _bop24(bop: Bop24Scores, gt: GroundTruth) -> list[str]:
    lines = [
        f"BOP's 6D detection scores (bop_toolkit's eval_bop24_pose.py: {bop.targets} instances "
        f"to find, {bop.estimates} estimates scored):",
        f"  {'object':<14} {'mAP_MSSD':>8} {'mAP_MSPD':>8} {'mAP_MSSD_mm':>11}",
    ]
    rows = [(gt.object_ids.get(o, f"obj_{o:06d}"), r) for o, r in sorted(bop.per_object.items())]
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


def _coco(scores: list[CocoScores]) -> list[str]:
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


def _annotation_errors(errs: list[dict]) -> list[str]:
    if not errs:
        return []
    e = np.array([x["error_mm"] / x["diameter_mm"] for x in errs])
    unflagged = sum(1 for x in errs if x["error_mm"] > 0.05 * x["diameter_mm"] and not x["flags"])
    return [
        f"auto-annotation: {len(errs)} posed instances with known truth, median error "
        f"{100 * np.median(e):.3f}% of the diameter, {int(np.sum(e > 0.05))} above 5% "
        f"({unflagged} of them unflagged)"
    ]


def _physics(found: ResultsPhysics, n: int) -> list[str]:
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
