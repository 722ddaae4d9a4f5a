"""``annotator evaluate GT``: the paper's symmetry-aware AP of pose estimation results."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from annotator.errors import UserError
from annotator.evaluation.evaluate import (
    Options,
    annotations_as_results,
    evaluate,
    format_table,
    per_instance_errors,
    plot_curves,
)
from annotator.evaluation.readers import read_ground_truth, read_results
from annotator.io.atomic import write_json


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "gt", help="ground truth: one of our datasets, a BOP dataset, or a Siléane object folder"
    )
    parser.add_argument(
        "--results",
        help="BOP result CSV or folder of <scene>.json lists; omitted on our datasets: "
        "the annotation.json poses are scored against gt.json",
    )
    parser.add_argument(
        "--max-occlusion",
        type=float,
        default=0.5,
        help="instances of interest are less occluded (default 0.5)",
    )
    parser.add_argument(
        "-n",
        "--max-results",
        type=int,
        nargs="*",
        default=[1, 3],
        help="AP_n for each n (default 1 3)",
    )
    g = parser.add_mutually_exclusive_group()
    g.add_argument("--threshold", type=float, help="match threshold in mm")
    g.add_argument(
        "--threshold-fraction",
        type=float,
        default=0.1,
        help="threshold as a fraction of the diameter (default 0.1)",
    )
    parser.add_argument(
        "--symmetry", help="symmetry class for a Siléane folder without symmetry.yaml"
    )
    parser.add_argument(
        "--per-object",
        action="store_true",
        help="one row per object (default: only when there are several)",
    )
    parser.add_argument("--json", metavar="OUT", help="write the full report as JSON")
    parser.add_argument("--plot", metavar="OUT.png", help="draw the mean precision/recall curves")


def run(args: argparse.Namespace) -> int:
    if not 0 < args.max_occlusion <= 1:
        raise UserError("--max-occlusion must be in (0, 1]")
    if any(n < 1 for n in args.max_results):
        raise UserError("--max-results values must be at least 1")
    if args.threshold is not None and args.threshold <= 0 or args.threshold_fraction <= 0:
        raise UserError("the threshold must be positive")
    gt = read_ground_truth(args.gt, symmetry=args.symmetry)
    if args.results:
        results = read_results(args.results, gt)
        source = args.results
    elif gt.kind == "ours":
        results = annotations_as_results(Path(args.gt), gt)
        if not results:
            raise UserError("no annotation.json to score and no --results given", path=args.gt)
        source = "annotation.json (auto-annotation vs gt.json)"
    else:
        raise UserError("--results is required for BOP and Siléane ground truth")
    opts = Options(
        max_occlusion=args.max_occlusion,
        max_results=tuple(args.max_results),
        threshold_mm=args.threshold,
        threshold_fraction=args.threshold_fraction,
    )
    report = evaluate(gt, results, opts)
    thr = "threshold: " + (
        f"{args.threshold} mm"
        if args.threshold
        else f"{args.threshold_fraction:g} x diameter of the enclosing sphere centred on the surface centroid"
    )
    print(
        f"evaluating {source} against {args.gt} ({gt.kind}); {thr}; instances of interest: occlusion < {args.max_occlusion:g}"
    )
    print(format_table(report, per_object=args.per_object or len(report.per_object) > 1))
    if not args.results and gt.kind == "ours":
        errs = per_instance_errors(Path(args.gt))
        if errs:
            e = np.array([x["error_mm"] / x["diameter_mm"] for x in errs])
            print(
                f"auto-annotation: {len(errs)} posed instances with known truth, median error {100 * np.median(e):.3f}% "
                f"of the diameter, {int(np.sum(e > 0.05))} above 5% ({sum(1 for x in errs if x['error_mm'] > 0.05 * x['diameter_mm'] and not x['flags'])} of them unflagged)"
            )
    if args.json:
        write_json(args.json, report.to_json())
    if args.plot:
        plot_curves(report, args.plot)
        print(f"precision/recall curves: {args.plot}")
    return 0
