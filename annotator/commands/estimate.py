"""``annotator estimate DATASET OUT --method ppf``: a baseline pose estimator's results.

Poses of every part in every scene from its depth map alone, written to OUT as one BOP
results CSV that ``annotator evaluate DATASET --results OUT`` scores. The method is a native
point pair feature estimator (Drost et al. 2010) whose vote clustering is mean shift in SE(3),
or, with ``--symmetric``, in the pose space of the part's symmetry (Brégier et al. 2017,
section 4.2); see :mod:`annotator.estimation`. This module only reads options and prints.
"""

from __future__ import annotations

import argparse

from annotator.commands import add_ray_option, add_workers_option, finish, whole


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="dataset folder (FORMAT.md) with depth maps")
    parser.add_argument("out", help="results file to write (BOP CSV)")
    parser.add_argument(
        "--method",
        choices=("ppf",),
        default="ppf",
        help="ppf: point pair features, Drost et al. 2010 (the only method so far)",
    )
    parser.add_argument(
        "--symmetric",
        action="store_true",
        help="mean shift and duplicate removal by the part's symmetry-aware distance instead "
        "of in SE(3) (the paper's 'PPF sym')",
    )
    parser.add_argument(
        "--post-process",
        action="store_true",
        help="keep the 20 best hypotheses, refine them by ICP, re-score them by agreement with "
        "the measured depth and filter duplicates (the paper's 'PP')",
    )
    parser.add_argument(
        "--scenes", default="*", metavar="PATTERN", help="only scenes whose id matches (fnmatch)"
    )
    parser.add_argument(
        "--max-hypotheses",
        type=whole(low=1),
        default=30,
        metavar="N",
        help="results per part and scene at most (default 30)",
    )
    add_workers_option(parser)
    add_ray_option(parser)
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="replace OUT and its COCO file OUT.json if they exist (refused otherwise)",
    )
    parser.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from annotator.estimation.dataset import estimate_dataset
    from annotator.estimation.estimator import PPFSettings

    summary = estimate_dataset(
        args.dataset,
        args.out,
        settings=PPFSettings(
            symmetric=args.symmetric,
            post_process=args.post_process,
            max_hypotheses=args.max_hypotheses,
        ),
        scenes=args.scenes,
        workers=args.workers,
        quiet=args.quiet,
        ray_address=args.ray,
        ray_wait=args.ray_wait,
        overwrite=args.overwrite,
    )
    return finish(summary, as_json=args.json)
