"""``annotator occlusion DATASET``: masks' pixel counts, boxes and occlusion rates per instance.

Reads annotation.json (or gt.json with ``--poses gt``) and writes ``visibility.json`` per scene
(atomically; scenes whose visibility.json was made from the same poses and tolerance, after
they and the depth last changed, are skipped unless ``--force``). annotate already stores the
rates in annotation.json; this command gives the full per-camera detail.
"""

from __future__ import annotations

import argparse

from annotator.commands import add_ray_option, add_workers_option, finish, number
from annotator.occlusion import DEPTH_TOLERANCE_MM
from annotator.occlusion.dataset import compute_occlusion

#: The argument naming the dataset this command writes into (its writer lock is held).
WRITES = "dataset"


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
    summary = compute_occlusion(
        args.dataset,
        poses=args.poses,
        scenes=args.scenes,
        depth_tolerance=args.depth_tolerance,
        force=args.force,
        workers=args.workers,
        quiet=args.quiet,
        ray_address=args.ray,
        ray_wait=args.ray_wait,
    )
    return finish(summary, as_json=args.json)
