"""``annotator twin-report DATASET TWIN``: real against simulated depth, scene by scene.

TWIN is the twin of DATASET made by ``annotator synth --twin DATASET TWIN``. Prints a table
(valid-depth fractions, depth differences on the parts, instances that disagree), and writes
pictures into ``TWIN/report/`` (``--report DIR``): ``histogram.png`` of the differences and
``<scene>.png``, the real image with each instance green (agrees) or red (disagrees).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from annotator.commands import number
from annotator.errors import UserError
from annotator.io.output_folder import check_pictures_folder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="the real dataset (FORMAT.md)")
    parser.add_argument("twin", help="its twin, made by `annotator synth --twin DATASET TWIN`")
    parser.add_argument(
        "--tolerance",
        type=number(low=0),
        default=1.5,
        help="mm of depth difference that count (1.5)",
    )
    parser.add_argument(
        "--max-disagreement",
        type=number(low=0, high=1),
        default=0.3,
        help="an instance disagrees above this fraction of its pixels (0.3)",
    )
    parser.add_argument("--report", metavar="DIR", help="pictures folder (default TWIN/report)")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")


def run(args: argparse.Namespace) -> int:
    from annotator.dataset import load_dataset
    from annotator.twins.comparison import compare_twin

    if args.tolerance <= 0 or not 0 < args.max_disagreement <= 1:
        raise UserError("--tolerance must be positive and --max-disagreement in (0, 1]")
    if args.report:
        check_pictures_folder(args.report, option="--report", datasets=[args.dataset, args.twin])
    result = compare_twin(
        load_dataset(args.dataset),
        load_dataset(args.twin),
        tolerance_mm=args.tolerance,
        max_disagreement=args.max_disagreement,
        pictures=Path(args.report) if args.report else None,
        warn=lambda line: print(line, file=sys.stderr),
    )
    doc = result.to_json()
    if args.json:
        print(json.dumps(doc, indent=1))
        return 0
    _print_table(doc, args.tolerance)
    print(f"pictures: {result.pictures} (histogram.png, <scene>.png: red = disagrees)")
    return 0


def _print_table(doc: dict[str, Any], tolerance: float) -> None:
    """One row per scene and one for all of them."""
    print(
        f"{'scene':<12} {'valid real':>10} {'valid twin':>10} {'|d| median':>10} {'|d| p95':>8}  disagreeing instances"
    )
    for r in doc["scenes"]:
        bad = [i["instance"] for i in r["instances"] if i["disagrees"]]
        med = "-" if r["median_abs_mm"] is None else f"{r['median_abs_mm']:.2f} mm"
        p95 = "-" if r["p95_abs_mm"] is None else f"{r['p95_abs_mm']:.2f}"
        print(
            f"{r['scene']:<12} {r['valid_real']:>10.3f} {r['valid_twin']:>10.3f} {med:>10} {p95:>8}  {', '.join(bad) or '-'}"
        )
    o = doc["overall"]
    print(
        f"{'all':<12} {o['valid_real']:>10.3f} {o['valid_twin']:>10.3f} "
        f"{(o['median_abs_mm'] or 0):>7.2f} mm {(o['p95_abs_mm'] or 0):>8.2f}  "
        f"{o['instances_disagreeing']} instance(s) disagree (> {doc['max_disagreement']:.0%} of "
        f"pixels beyond {tolerance:g} mm)"
    )
