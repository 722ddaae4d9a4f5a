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
from annotator.export.selection import select_scenes
from annotator.formats import EXPORTS, get_format
from annotator.io.atomic import atomic_folder
from annotator.io.output_folder import check_output_folder, write_manifest


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
        choices=("annotation", "gt"),
        default="annotation",
        help="poses from annotation.json (default) or gt.json",
    )
    parser.add_argument(
        "--cameras", help="comma-separated rig cameras to export (BOP; default all)"
    )
    parser.add_argument(
        "--layout",
        choices=("scenewise", "imagewise", "webdataset"),
        default="scenewise",
        help="BOP: scene folders (default), bop_toolkit's image-wise files, or its webdataset "
        "tar shards",
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="replace OUT if an earlier export wrote it"
    )
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    if args.format not in EXPORTS:
        raise UserError(f"unknown format {args.format!r} (expected one of {', '.join(EXPORTS)})")
    fmt = get_format(args.format)
    if args.layout != "scenewise" and args.format != "bop":
        raise UserError("--layout is for --format bop")
    layout = {"layout": args.layout} if args.format == "bop" else {}
    ds = load_dataset(args.dataset)
    names = [c.name for c in ds.rig.cameras]
    cameras = (
        names if not args.cameras else [c.strip() for c in args.cameras.split(",") if c.strip()]
    )
    unknown = [c for c in cameras if c not in names]
    if unknown:
        raise UserError(f"unknown camera(s) {', '.join(unknown)} (the rig has {', '.join(names)})")
    out = Path(args.out)
    check_output_folder(out, command="export", overwrite=args.overwrite, protect=[ds.root])
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
        write_manifest(tmp, command="export")
        unreadable = fmt.export(ds, sel.scenes, tmp, cameras=cameras, progress=bar.update, **layout)
    # Scenes that could not be read (corrupt annotation, review, image or depth) are named
    # and make the exit status 1; the rest of the export is complete.
    errors = {sid: r[len("error: ") :] for sid, r in sel.skipped.items() if r.startswith("error: ")}
    errors.update(unreadable)
    left_out = {sid: r for sid, r in sel.skipped.items() if sid not in errors}
    exported = len(sel.scenes) - len(unreadable)
    reasons: dict[str, int] = {}
    for r in left_out.values():
        reasons[r] = reasons.get(r, 0) + 1
    if errors:
        reasons["unreadable"] = len(errors)
    summary = {
        "format": args.format,
        "out": str(out),
        "exported": exported,
        "left_out": reasons,
        "scenes_left_out": left_out,
        "failures": dict(sorted(errors.items())),
    }
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        for sid, err in sorted(errors.items()):
            print(f"failed: scene {sid}: {err}", file=sys.stderr)
        why = "; ".join(f"{n} {r}" for r, n in sorted(reasons.items()))
        print(
            f"export: {exported} scenes written to {out} ({args.format})"
            + (f"; left out: {why}" if why else "")
        )
    return 1 if errors else 0
