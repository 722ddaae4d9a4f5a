"""``annotator annotate DATASET``: a pose for every instance with visible markers, in batch."""

from __future__ import annotations

import argparse
import fnmatch

from annotator.annotation.batch import AnnotateJob, is_up_to_date
from annotator.batch import run_batch
from annotator.commands import add_workers_option, finish_batch
from annotator.dataset import load_dataset, require_meshes
from annotator.dataset.check import BROKEN_LINK
from annotator.errors import UserError
from annotator.scale import add_ray_option


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
    ds = load_dataset(args.dataset)
    scenes = [s for s in ds.scenes() if fnmatch.fnmatch(s.id, args.scenes)]
    if not scenes:
        raise UserError(f"no scene matches {args.scenes!r}", path=ds.root / "scenes")
    require_meshes(ds)
    job = AnnotateJob.for_dataset(ds)
    todo = [s.id for s in scenes if args.force or not is_up_to_date(ds, s, job.digest)]
    skipped = len(scenes) - len(todo)
    report = run_batch(
        job,
        todo,
        workers=args.workers,
        desc="annotate",
        quiet=args.quiet,
        ray_address=args.ray,
        ray_wait=args.ray_wait,
    )
    for link in ds.broken_scene_links():
        if fnmatch.fnmatch(link.name, args.scenes):
            report.failed[link.name] = f"{link}: {BROKEN_LINK}"
    posed = sum(r["instances"] for r in report.done.values())
    flagged = sum(r["flagged"] for r in report.done.values())
    warned = sum(r["warned"] for r in report.done.values())
    summary = {
        "scenes": len(scenes),
        "done": len(report.done),
        "skipped": skipped,
        "failed": len(report.failed),
        "instances_posed": posed,
        "instances_flagged": flagged,
        "scenes_warned": warned,
        "failures": dict(sorted(report.failed.items())),
    }
    return finish_batch(
        report,
        summary,
        f"annotate: {len(report.done)} scenes done, {skipped} up to date (skipped), "
        f"{len(report.failed)} failed; {posed} instances posed, {flagged} flagged; {warned} "
        "scenes with warnings (parts without a pose, blur, exposure: `annotator check "
        "--annotations`)",
        as_json=args.json,
    )
