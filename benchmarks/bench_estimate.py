"""The paper's table 3 on our data: the PPF baseline with and without the symmetry-aware mode
finding and duplicate removal (``--symmetric``), with and without the post-processing
(``--post-process``), on synthetic bin scenes of one part per symmetry class: bracket (none),
brick (finite, half turn), gear (finite, 8 teeth), cylinder (revolution with flip).

Per part, ``annotator synth`` makes ``--scenes`` scenes (640x512, 8-12 parts, depth from
simulated active stereo); the four variants run on every scene (the votes, which do not
depend on the variant, are computed once per scene and shared; each variant's time counts
them), and ``annotator evaluate``'s reader and scoring give AP, AP_1 and AP_3 (threshold 10%
of the diameter, instances at most 50% occluded). The results files are checked to be those
``annotator estimate`` writes (on two scenes of the first part).

Target (the paper's finding): on the symmetric parts ``--symmetric`` gives a higher AP than
without (ratio > 1); on the part without symmetry it changes nothing beyond noise (ratio
within 1 +- 0.05).

    .venv/bin/python -m benchmarks.bench_estimate [--scenes 20] [--workers 2] [--keep DIR]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from annotator.cli import main as annotator
from annotator.estimation.estimator import variants
from annotator.estimation.job import EstimateJob
from annotator.estimation.results import write_results
from annotator.evaluation.evaluate import EvaluationSettings, evaluate
from annotator.formats import ours
from annotator.runner import available_cpus, run_batch

PARTS = ("bracket", "brick", "gear", "cylinder")
VARIANTS = variants(symmetric=(False, True), post_process=(False, True))


def make_scenes(root: Path, part: str, scenes: int, workers: int, seed: int) -> Path:
    """``annotator synth`` of one part, reused when ``root/part`` already has the scenes."""
    out = root / part
    if out.is_dir() and len(list((out / "scenes").glob("*/depth.png"))) == scenes:
        return out
    args = ["synth", str(out), "--parts", part, "--scenes", str(scenes), "--instances", "8-12"]
    args += ["--size", "640x512", "--seed", str(seed), "--workers", str(workers), "--quiet"]
    if annotator(args + (["--overwrite"] if out.exists() else [])) != 0:
        raise SystemExit(f"synth failed for {part}")
    return out


def run_part(ds: Path, workers: int, results: Path) -> tuple[list[dict], list[float]]:
    """Every variant on every scene: per variant the scores and the mean seconds per scene."""
    ids = sorted(p.name for p in (ds / "scenes").iterdir() if p.is_dir())
    report = run_batch(EstimateJob(str(ds), tuple(VARIANTS)), ids, workers=workers, quiet=True)
    if report.failed:
        report.print_failures()
        raise SystemExit("estimation failed")
    gt = ours.read_ground_truth(ds)
    scores, seconds = [], []
    for k, v in enumerate(VARIANTS):
        csv = results / f"{ds.name}_{v.label.replace(' ', '_')}.csv"
        write_results(csv, [row for sid in ids for row in report.done[sid]["rows"][k]])
        s = evaluate(gt, ours.read_results(csv, gt), EvaluationSettings(max_results=(1, 3))).overall
        scores.append({"AP": s.ap, "AP_1": s.ap_n[1], "AP_3": s.ap_n[3]})
        seconds.append(float(np.mean([report.done[sid]["seconds"][k] for sid in ids])))
    return scores, seconds


def same_as_command(ds: Path, results: Path) -> bool:
    """``annotator estimate --symmetric`` on two scenes writes the benchmark's lines (time
    column aside)."""
    out = results / "command.csv"
    args = ["estimate", str(ds), str(out), "--symmetric", "--scenes", "00000[01]"]
    if annotator(args + ["--workers", "2", "--quiet"]) != 0:
        return False
    mine = (results / f"{ds.name}_PPF_sym.csv").read_text().splitlines()
    theirs = out.read_text().splitlines()

    def strip(lines: list[str], keep: set[str] | None = None) -> list[str]:
        rows = [ln.rsplit(",", 1)[0] for ln in lines[1:]]
        return [r for r in rows if keep is None or r.split(",")[0] in keep]

    return strip(theirs) == strip(mine, {"0", "1"})


def table(rows: dict[str, list[dict]], seconds: dict[str, list[float]]) -> str:
    lines = []
    groups = " | ".join(f"{v.label:^16}" for v in VARIANTS)
    lines.append(f"{'':10} | {groups}")
    lines.append(
        f"{'part':10} | " + " | ".join(f"{'AP':>4} {'AP1':>5} {'AP3':>5}" for _ in VARIANTS)
    )
    lines.append("-" * len(lines[-1]))
    for part, scores in rows.items():
        cells = " | ".join(f"{s['AP']:.2f}  {s['AP_1']:.2f}  {s['AP_3']:.2f}" for s in scores)
        lines.append(f"{part:10} | {cells}")
    secs = np.mean([seconds[p] for p in rows], axis=0)
    lines.append(f"{'s/scene':10} | " + " | ".join(f"{s:^16.2f}" for s in secs))
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scenes", type=int, default=20, help="scenes per part (default 20)")
    ap.add_argument("--workers", type=int, default=available_cpus())
    ap.add_argument("--parts", default=",".join(PARTS))
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--keep", metavar="DIR", help="make (or reuse) the scenes and results in DIR")
    args = ap.parse_args()
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.keep) if args.keep else Path(tmp)
        results = root / "results"
        results.mkdir(parents=True, exist_ok=True)
        rows, seconds = {}, {}
        for k, part in enumerate(parts):
            ds = make_scenes(root, part, args.scenes, args.workers, args.seed + k)
            rows[part], seconds[part] = run_part(ds, args.workers, results)
            print(f"{part}: done", flush=True)
        checked = same_as_command(root / parts[0], results) if args.scenes >= 2 else None
    print()
    print(
        f"PPF on {args.scenes} synthetic scenes per part (640x512, 8-12 parts each); AP, AP_1, "
        "AP_3 for instances at most 50% occluded, threshold 10% of the diameter"
    )
    print(table(rows, seconds))
    print("  (s/scene: one worker, one thread, mean over every part's scenes)")
    print()
    print("--symmetric / without, AP (target: > 1 on symmetric parts, 1 +- 0.05 without symmetry):")
    ok = True
    for part in parts:
        sym = build_symmetry(part)
        r = [rows[part][i + 1]["AP"] / max(rows[part][i]["AP"], 1e-9) for i in (0, 2)]
        good = all(x > 1.0 for x in r) if sym != "none" else all(abs(x - 1) <= 0.05 for x in r)
        ok &= good
        print(
            f"  {part:9} ({sym}): x{r[0]:.2f} without post-processing, x{r[1]:.2f} with "
            f"{'(ok)' if good else '(MISSED)'}"
        )
    if checked is not None:
        print(f"results file identical to `annotator estimate --symmetric`'s: {checked}")
    print("target met" if ok and checked is not False else "target MISSED")


def build_symmetry(part: str) -> str:
    from annotator.parts import build_part

    return build_part(part).symmetry.kind


if __name__ == "__main__":
    main()
