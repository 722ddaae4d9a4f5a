"""Markers glued by hand: pose error and flags before and after ``annotator sites``, the
measured sites against the true glued ones, and the command's seconds.

Two datasets of ``--scenes`` scenes (two 1280x1024 cameras, 8-12 parts of bracket, brick and
cylinder, with depth), made by ``annotator synth``: one whose markers are glued by hand
(``--glue 0.7,2``: each marker of each instance moved in its plane by N(0, 0.7 mm) per axis
and turned by N(0, 2 degrees)), one with markers exactly on their sites. On each:
annotate, then ``annotator sites --yes``, then annotate again; everything as whole processes.

    .venv/bin/python -m benchmarks.bench_sites [--scenes 15] [--rounds 1] [--seed 5] [--keep DIR]
        [--anchor REV]

Targets (issue 54): after one ``sites`` and a re-annotation of the glued scenes, median pose
error no worse than the code's when the issue was filed (commit :data:`ANCHOR`, run beside
today's on a copy of the same scenes: the issue's 0.154% of D was measured on other scenes;
``--anchor ''`` compares with that figure instead), p95 <= 1% of D, flagged poses <= 25%, no pose off by more than 1% of D
without a flag; and, from before: posed >= 95% of the parts at least half visible; measured
sites within 0.2 mm RMS (corner positions) of the true glued sites over the markers used in
at least 3 scenes; on exact sites, median error within 10% of before and corrections under
0.1 mm RMS; ``annotator sites`` under a minute. Also printed: the share of poses within 3x
their stated uncertainty, and the measured sites' error against the truth by the number of
scenes they were measured from (what ``annotate``'s trust in a site, ``site_scenes``, rests
on).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from annotator.dataset import load_dataset
from devkit.whole_process import code_at, posed_of_visible, relative_errors, run_annotator as run

#: The code when issue 54 was filed: its median on the same scenes is the one not to lose.
ANCHOR = "4a39c81"


def pose_figures(root: Path) -> dict[str, float]:
    """Pose error (% of D), flags and posed fraction of the parts at least half visible."""
    errors, rel, flagged = relative_errors(root)
    posed, visible = posed_of_visible(root, errors)
    return {
        "median": float(np.median(rel)),
        "p95": float(np.percentile(rel, 95)),
        "flagged": float(flagged.mean()),
        "gross_unflagged": int(((rel > 5) & ~flagged).sum()),
        "within_3_sigma": float(
            np.mean(
                [e["error_mm"] <= 3 * e["uncertainty_mm"] for e in errors if e["uncertainty_mm"]]
            )
        ),
        "over_1pct_unflagged": int(((rel > 1) & ~flagged).sum()),
        "posed": posed / max(visible, 1),
        "poses": len(rel),
    }


def without_gauge(measured: np.ndarray, true: np.ndarray, directions: list[str]) -> np.ndarray:
    """``measured`` (K, 4, 3) moved by the rigid motion, made of the ``directions`` the
    solve reported as not observable only, that brings it nearest to ``true``: no tool can
    measure those (for a cylinder's turn about its axis, it is a symmetry of the part), so
    they are left out of the comparison."""
    if not directions or len(measured) == 0:
        return measured
    centre = measured.reshape(-1, 3).mean(axis=0)
    fields = []
    for d in directions:
        kind, axis = d.rsplit(" ", 1)
        a = np.eye(3)["xyz".index(axis)]
        field = (
            np.cross(a, measured - centre)
            if kind == "turn about"
            else np.broadcast_to(a, measured.shape)
        )
        fields.append(field.reshape(-1))
    A = np.stack(fields, axis=1)
    amp = np.linalg.lstsq(A, (true - measured).reshape(-1), rcond=None)[0]
    return measured + (A @ amp).reshape(measured.shape)


def site_errors(root: Path, report: dict) -> tuple[float, float, int]:
    """RMS corner error (mm) of the layout and of the measured sites against the truth, over
    the markers used in at least 3 scenes (the measured ones up to the motions the solve
    reported as not observable, see :func:`without_gauge`)."""
    truth = json.loads((root / "glued_sites.json").read_text())
    ds = load_dataset(root)
    before, after = [], []
    for rec in report["instances"]:
        obj, inst = rec["instance"].split("/")
        true = np.asarray(truth[obj][inst])
        layout = ds.objects[obj].markers.corners
        measured = ds.objects[obj].site_corners(inst)
        keep = [m["site"] for m in rec["markers"] if m["scenes"] >= 3]
        aligned = without_gauge(measured[keep], true[keep], rec["unobservable"])
        before += list(np.mean(np.sum((layout[keep] - true[keep]) ** 2, -1), axis=1))
        after += list(np.mean(np.sum((aligned - true[keep]) ** 2, -1), axis=1))
    return float(np.sqrt(np.mean(before))), float(np.sqrt(np.mean(after))), len(after)


def by_scenes(root: Path) -> dict[str, tuple[int, float]]:
    """The measured sites' RMS corner error (mm) against the truth, gauge included (what a
    pose meets), by the number of scenes object.yaml's ``site_scenes`` says they were
    measured from (``"5+"`` five or more)."""
    truth = json.loads((root / "glued_sites.json").read_text())
    ds = load_dataset(root)
    groups: dict[str, list[float]] = {}
    for obj, insts in truth.items():
        for inst, true in insts.items():
            counts = ds.objects[obj].instance(inst).site_scenes
            if counts is None:
                continue
            sq = np.mean(np.sum((ds.objects[obj].site_corners(inst) - true) ** 2, -1), axis=1)
            for n, e in zip(counts, sq):
                groups.setdefault(str(n) if n < 5 else "5+", []).append(float(e))
    return {n: (len(v), float(np.sqrt(np.mean(v)))) for n, v in sorted(groups.items())}


def corrections_rms(report: dict) -> float:
    c = [
        m["du_mm"] ** 2 + m["dv_mm"] ** 2
        for rec in report["instances"]
        for m in rec["markers"]
        if m["scenes"] >= 1
    ]
    return float(np.sqrt(np.mean(c))) if c else 0.0


def one(
    root: Path, glue: str, scenes: int, rounds: int, seed: int, *, anchor: str | None = None
) -> tuple[dict, dict | None]:
    """Make the dataset, then annotate / sites / annotate it; with ``anchor`` (a commit) the
    same on a copy of the same scenes by that commit's code, side by side."""
    run(
        "synth", str(root), "--parts", "bracket,brick,cylinder", "--scenes", str(scenes),
        "--instances", "8-12", "--seed", str(seed), "--glue", glue, "--quiet",
    )  # fmt: skip
    theirs = None
    if anchor is not None:
        copy = root.with_name(f"{root.name}_anchor")
        shutil.copytree(root, copy)
        with code_at(anchor) as env:
            theirs = cycle(copy, rounds, env)
    return cycle(root, rounds, None), theirs


