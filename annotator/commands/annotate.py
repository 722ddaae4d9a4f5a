"""``annotator annotate DATASET``: a pose for every instance with visible markers, in batch."""

from __future__ import annotations

import argparse
import sys

from annotator.commands import add_ray_option, add_workers_option, finish_batch
from annotator.dataset import load_dataset
from annotator.dataset.frames import frames_line

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
    doc = summary.to_json()
    if not args.json:
        for sid, left in sorted(summary.frames_left_out.items()):
            total = summary.report.done[sid].get("frames")
            print(f"scene {sid}: {frames_line(left, total)}", file=sys.stderr)
        for sid, notes in sorted(summary.notes.items()):
            for note in notes:  # what to do next (`annotator sites`), what moved
                print(f"scene {sid}: {note}", file=sys.stderr)
    frames = f"{doc['frames_posed']} of {doc['frames']} frames posed; " if "frames" in doc else ""
    return finish_batch(
        summary.report,
        doc,
        f"annotate: {doc['done']} scenes done, {doc['skipped']} up to date (skipped), "
        f"{doc['failed']} failed; {frames}{doc['instances_posed']} instances posed, "
        f"{doc['instances_flagged']} flagged; {doc['scenes_warned']} scenes with warnings "
        "(parts without a pose, blur, exposure: `annotator check --annotations`)",
        as_json=args.json,
    )
