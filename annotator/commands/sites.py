"""``annotator sites DATASET``: measure where every instance's markers really are (markers
glued by hand) and write them into object.yaml after showing the diff.

The work is in :mod:`annotator.sites`; this module reads options, prints and asks.
"""

from __future__ import annotations

import argparse
import sys

from annotator.commands import add_workers_option, confirm, finish, number
from annotator.dataset import load_dataset

#: The argument naming the dataset this command writes into (its writer lock is held).
WRITES = "dataset"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="dataset folder (FORMAT.md), annotated")
    parser.add_argument(
        "--scenes", default="*", metavar="PATTERN", help="only scenes whose id matches (fnmatch)"
    )
    parser.add_argument(
        "--max-move",
        type=number(low=0, above=True),
        default=2.0,
        metavar="MM",
        help="flag markers whose measured site is farther than this from the layout's (default 2)",
    )
    parser.add_argument(
        "--yes",
        action="store_true",
        help="write object.yaml without asking (never asked when standard input is not a terminal)",
    )
    parser.add_argument(
        "--dry-run", action="store_true", help="show the report and the diff, write nothing"
    )
    add_workers_option(parser)
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from annotator.sites.survey import measure_sites

    summary = measure_sites(
        load_dataset(args.dataset),
        scenes=args.scenes,
        max_move_mm=args.max_move,
        workers=args.workers,
        quiet=args.quiet,
    )
    if not args.json and (preview := summary.preview()):
        print(preview)
    if not args.dry_run:
        # Asked about each on a terminal, unless --yes; every question first, then all are
        # written, or none.
        asking = not args.yes and sys.stdin.isatty()
        summary.write(confirm=confirm if asking else None)
    return finish(summary, as_json=args.json)
