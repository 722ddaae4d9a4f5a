"""``annotator occlusion DATASET``: masks' pixel counts, boxes and occlusion rates per instance.

Reads annotation.json (or gt.json with ``--poses gt``) and writes ``visibility.json`` per scene
(atomically; scenes whose visibility.json was made from the same poses and tolerance, after
they and the depth last changed, are skipped unless ``--force``). annotate already stores the
rates in annotation.json; this command gives the full per-camera detail.
"""

from __future__ import annotations

import argparse
import fnmatch

from annotator.commands import add_ray_option, add_workers_option, finish_batch, number
from annotator.dataset import load_dataset
from annotator.dataset.model import SCENES_DIR
from annotator.errors import UserError
from annotator.occlusion import DEPTH_TOLERANCE_MM
from annotator.occlusion.job import VisibilityJob, is_fresh
from annotator.runner import run_batch


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="dataset folder (FORMAT.md)")
    parser.add_argument("--poses", choices=("annotation", "gt"), default="annotation")
    parser.add_argument("--scenes", default="*", metavar="PATTERN")
    parser.add_argument(
        "--depth-tolerance",
        type=number(low=0),
        default=DEPTH_TOLERANCE_MM,
        help=f"mm (default {DEPTH_TOLERANCE_MM:g})",
    )
    add_workers_option(parser)
    add_ray_option(parser)
    parser.add_argument("--force", action="store_true")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--quiet", action="store_true")


def run(args: argparse.Namespace) -> int:
    ds = load_dataset(args.dataset)
    scenes = [s for s in ds.scenes() if fnmatch.fnmatch(s.id, args.scenes)]
    if not scenes:
        raise UserError(f"no scene matches {args.scenes!r}", path=ds.root / SCENES_DIR)

    todo = [
        s.id for s in scenes if args.force or not is_fresh(ds, s, args.poses, args.depth_tolerance)
    ]
    report = run_batch(
        VisibilityJob(str(ds.root), args.poses, args.depth_tolerance),
        todo,
        workers=args.workers,
        desc="occlusion",
        quiet=args.quiet,
        ray_address=args.ray,
        ray_wait=args.ray_wait,
    )
    summary = {
        "done": len(report.done),
        "skipped": len(scenes) - len(todo),
        "failed": len(report.failed),
        "failures": report.failed,
    }
    return finish_batch(
        report,
        summary,
        f"occlusion: {summary['done']} scenes done, {summary['skipped']} up to date, "
        f"{summary['failed']} failed",
        as_json=args.json,
    )
