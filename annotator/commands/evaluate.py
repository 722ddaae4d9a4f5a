"""``annotator evaluate GT``: the paper's symmetry-aware AP of pose estimation results.

The definitions are those of the authors' evaluation code (see
:mod:`annotator.evaluation.metrics`); this module only reads options, prints and writes.
Heavy libraries are imported only where a format needs them, so that a whole run on the
paper's files takes a fraction of a second.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from annotator.commands import number, whole
from annotator.errors import UserError

if TYPE_CHECKING:
    from types import ModuleType

    from annotator.evaluation.bop19 import Bop19Scores
    from annotator.evaluation.bop24 import Bop24Scores
    from annotator.evaluation.coco import CocoScores
    from annotator.evaluation.evaluate import EvaluationOptions, EvaluationReport
    from annotator.formats.base import GroundTruth, PoseResults
    from annotator.physics.results import ResultsPhysics


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # The order of the calls is the order of the usage line, which argparse errors print.
    parser.add_argument(
        "gt", help="ground truth: one of our datasets, a BOP dataset, or a Siléane object folder"
    )
    parser.add_argument(
        "--results",
        help="BOP result CSV, or folder of <scene>.json lists in the ground truth's unit "
        "(metres for a Siléane folder, mm otherwise); omitted on our datasets: the "
        "annotation.json poses are scored against gt.json",
    )
    _add_matching_options(parser)
    _add_object_options(parser)
    _add_twin_options(parser)
    _add_report_options(parser)


def _add_matching_options(parser: argparse.ArgumentParser) -> None:
    """Which instances are to be found, and when a result finds one."""
    group = parser.add_argument_group("matching")
    group.add_argument(
        "--max-occlusion",
        type=number(low=0, high=1),
        default=0.5,
        help="instances to find have at most this occlusion rate (default 0.5, inclusive)",
    )
    group.add_argument(
        "-n",
        "--max-results",
        type=whole(low=1),
        nargs="*",
        default=[1, 3],
        help="AP_n for each n: at most n results per scene (default 1 3)",
    )
    g = group.add_mutually_exclusive_group()
    g.add_argument(
        "--threshold", type=number(low=0, above=True), help="match threshold in mm (inclusive)"
    )
    g.add_argument(
        "--threshold-fraction",
        type=number(low=0, above=True),
        help="threshold as a fraction of the diameter (default: the dataset's own threshold "
        "if it has one, as the paper's poseutils.json, else 0.1)",
    )
    group.add_argument(
        "--only-scenes-with-results",
        action="store_true",
        help="score only the scenes the results mention, as the authors' code does "
        "(default: a ground-truth scene without results is one where nothing was found)",
    )


def _add_object_options(parser: argparse.ArgumentParser) -> None:
    """The objects: a symmetry where the ground truth lacks one, a row for each."""
    group = parser.add_argument_group("objects")
    group.add_argument("--symmetry", help="symmetry class for a Siléane folder with only mesh.ply")
    group.add_argument(
        "--per-object",
        action="store_true",
        help="one row per object (default: only when there are several)",
    )


def _add_twin_options(parser: argparse.ArgumentParser) -> None:
    """The synthetic twin, scored beside the real data."""
    group = parser.add_argument_group("twin")
    group.add_argument(
        "--twin",
        metavar="TWIN",
        help="the synthetic twin of GT (`annotator synth --twin`): scored too, with "
        "--twin-results, and printed beside it, as the paper's table compares real and "
        "simulated data",
    )
    group.add_argument("--twin-results", metavar="RESULTS", help="results on the twin's scenes")


def _add_report_options(parser: argparse.ArgumentParser) -> None:
    """What else is computed and where the report goes."""
    group = parser.add_argument_group("report")
    group.add_argument(
        "--bop19",
        action="store_true",
        help="also BOP's average recall (VSD when the depth images are there, MSSD, MSPD), "
        "as bop_toolkit's eval_bop19_pose.py computes it; BOP ground truth and a result CSV",
    )
    group.add_argument(
        "--bop24",
        action="store_true",
        help="also BOP's 6D detection scores: bop24_mAP (MSSD and MSPD), bop25_mAP (MSSD), "
        "bop25_mAP_mm (MSSD in mm), as bop_toolkit's eval_bop24_pose.py computes them "
        "(images of test_targets_bop24.json, instances under 10%% visible ignored, the best "
        "100 estimates per image); BOP ground truth and a result CSV",
    )
    group.add_argument(
        "--coco-results",
        metavar="RESULTS.json",
        help="also BOP's 2D detection and segmentation scores (COCO's AP and AR, as "
        "bop_toolkit's eval_bop22_coco.py) of a COCO results file, on a BOP dataset's "
        "scene_gt_coco files: boxes if every result has one, masks likewise; alone (without "
        "--results) only these",
    )
    group.add_argument(
        "--physics",
        action="store_true",
        help="also the share of estimates physically impossible in the real pile (through a "
        "true part or the support, or resting on nothing), per object; our datasets only",
    )
    group.add_argument("--json", metavar="OUT", help="write the full report as JSON")
    group.add_argument("--plot", metavar="OUT.png", help="draw the mean precision/recall curves")


def run(args: argparse.Namespace) -> int:
    from annotator.evaluation.evaluate import EvaluationOptions, evaluate, format_table

    _check_options(args)
    gt_path = Path(args.gt)
    if args.coco_results and not args.results:
        coco = _coco(args, gt_path)
        _print_coco(coco)
        if args.json:
            from annotator.io.atomic import write_json

            write_json(args.json, {f"bop22_coco_{c.ann_type}": c.to_json() for c in coco})
        return 0
    fmt, gt, results, source = _inputs(args)
    opts = EvaluationOptions(
        max_occlusion=args.max_occlusion,
        max_results=tuple(args.max_results),
        threshold_mm=args.threshold,
        threshold_fraction=args.threshold_fraction,
        only_scenes_with_results=args.only_scenes_with_results,
    )
    report = evaluate(gt, results, opts)
    _print_header(args, fmt.NAME, source, gt, results, report)
    per_object = args.per_object or len(report.per_object) > 1
    bop = _bop19(args, gt_path, gt) if args.bop19 else None
    bop24 = _bop24(args, gt_path, gt) if args.bop24 else None
    coco = _coco(args, gt_path) if args.coco_results else []
    twin_report = _twin(args, opts) if args.twin else None
    if twin_report is not None:
        others = {"real": report, "twin": twin_report}
        print(format_table(report, per_object=per_object, others=others))
    else:
        print(format_table(report, per_object=per_object))
    if bop is not None:
        _print_bop19(bop, report, gt)
    if bop24 is not None:
        _print_bop24(bop24, gt)
    _print_coco(coco)
    if not args.results and fmt.NAME == "ours":
        _print_annotation_errors(gt_path)
    physics = _physics(args, gt, results, opts) if args.physics else None
    if args.json:
        from annotator.io.atomic import write_json

        doc = report.to_json()
        if twin_report is not None:
            doc = {"real": doc, "twin": twin_report.to_json()}
        if bop is not None:
            doc["bop19"] = bop.to_json()
        if bop24 is not None:
            doc["bop24"] = bop24.to_json()
        for c in coco:
            doc[f"bop22_coco_{c.ann_type}"] = c.to_json()
        if physics is not None:
            doc["physics"] = physics.to_json()
        write_json(args.json, doc)
    if args.plot:
        from annotator.evaluation.evaluate import plot_curves

        plot_curves(report, args.plot)
        print(f"precision/recall curves: {args.plot}")
    return 0


def _physics(
    args: argparse.Namespace, gt: GroundTruth, results: PoseResults, opts: EvaluationOptions
) -> ResultsPhysics:
    """The physics of the estimates each AP_n counts (the largest n), printed per object."""
    from annotator.dataset import load_dataset
    from annotator.physics.results import results_physics

    n = max(opts.max_results)
    found = results_physics(load_dataset(args.gt), gt, results, per_object=n)
    print(
        f"physics: estimates physically impossible in the real pile (the best {n} per object "
        "and image; through a true part or the support, or resting on nothing)"
    )
    print(f"  {'object':<14} {'checked':>7} {'through':>7} {'floating':>8} {'impossible':>10}")
    for obj, count in sorted(found.checked.items()):
        print(
            f"  {obj:<14} {count:>7} {found.penetrating.get(obj, 0):>7} "
            f"{found.floating.get(obj, 0):>8} {found.share(obj):>10.1%}"
        )
    print(f"  {'all':<14} {sum(found.checked.values()):>7} {'':>7} {'':>8} {found.share():>10.1%}")
    if found.images_without_support:
        print(f"note: {found.images_without_support} images have no depth: no support checked")
    return found


def _check_options(args: argparse.Namespace) -> None:
    """Combinations that cannot work, refused before anything is read."""
    from annotator.io.output_folder import check_output_files

    for out in (args.json, args.plot):
        if out and Path(out).is_dir():
            raise UserError("is a folder; give a file name", path=out)
    check_output_files(
        [("--json", args.json), ("--plot", args.plot)],
        inputs=[args.results, args.twin_results, args.coco_results],
        datasets=[args.gt, args.twin],
    )
    if (args.twin or args.twin_results) and not (args.twin and args.twin_results and args.results):
        raise UserError("--twin needs --twin-results, and --results for GT")
    for flag in ("bop19", "bop24"):
        if getattr(args, flag) and not args.results:
            raise UserError(
                f"--{flag} scores a BOP dataset against a result CSV (--results); export ours "
                "first with `annotator export DATASET OUT --format bop`"
            )
        if getattr(args, flag) and args.twin:
            raise UserError(f"--{flag} and --twin cannot be combined")
    from annotator.formats import detect_format

    if args.physics and detect_format(Path(args.gt)).NAME != "ours":
        raise UserError(
            "--physics needs the parts' meshes and depth of one of our datasets", path=args.gt
        )


def _inputs(args: argparse.Namespace) -> tuple[ModuleType, GroundTruth, PoseResults, str]:
    """The ground truth's format, the ground truth, the results and a line saying where
    the results come from."""
    from annotator.formats import detect_format

    gt_path = Path(args.gt)
    fmt = detect_format(gt_path)
    for flag in ("bop19", "bop24"):
        if getattr(args, flag) and fmt.NAME != "bop":
            raise UserError(
                f"--{flag} scores a BOP dataset; export ours first with "
                "`annotator export DATASET OUT --format bop`",
                path=gt_path,
            )
    gt = fmt.read_ground_truth(gt_path, symmetry=args.symmetry)
    if args.results:
        results = fmt.read_results(Path(args.results), gt)
        unit = "metres" if gt.unit == "m" else "mm"
        source = f"{args.results} (lengths in {unit}, as the ground truth)"
    elif fmt.NAME == "ours":
        from annotator.formats.ours import annotations_as_results

        results = annotations_as_results(gt_path, gt)
        if not results.poses:
            raise UserError("no annotation.json to score and no --results given", path=args.gt)
        source = "annotation.json (auto-annotation vs gt.json)"
    else:
        raise UserError("--results is required for BOP and Siléane ground truth")
    return fmt, gt, results, source


def _print_header(
    args: argparse.Namespace,
    format_name: str,
    source: str,
    gt: GroundTruth,
    results: PoseResults,
    report: EvaluationReport,
) -> None:
    from annotator.symmetry.space import MATCH_THRESHOLD_FRACTION

    if results.unknown_scenes:
        first = ", ".join(results.unknown_scenes[:5])
        more = ", ..." if len(results.unknown_scenes) > 5 else ""
        print(
            f"warning: {len(results.unknown_scenes)} result scenes have no ground truth and are "
            f"not scored: {first}{more}",
            file=sys.stderr,
        )
    if args.threshold is not None:
        thr = f"{args.threshold:g} mm"
    elif args.threshold_fraction is None and gt.thresholds:
        thr = "the dataset's own (poseutils.json distance_threshold)"
    else:
        fraction = args.threshold_fraction or MATCH_THRESHOLD_FRACTION
        thr = f"{fraction:g} x diameter of the enclosing sphere centred on the surface centroid"
    print(
        f"evaluating {source} against {args.gt} ({format_name}); threshold: {thr}; "
        f"instances to find: occlusion <= {args.max_occlusion:g}; the authors' definitions"
    )
    for note in gt.notes + results.notes:
        print(f"note: {note}")
    if report.unscored_scenes:
        print(
            f"note: {len(report.unscored_scenes)} ground-truth scenes have no results and are "
            "not scored (--only-scenes-with-results)"
        )
    elif not results.scenes >= set(gt.scenes) and results.scenes:
        missing = len(set(gt.scenes) - results.scenes)
        print(f"note: {missing} ground-truth scenes have no results: counted as nothing found")


def _twin(args: argparse.Namespace, opts: EvaluationOptions) -> EvaluationReport:
    from annotator.evaluation.evaluate import evaluate
    from annotator.formats import detect_format

    twin_fmt = detect_format(Path(args.twin))
    twin_gt = twin_fmt.read_ground_truth(Path(args.twin), symmetry=args.symmetry)
    return evaluate(twin_gt, twin_fmt.read_results(Path(args.twin_results), twin_gt), opts)


def _bop19(args: argparse.Namespace, gt_path: Path, gt: GroundTruth) -> Bop19Scores:
    from tqdm import tqdm

    from annotator.evaluation.bop19 import bop19_scores
    from annotator.formats.bop_images import read_bop_split
    from annotator.rendering.raycast import render_depth

    split = read_bop_split(gt_path, Path(args.results), gt)
    with tqdm(
        total=len(split.images),
        desc="BOP scores",
        unit="image",
        disable=not sys.stderr.isatty(),
        file=sys.stderr,
    ) as bar:
        scores = bop19_scores(
            split.images,
            split.estimates,
            split.objects,
            render=render_depth,
            delta=split.delta,
            progress=bar.update,
        )
    scores.notes[:0] = split.notes
    return scores


def _bop24(args: argparse.Namespace, gt_path: Path, gt: GroundTruth) -> Bop24Scores:
    from annotator.evaluation.bop24 import bop24_scores, max_estimates_for
    from annotator.formats.bop_images import read_bop_split

    results = Path(args.results)
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


def _score(v: float | None) -> str:
    """A score in the printed tables (``-`` where there is none)."""
    return "   -  " if v is None else f"{v:.4f}"


def _print_bop24(bop: Bop24Scores, gt: GroundTruth) -> None:
    print(
        f"BOP's 6D detection scores (bop_toolkit's eval_bop24_pose.py: {bop.targets} instances "
        f"to find, {bop.estimates} estimates scored):"
    )
    print(f"  {'object':<14} {'mAP_MSSD':>8} {'mAP_MSPD':>8} {'mAP_MSSD_mm':>11}")
    rows = [(gt.object_ids.get(o, f"obj_{o:06d}"), r) for o, r in sorted(bop.per_object.items())]
    rows.append(("all", bop.maps))
    for name, row in rows:
        print(
            f"  {name:<14} {_score(row['mssd']):>8} {_score(row['mspd']):>8} {_score(row['mssd_mm']):>11}"
        )
    print(
        f"  bop24_mAP {_score(bop.bop24_map)}  bop25_mAP {_score(bop.maps['mssd'])}  "
        f"bop25_mAP_mm {_score(bop.maps['mssd_mm'])}"
    )
    for note in bop.notes:
        print(f"note: {note}")


def _coco(args: argparse.Namespace, gt_path: Path) -> list[CocoScores]:
    """COCO's scores of ``--coco-results``, for boxes and masks as the results have them."""
    from annotator.evaluation.coco import coco_scores
    from annotator.formats import detect_format
    from annotator.formats.coco_results import (
        ANN_TYPES,
        read_coco_ground_truth,
        read_coco_results,
    )
    from annotator.io.documents import read_json

    if detect_format(gt_path).NAME != "bop":
        raise UserError(
            "--coco-results scores 2D detections on a BOP dataset's scene_gt_coco files; "
            "export ours first with `annotator export DATASET OUT --format bop`",
            path=gt_path,
        )
    path = Path(args.coco_results)
    doc = read_json(path) if path.is_file() else None
    has = {"bbox": "bbox", "segm": "segmentation"}
    types = [
        t
        for t in ANN_TYPES
        if isinstance(doc, list) and doc and all(isinstance(r, dict) and has[t] in r for r in doc)
    ]
    if not types:
        read_coco_results(path, "bbox")  # names what is wrong with the file
        raise UserError("no result has a 'bbox' or a 'segmentation' to score", path=path)
    gt = read_coco_ground_truth(gt_path)
    return [coco_scores(gt, read_coco_results(path, t), t) for t in types]


