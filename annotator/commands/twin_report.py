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

from annotator.commands import number
from annotator.errors import UserError


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
    import numpy as np

    from annotator.dataset import load_dataset, read_poses
    from annotator.io.images import write_png
    from annotator.twins.report import compare_scene, histogram_png, overlay

    if args.tolerance <= 0 or not 0 < args.max_disagreement <= 1:
        raise UserError("--tolerance must be positive and --max-disagreement in (0, 1]")
    ds = load_dataset(args.dataset)
    twin = load_dataset(args.twin)
    if ds.rig.depth is None:
        raise UserError("the dataset has no depth maps to compare (rig.depth)", path=ds.root)
    depth_cam = ds.rig.depth_camera
    assert depth_cam is not None  # rig.depth is set
    twins = {s.id: s for s in twin.scenes() if s.gt_path.exists()}
    if not twins:
        raise UserError("no twin scene (run `annotator synth --twin` first)", path=twin.root)
    report_dir = Path(args.report) if args.report else twin.root / "report"
    rows, diffs = [], []
    for sid, tsc in sorted(twins.items()):
        try:
            real_scene = ds.scene(sid)
        except KeyError:
            print(f"warning: twin scene {sid} has no scene in {ds.root}", file=sys.stderr)
            continue
        real = real_scene.read_depth(ds.rig)
        sim = tsc.read_depth(twin.rig)
        if real is None or sim is None:
            print(f"warning: scene {sid} has no depth map to compare", file=sys.stderr)
            continue
        poses = read_poses(tsc.gt_path)
        comp, front = compare_scene(ds, sid, real, sim, poses, tolerance_mm=args.tolerance)
        rows.append(comp)
        diffs.append(comp.part_diffs)
        img = real_scene.read_image(depth_cam)
        write_png(report_dir / f"{sid}.png", overlay(img, front, comp, args.max_disagreement, 2))
    if not rows:
        raise UserError("no scene with depth in both datasets", path=twin.root)
    all_diffs = np.concatenate(diffs) if diffs else np.zeros(0)
    histogram_png(all_diffs, report_dir / "histogram.png")
    lim = args.max_disagreement
    doc = {
        "tolerance_mm": args.tolerance,
        "max_disagreement": lim,
        "scenes": [r.to_json(lim) for r in rows],
        "overall": {
            "valid_real": round(float(np.mean([r.valid_real for r in rows])), 4),
            "valid_twin": round(float(np.mean([r.valid_twin for r in rows])), 4),
            "median_abs_mm": round(float(np.median(np.abs(all_diffs))), 3)
            if len(all_diffs)
            else None,
            "p95_abs_mm": round(float(np.percentile(np.abs(all_diffs), 95)), 3)
            if len(all_diffs)
            else None,
            "instances_disagreeing": sum(i.disagrees(lim) for r in rows for i in r.instances),
        },
        "pictures": str(report_dir),
    }
    if args.json:
        print(json.dumps(doc, indent=1))
        return 0
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
        f"{o['instances_disagreeing']} instance(s) disagree (> {lim:.0%} of pixels beyond "
        f"{args.tolerance:g} mm)"
    )
    print(f"pictures: {report_dir} (histogram.png, <scene>.png: red = disagrees)")
    return 0
