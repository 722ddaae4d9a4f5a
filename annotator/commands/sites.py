"""``annotator sites DATASET``: measure where every instance's markers really are (markers
glued by hand) and write them into object.yaml after showing the diff.

The work is in :mod:`annotator.sites`; this module reads options, prints and asks.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING

import numpy as np

from annotator.commands import add_workers_option, confirm, number
from annotator.dataset import load_dataset

if TYPE_CHECKING:  # imported when the command runs, so that `annotator --help` stays fast
    from annotator.sites.measure import InstanceSites
    from annotator.sites.survey import SitesSurvey


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
    survey = summary.survey
    if not args.json:
        _print_report(survey)
    if not args.dry_run:
        # Asked about each on a terminal, unless --yes; every question first, then all are
        # written, or none.
        asking = not args.yes and sys.stdin.isatty()
        summary.write(confirm=confirm if asking else None)
    if args.json:
        print(json.dumps(summary.to_json(), indent=1))
    else:
        print(_last_line(args, survey, summary.written))
    return 1 if survey.report.failed or summary.declined else 0


def _print_report(survey: SitesSurvey) -> None:
    """The failed scenes, every instance's table, the diffs."""
    survey.report.print_failures()
    for m in survey.measured:
        print("\n".join(_lines(m)))
    for update in survey.updates:
        print(update.diff, end="" if update.diff.endswith("\n") else "\n")


def _last_line(args: argparse.Namespace, survey: SitesSurvey, written: list[str]) -> str:
    spread = survey.spread
    told = (
        ""
        if spread is None
        else (f" (gluing moved them by {spread[0]:.2f} mm and {spread[1]:.1f} deg, 1-sigma)")
    )
    settled = (
        f"; {survey.rounds} rounds (the last moved the sites by {survey.moves[-1]:.3f} mm RMS)"
        if survey.moves
        else ""
    )
    return (
        f"sites: {len(survey.measured)} instances measured from {len(survey.report.done)} "
        f"{'frames' if any('/' in u for u in survey.report.done) else 'scenes'}{told}{settled}, "
        f"{survey.flagged} markers flagged; "
        + (
            f"wrote {len(written)} object.yaml; run `annotator annotate {args.dataset}` again"
            if written
            else "nothing written" + (" (--dry-run)" if args.dry_run and survey.updates else "")
        )
    )


def _lines(m: InstanceSites) -> list[str]:
    sol = m.solution
    head = (
        f"{m.key}: {len(sol.poses)} scenes, {sol.used} marker views used"
        f"{f' ({sol.left_out} left out)' if sol.left_out else ''}, corner RMS "
        f"{sol.rms_before:.2f} -> {sol.rms_after:.2f} px"
        + (f"; not observable: {', '.join(sol.unobservable)}" if sol.unobservable else "")
    )
    out = [head, "  site    id  scenes   du mm (1-sigma)   dv mm (1-sigma)   turn deg (1-sigma)"]
    for k, mid in enumerate(m.marker_ids):
        if sol.seen[k] == 0 and k not in m.flags:
            continue
        du, dv, dt = sol.corrections[k]
        su, sv, st = sol.std[k]
        cells = (
            f"  {k:4d}  {mid:4d}  {sol.seen[k]:6d}   {du:+6.2f} ({su:4.2f})     "
            f"{dv:+6.2f} ({sv:4.2f})     {np.degrees(dt):+6.2f} ({np.degrees(st):4.2f})"
        )
        out.append(cells + (f"   ! {m.flags[k]}" if k in m.flags else ""))
    return out
