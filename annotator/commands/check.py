"""``annotator check DATASET``: list every problem of a dataset, one line each."""

from __future__ import annotations

import argparse
import json

from annotator.dataset import load_dataset
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
    physics = parser.add_argument_group("physics", "are the poses physically possible?")
    physics.add_argument(
        "--physics",
        action="store_true",
        help="check every posed scene's parts: passing through each other or their support "
        "(penetrates), resting on nothing (floats); each flagged part is a warning line",
    )
    physics.add_argument(
        "--poses",
        choices=("annotation", "gt"),
        default="annotation",
        help="--physics: the poses checked (annotation.json with the review's repairs, or gt.json)",
    )
    physics.add_argument(
        "--stability",
        action="store_true",
        help="--physics: also leave each pile to gravity for a moment in MuJoCo and flag the "
        "parts that fall (unstable); seconds per scene",
    )


def run(args: argparse.Namespace) -> int:
    report = check_dataset(args.dataset, annotations=args.annotations)
    problems, scenes = report.problems, report.scenes
    physics = None
    if (args.physics or args.stability) and not report.errors:
        # Physics needs open3d, scipy.spatial and mujoco (about a second to import): only
        # when asked for, so that a plain check starts at once.
        from annotator.physics.dataset import physics_of_dataset, physics_problems

        ds = load_dataset(args.dataset)
        physics = physics_of_dataset(ds, poses=args.poses, stability=args.stability)
        problems = problems + physics_problems(ds, physics, args.poses)
    if args.json:
        print(
            json.dumps(
                {
                    **({"physics": physics.to_json()} if physics is not None else {}),
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
