"""``annotator sites DATASET``: measure where every instance's markers really are (markers
glued by hand) and write them into object.yaml after showing the diff.

The work is in :mod:`annotator.sites`; this module reads options, prints and asks.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import sys

import numpy as np

from annotator.commands import add_workers_option, confirm, number
from annotator.dataset import load_dataset, require_meshes
from annotator.errors import UserError
from annotator.io.atomic import write_text
from annotator.io.documents import unified_diff
from annotator.runner import run_batch


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
    from annotator.sites.measure import DetectJob, measure_sites, updated_object_yaml
    from annotator.sites.solve import SiteSettings

    ds = load_dataset(args.dataset)
    scenes = [
        s for s in ds.scenes() if fnmatch.fnmatch(s.id, args.scenes) and s.annotation_path.exists()
    ]
    if not scenes:
        raise UserError(
            "no scene has an annotation.json: run `annotator annotate "
            f"{args.dataset}` first (sites are measured from annotated scenes)",
            path=ds.root / "scenes",
        )
    require_meshes(ds)
    report = run_batch(
        DetectJob(str(ds.root)),
        [s.id for s in scenes],
        workers=args.workers,
        desc="sites: markers",
        quiet=args.quiet,
    )
    detections = {sid: r["markers"] for sid, r in report.done.items()}
    measured, spread = measure_sites(
        ds,
        [s for s in scenes if s.id in detections],
        detections,
        settings=SiteSettings(max_move_mm=args.max_move),
    )
    by_object: dict[str, list] = {}
    for m in measured:
        by_object.setdefault(m.object, []).append(m)
    diffs = {}
    for name, ms in by_object.items():
        path = ds.objects[name].folder / "object.yaml"
        old, new = updated_object_yaml(path, ms)
        if old != new:
            diffs[path] = (new, unified_diff(old, new, path, label="measured sites"))
    written = []
    if not args.json:
        report.print_failures()
        for m in measured:
            print("\n".join(_lines(m)))
        for _, diff in diffs.values():
            print(diff, end="" if diff.endswith("\n") else "\n")
    status = 1 if report.failed else 0
    if diffs and not args.dry_run:
        asking = not args.yes and sys.stdin.isatty()
        for path, (new, _) in diffs.items():
            if not asking or confirm(path):
                write_text(path, new)
                written.append(str(path))
            else:
                status = 1
    flagged = sum(len(m.flags) for m in measured)
    if args.json:
        print(
            json.dumps(
                {
                    "scenes": len(scenes),
                    "glue_spread": None
                    if spread is None
                    else {"mm": round(spread[0], 4), "deg": round(spread[1], 3)},
                    "instances": [m.to_json() for m in measured],
                    "flagged_markers": flagged,
                    "written": written,
                    "failures": dict(sorted(report.failed.items())),
                },
                indent=1,
            )
        )
    else:
        told = (
            ""
            if spread is None
            else (f" (gluing moved them by {spread[0]:.2f} mm and {spread[1]:.1f} deg, 1-sigma)")
        )
        print(
            f"sites: {len(measured)} instances measured from {len(report.done)} scenes{told}, "
            f"{flagged} markers flagged; "
            + (
                f"wrote {len(written)} object.yaml; run `annotator annotate {args.dataset}` again"
                if written
                else "nothing written" + (" (--dry-run)" if args.dry_run and diffs else "")
            )
        )
    return status


def _lines(m) -> list[str]:  # noqa: ANN001 - InstanceSites, imported lazily
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
