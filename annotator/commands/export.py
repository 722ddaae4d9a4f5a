"""``annotator export DATASET OUT --format bop|sileane``: accepted scenes, ready for others."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from tqdm import tqdm

from annotator.dataset import load_dataset
from annotator.errors import UserError
from annotator.export.bop import export_bop
from annotator.export.selection import select_scenes
from annotator.export.sileane import export_sileane
from annotator.io.atomic import atomic_folder

FORMATS = ("bop", "sileane")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="dataset folder (FORMAT.md)")
    parser.add_argument(
        "out", help="output folder (must not exist or be empty, unless --overwrite)"
    )
    parser.add_argument("--format", required=True, help="bop or sileane")
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
        choices=("annotation", "gt"),
        default="annotation",
        help="poses from annotation.json (default) or gt.json",
    )
    parser.add_argument(
        "--cameras", help="comma-separated rig cameras to export (BOP; default all)"
    )
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty OUT")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    if args.format not in FORMATS:
        raise UserError(f"unknown format {args.format!r} (expected one of {', '.join(FORMATS)})")
    ds = load_dataset(args.dataset)
    names = [c.name for c in ds.rig.cameras]
    cameras = (
        names if not args.cameras else [c.strip() for c in args.cameras.split(",") if c.strip()]
    )
    unknown = [c for c in cameras if c not in names]
    if unknown:
        raise UserError(f"unknown camera(s) {', '.join(unknown)} (the rig has {', '.join(names)})")
    out = Path(args.out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not args.overwrite:
        raise UserError("exists and is not empty (use --overwrite to replace it)", path=out)
    parent = out.resolve().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create the output folder ({exc.strerror})", path=out) from None
    if not os.access(parent, os.W_OK):
        raise UserError("the output folder is not writable", path=out)
    sel = select_scenes(
        ds,
        include_pending=args.include_pending,
        drop_rejected_instances=args.drop_rejected_instances,
        poses_from=args.poses,
    )
    if not sel.scenes:
        why = ", ".join(f"{n} {r}" for r, n in sorted(sel.reasons().items())) or "no scenes"
        raise UserError(
            f"no accepted scene to export ({why}); review them with `annotator review`, or use --include-pending",
            path=ds.root,
        )
    bar = tqdm(
        total=len(sel.scenes),
        desc=f"export {args.format}",
        unit="scene",
        disable=args.quiet or not sys.stderr.isatty(),
        file=sys.stderr,
    )
    with bar, atomic_folder(out) as tmp:
        if args.format == "bop":
            export_bop(ds, sel.scenes, tmp, cameras=cameras, progress=bar.update)
        else:
            export_sileane(ds, sel.scenes, tmp, progress=bar.update)
    summary = {
        "format": args.format,
        "out": str(out),
        "exported": len(sel.scenes),
        "left_out": sel.reasons(),
        "scenes_left_out": sel.skipped,
    }
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        why = "; ".join(f"{n} {r}" for r, n in sorted(sel.reasons().items()))
        print(
            f"export: {len(sel.scenes)} scenes written to {out} ({args.format})"
            + (f"; left out: {why}" if why else "")
        )
    return 0
