"""``annotator check DATASET``: list every problem of a dataset, one line each."""

from __future__ import annotations

import argparse
import json

from annotator.dataset.check import check_dataset


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="dataset folder (FORMAT.md)")
    parser.add_argument("--json", action="store_true", help="print the problems as JSON")
    parser.add_argument(
        "--annotations",
        action="store_true",
        help="also list the scenes whose annotation.json carries warnings (a part without a "
        "pose, blurred or badly exposed images), as warnings",
    )


def run(args: argparse.Namespace) -> int:
    report = check_dataset(args.dataset, annotations=args.annotations)
    problems, scenes = report.problems, report.scenes
    if args.json:
        print(
            json.dumps(
                {
                    "scenes": scenes,
                    "problems": [
                        {"path": str(p.path), "message": p.message}
                        for p in problems
                        if not p.warning
                    ],
                    "warnings": [
                        {"path": str(p.path), "message": p.message} for p in problems if p.warning
                    ],
                },
                indent=1,
            )
        )
    else:
        for p in problems:
            print(p)
        n = sum(not p.warning for p in problems)
        w = len(problems) - n
        print(
            f"check: {scenes} scenes, {n} problem{'s' if n != 1 else ''}"
            + (f", {w} warning{'s' if w != 1 else ''}" if w else "")
            + f" in {args.dataset}"
        )
    return 1 if any(not p.warning for p in problems) else 0
