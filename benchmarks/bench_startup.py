"""Start-up: ``annotator --help`` and a plain ``annotator check sample_scenes`` as whole
processes, beside a bare Python start and the heavy imports a plain check no longer makes
(open3d, scipy.spatial, mujoco), all measured in this run (median of ``--runs``).

Targets: ``--help`` <= 0.3 s, ``check`` without ``--physics`` <= 0.6 s (tests/test_startup.py
fails when a plain check imports open3d).

    .venv/bin/python -m benchmarks.bench_startup [--runs 7]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _median(cmd: list[str], runs: int) -> float:
    seconds = []
    for _ in range(runs):
        start = time.perf_counter()
        subprocess.run(cmd, check=False, capture_output=True, cwd=ROOT)
        seconds.append(time.perf_counter() - start)
    return statistics.median(seconds)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=7)
    args = ap.parse_args()
    py = sys.executable
    bare = _median([py, "-c", "pass"], args.runs)
    heavy = _median([py, "-c", "import open3d, scipy.spatial, mujoco"], args.runs)
    rows = [
        ("annotator --help", [py, "-m", "annotator", "--help"], 0.3),
        ("annotator check sample_scenes", [py, "-m", "annotator", "check", "sample_scenes"], 0.6),
    ]
    print(
        f"bare Python start: {bare:.3f} s; importing open3d, scipy.spatial, mujoco: {heavy:.3f} s"
    )
    ok = True
    for name, cmd, target in rows:
        got = _median(cmd, args.runs)
        met = "" if got <= target else "  NOT met"
        ok = ok and got <= target
        print(
            f"{name}: {got:.3f} s (median of {args.runs}; {got / bare:.1f}x a bare Python "
            f"start, {got / heavy:.2f}x the heavy imports alone; target {target} s){met}"
        )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
