"""``annotator export DATASET OUT --format bop|sileane``: accepted scenes, ready for others."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from tqdm import tqdm

from annotator.commands import finish
from annotator.dataset import load_dataset
from annotator.errors import UserError
from annotator.export.dataset import export_dataset
from annotator.export.fill import METHODS as FILLS
from annotator.export.options import EXPORTS, LAYOUTS, POSES_FROM


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="dataset folder (FORMAT.md)")
    parser.add_argument(
        "out",
        help="output folder: new or empty, or an earlier export's with --overwrite; "
        "never the dataset, inside it or around it",
    )
    parser.add_argument("--format", required=True, help=" or ".join(EXPORTS))
    parser.add_argument(
        "--include-pending", action="store_true", help="also export scenes not reviewed yet"
    )
    parser.add_argument(
        "--drop-rejected-instances",
        action="store_true",
        help="export scenes with rejected instances, without them",
    )
    parser.add_argument(
        "--poses",
        choices=POSES_FROM,
        default="annotation",
        help="poses from annotation.json (default) or gt.json",
    )
    parser.add_argument(
        "--cameras", help="comma-separated rig cameras to export (BOP; default all)"
    )
    parser.add_argument(
        "--layout",
        choices=LAYOUTS,
        default="scenewise",
        help="BOP: scene folders (default), bop_toolkit's image-wise files, or its webdataset "
        "tar shards",
    )
    parser.add_argument(
        "--sensors",
        action="store_true",
        help="BOP: every rig camera a sensor of BOP's multi-sensor layout (gray_<camera>/, "
        "scene_gt_<camera>.json, camera_<camera>.json...), as BOP's industrial datasets, "
        "even a single camera (default: that layout for several cameras, the classic one "
        "for one)",
    )
    parser.add_argument(
        "--remove-markers",
        action="store_true",
        help="write the intensity images with the markers filled in, and mask_markers (where "
        "they were; also a 'marker' category in BOP's COCO file); depth as measured",
    )
    parser.add_argument(
        "--marker-fill",
        choices=FILLS,
        help="with --remove-markers: fill from the same surface around each marker (default) "
        "or with OpenCV's inpainting (telea)",
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="replace OUT if an earlier export wrote it"
    )
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    bars: list[tqdm] = []

    def progress(total: int) -> Callable[[], None]:
        bar = tqdm(
            total=total,
            desc=f"export {args.format}",
            unit="scene",
            disable=args.quiet or not sys.stderr.isatty(),
            file=sys.stderr,
        )
        bars.append(bar)
        return bar.update

    if args.marker_fill and not args.remove_markers:
        raise UserError("--marker-fill is for --remove-markers")
    try:
        summary = export_dataset(
            load_dataset(args.dataset),
            args.out,
            format=args.format,
            cameras=[c.strip() for c in args.cameras.split(",") if c.strip()]
            if args.cameras
            else None,
            include_pending=args.include_pending,
            drop_rejected_instances=args.drop_rejected_instances,
            poses=args.poses,
            layout=args.layout,
            sensors=args.sensors,
            overwrite=args.overwrite,
            progress=progress,
            remove_markers=args.remove_markers,
            fill=args.marker_fill or "surface",
        )
    finally:
        for bar in bars:
            bar.close()
    return finish(summary, as_json=args.json)
