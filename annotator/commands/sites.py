"""``annotator sites DATASET``: measure where every instance's markers really are (markers
glued by hand) and write them into object.yaml after showing the diff.

The work is in :mod:`annotator.sites`; this module reads options, prints and asks.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from annotator.commands import add_workers_option, confirm, number
from annotator.dataset import load_dataset
from annotator.dataset.model import SCENES_DIR
from annotator.errors import UserError
from annotator.io.atomic import write_together

if TYPE_CHECKING:  # imported when the command runs, so that `annotator --help` stays fast
    from annotator.sites.measure import InstanceSites
    from annotator.sites.survey import SitesSurvey


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
    from annotator.sites.survey import annotated_scenes, survey_sites

    ds = load_dataset(args.dataset)
    scenes = annotated_scenes(ds, args.scenes)
    if not any(fnmatch.fnmatch(s.id, args.scenes) for s in ds.scenes()):
        raise UserError(f"no scene matches {args.scenes!r}", path=ds.root / SCENES_DIR)
    if not scenes:
        raise UserError(
            "no scene has an annotation.json: run `annotator annotate "
            f"{args.dataset}` first (sites are measured from annotated scenes)",
            path=ds.root / SCENES_DIR,
        )
    survey = survey_sites(
        ds, scenes, max_move_mm=args.max_move, workers=args.workers, quiet=args.quiet
    )
    if not args.json:
        _print_report(survey)
    written, declined = _write(args, survey, ds.root)
    if args.json:
        print(json.dumps(_json(survey, written), indent=1))
    else:
        print(_last_line(args, survey, written))
    return 1 if survey.report.failed or declined else 0


def _print_report(survey: SitesSurvey) -> None:
    """The failed scenes, every instance's table, the diffs."""
    survey.report.print_failures()
    for m in survey.measured:
        print("\n".join(_lines(m)))
    for update in survey.updates:
        print(update.diff, end="" if update.diff.endswith("\n") else "\n")


def _write(args: argparse.Namespace, survey: SitesSurvey, root: Path) -> tuple[list[str], bool]:
    """Write the object.yaml files (asking about each on a terminal, unless --yes; none with
    --dry-run), all together (:func:`annotator.io.atomic.write_together`): the paths written,
    and whether the user declined any."""
    written: list[str] = []
    declined = False
    if not survey.updates or args.dry_run:
        return written, declined
    asking = not args.yes and sys.stdin.isatty()
    chosen = {}
    for update in survey.updates:  # every question first: then all are written, or none
        if not asking or confirm(update.path):
            chosen[update.path] = update.text
            written.append(str(update.path))
        else:
            declined = True
    write_together(root, chosen)
    return written, declined


def _json(survey: SitesSurvey, written: list[str]) -> dict[str, Any]:
    spread = survey.spread
    return {
        "scenes": len(survey.scenes),
        "glue_spread": None
        if spread is None
        else {"mm": round(spread[0], 4), "deg": round(spread[1], 3)},
        "instances": [m.to_json() for m in survey.measured],
        "rounds": survey.rounds,
        "round_moves_mm": [round(m, 4) for m in survey.moves],
        "flagged_markers": survey.flagged,
        "written": written,
        "failures": dict(sorted(survey.report.failed.items())),
    }


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