def cycle(root: Path, rounds: int, env: dict[str, str] | None) -> dict:
    """annotate, then ``rounds`` times sites + annotate: the figures after each."""
    run("annotate", str(root), "--quiet", env=env)
    out: dict[str, Any] = {"before": pose_figures(root), "rounds": []}
    for _ in range(rounds):
        seconds, text = run("sites", str(root), "--yes", "--json", "--quiet", env=env)
        report = json.loads(text)
        run("annotate", str(root), "--quiet", env=env)
        out["rounds"].append(
            {
                "seconds": seconds,
                "poses": pose_figures(root),
                "report": report,
                "corrections_rms": corrections_rms(report),
            }
        )
    return out


def show(name: str, r: dict) -> None:
    def row(label: str, f: dict) -> str:
        return (
            f"  {label:<16} median {f['median']:.3f}% D  p95 {f['p95']:.3f}% D  "
            f"flagged {100 * f['flagged']:.0f}%  gross unflagged {f['gross_unflagged']}  "
            f"> 1% D unflagged {f['over_1pct_unflagged']}  "
            f"within 3 sigma {100 * f['within_3_sigma']:.0f}%  "
            f"posed {100 * f['posed']:.1f}% ({f['poses']} poses)"
        )

    print(f"{name}:")
    print(row("annotate", r["before"]))
    for k, rd in enumerate(r["rounds"], 1):
        print(row(f"sites+annotate {k}", rd["poses"]))
        print(
            f"  {'':<16} sites took {rd['seconds']:.1f} s (whole process); corrections RMS "
            f"{rd['corrections_rms']:.3f} mm; flagged markers {rd['report']['flagged_markers']}"
        )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=15)
    ap.add_argument("--rounds", type=int, default=1, help="sites + annotate, how many times")
    ap.add_argument(
        "--seed", type=int, default=5, help="synth's seed (another one: scenes not tuned on)"
    )
    ap.add_argument(
        "--keep", type=Path, default=None, help="make the datasets here and leave them (to look)"
    )
    ap.add_argument(
        "--anchor",
        default=ANCHOR,
        help="the commit whose code runs beside today's on the same glued scenes ('' for none)",
    )
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        tmp = args.keep or Path(scratch)
        glued, theirs = one(
            Path(tmp) / "glued", "0.7,2", args.scenes, args.rounds, args.seed,
            anchor=args.anchor or None,
        )  # fmt: skip
        show("glued by hand (0.7 mm, 2 deg)", glued)
        if theirs is not None:
            show(f"the same scenes by commit {args.anchor} (when issue 54 was filed)", theirs)
        b, a, n = site_errors(Path(tmp) / "glued", glued["rounds"][-1]["report"])
        print(
            f"  sites vs truth ({n} markers used in >= 3 scenes): RMS corner error "
            f"{b:.3f} mm (layout) -> {a:.3f} mm (measured, up to the directions reported "
            "not observable); target 0.2 mm"
        )
        for scenes, (count, rms) in by_scenes(Path(tmp) / "glued").items():
            print(f"    sites measured from {scenes} scene(s): {count} markers, {rms:.3f} mm RMS")
        spread = glued["rounds"][-1]["report"]["glue_spread"]
        print(
            f"  gluing spread estimated from the data: {spread['mm']:.3f} mm, "
            f"{spread['deg']:.2f} deg (true: 0.7 mm, 2 deg)"
        )
        exact, _ = one(Path(tmp) / "exact", "0,0", args.scenes, 1, args.seed)
        show("exact sites", exact)
    after = glued["rounds"][-1]["poses"]
    ratio = exact["rounds"][0]["poses"]["median"] / exact["before"]["median"]
    if theirs is None:
        median_check = ("median <= 0.154% D (issue 54's figure)", after["median"] <= 0.154)
    else:
        was = theirs["rounds"][-1]["poses"]["median"]
        median_check = (
            f"median no worse than {args.anchor}'s on these scenes ({was:.3f}%: "
            f"x{after['median'] / was:.3f})",
            after["median"] <= was,
        )
    checks = {
        median_check[0]: median_check[1],
        "p95 <= 1% D": after["p95"] <= 1.0,
        "flagged <= 25%": after["flagged"] <= 0.25,
        "0 poses > 1% D unflagged": after["over_1pct_unflagged"] == 0,
        "posed >= 95%": after["posed"] >= 0.95,
        "sites <= 0.2 mm RMS": a <= 0.2,
        f"exact: median ratio {ratio:.3f} within 10%": abs(ratio - 1) <= 0.10,
        "exact: corrections < 0.1 mm RMS": exact["rounds"][0]["corrections_rms"] < 0.1,
        "sites < 60 s": max(r["seconds"] for r in glued["rounds"]) < 60,
    }
    for name, ok in checks.items():
        print(f"  {'met    ' if ok else 'NOT met'}  {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
