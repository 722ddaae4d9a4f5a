"""``annotator evaluate GT``: the paper's symmetry-aware AP of pose estimation results.

The definitions are those of the authors' evaluation code (see
:mod:`annotator.evaluation.metrics`); the work is :func:`annotator.evaluate_dataset`'s, and
this module only reads options, prints and writes.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from annotator.commands import number, show, whole
from annotator.errors import UserError


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
    """The scores asked for (one option each, from the registry) and where the report goes."""
    from annotator.evaluation.scores import SCORES

    group = parser.add_argument_group("report")
    for score in SCORES:
        if score.option is None:
            continue
        if score.metavar is None:
            group.add_argument(score.option, action="store_true", help=score.help)
        else:
            group.add_argument(score.option, metavar=score.metavar, help=score.help)
    group.add_argument("--json", metavar="OUT", help="write the full report as JSON")
    group.add_argument("--plot", metavar="OUT.png", help="draw the mean precision/recall curves")
    group.add_argument("--overwrite", action="store_true", help="replace --json, --plot files")


def run(args: argparse.Namespace) -> int:
    from annotator.evaluation.dataset import evaluate_dataset
    from annotator.evaluation.evaluate import EvaluationSettings
    from annotator.evaluation.scores import SCORES

    _check_outputs(args)
    summary = evaluate_dataset(
        args.gt,
        results=args.results,
        settings=EvaluationSettings(
            max_occlusion=args.max_occlusion,
            max_results=tuple(args.max_results),
            threshold_mm=args.threshold,
            threshold_fraction=args.threshold_fraction,
            only_scenes_with_results=args.only_scenes_with_results,
        ),
        symmetry=args.symmetry,
        twin=args.twin,
        twin_results=args.twin_results,
        asked={s.name: getattr(args, s.dest) for s in SCORES if s.option is not None},
        per_object=args.per_object,
    )
    show(summary)
    if args.json:
        from annotator.io.atomic import write_json

        write_json(args.json, summary.to_json())
    if args.plot and summary.report is not None:
        from annotator.evaluation.evaluate import plot_curves

        plot_curves(summary.report, args.plot)
        print(f"precision/recall curves: {args.plot}")
    return summary.exit_status()


def _check_outputs(args: argparse.Namespace) -> None:
    """The report's files, refused before anything is read (the scores' own rules are
    :func:`annotator.evaluation.scores.check_request`'s, which the evaluation applies)."""
    from annotator.io.output_folder import check_output_files

    for out in (args.json, args.plot):
        if out and Path(out).is_dir():
            raise UserError("is a folder; give a file name", path=out)
    check_output_files(
        [("--json", args.json), ("--plot", args.plot)],
        inputs=[args.results, args.twin_results, args.coco_results],
        datasets=[args.gt, args.twin],
        overwrite=args.overwrite,
    )
