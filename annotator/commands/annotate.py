"""``annotator annotate DATASET``: a pose for every instance with visible markers, in batch."""

from __future__ import annotations

import argparse

from annotator.commands import add_ray_option, add_workers_option, finish
from annotator.dataset import load_dataset

#: The argument naming the dataset this command writes into (its writer lock is held).
WRITES = "dataset"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="dataset folder (FORMAT.md)")
    add_workers_option(parser)
    add_ray_option(parser)
    parser.add_argument(
        "--scenes", default="*", metavar="PATTERN", help="only scenes whose id matches (fnmatch)"
    )
    parser.add_argument(
        "--force", action="store_true", help="redo scenes whose annotation is up to date"
    )
    parser.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    # The annotation imports open3d and scipy.spatial (a second): not for `annotate --help`.
    from annotator.annotation.batch import annotate_dataset

    summary = annotate_dataset(
        load_dataset(args.dataset),
        scenes=args.scenes,
        force=args.force,
        workers=args.workers,
        quiet=args.quiet,
        ray_address=args.ray,
        ray_wait=args.ray_wait,
    )
    return finish(summary, as_json=args.json)