def _print_coco(scores: list[CocoScores]) -> None:
    for c in scores:
        what = "2D detection (boxes)" if c.ann_type == "bbox" else "2D segmentation (masks)"
        print(
            f"BOP's {what} scores (bop_toolkit's eval_bop22_coco.py, COCO's AP and AR: "
            f"{c.annotations} true instances in {c.images} images, {c.results} results):"
        )
        print("  " + "  ".join(f"{k} {v:.4f}" for k, v in list(c.stats.items())[:6]))
        print("  " + "  ".join(f"{k} {v:.4f}" for k, v in list(c.stats.items())[6:]))
        for note in c.notes:
            print(f"note: {note}")


def _print_bop19(bop: Bop19Scores, report: EvaluationReport, gt: GroundTruth) -> None:
    print(
        f"BOP's scores (bop_toolkit's eval_bop19_pose.py: {bop.targets} instances to find, "
        f"{bop.estimates} estimates scored):"
    )
    print(f"  {'object':<14} {'AR':>6} {'AR_VSD':>6} {'AR_MSSD':>7} {'AR_MSPD':>7}   paper AP")
    for oid, row in sorted(bop.per_object.items()):
        name = gt.object_ids.get(oid, f"obj_{oid:06d}")
        ap = report.per_object.get(name)
        print(
            f"  {name:<14} {_score(row['AR'])} {_score(row['vsd'])}  {_score(row['mssd'])}  {_score(row['mspd'])}"
            f"   {_score(ap.ap if ap else None)}"
        )
    print(
        f"  {'all':<14} {_score(bop.ar)} {_score(bop.metrics['vsd'])}  {_score(bop.metrics['mssd'])}  "
        f"{_score(bop.metrics['mspd'])}   {_score(report.overall.ap)}"
    )
    for note in bop.notes:
        print(f"note: {note}")
    for oid, row in sorted(bop.per_object.items()):
        name = gt.object_ids.get(oid, f"obj_{oid:06d}")
        ap = report.per_object.get(name)
        if ap is None or row["mssd"] is None or abs(ap.ap - row["mssd"]) < 0.2:
            continue
        print(
            f"note: {name}: the paper's AP {ap.ap:.4f} and BOP's AR_MSSD {row['mssd']:.4f} "
            "disagree: AR counts only the instances BOP lists as targets and the best "
            "estimates per target, with thresholds from 5 to 50 % of the diameter; AP "
            "counts every result, false ones too, at one threshold"
        )


def _print_annotation_errors(root: Path) -> None:
    import numpy as np

    from annotator.evaluation.evaluate import per_instance_errors

    errs = per_instance_errors(root)
    if not errs:
        return
    e = np.array([x["error_mm"] / x["diameter_mm"] for x in errs])
    unflagged = sum(1 for x in errs if x["error_mm"] > 0.05 * x["diameter_mm"] and not x["flags"])
    print(
        f"auto-annotation: {len(errs)} posed instances with known truth, median error "
        f"{100 * np.median(e):.3f}% of the diameter, {int(np.sum(e > 0.05))} above 5% "
        f"({unflagged} of them unflagged)"
    )
