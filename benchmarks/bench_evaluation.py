"""Pose distances per second, and the whole ``annotator evaluate`` process on 100 scenes x 30
true poses x 50 results in the paper's folder format (gt/<scene>.json, poseutils.json, a
results folder of <scene>.json lists, metres).

Targets: >= 1e6 distances per second; the whole evaluation process (Python start-up and
imports included) at least 100x faster than the authors' evaluation code, which takes about
0.9-1.9 s per scene of this size on these machines (90-190 s for the 100 scenes).

    .venv/bin/python -m benchmarks.bench_evaluation
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from annotator.formats.sileane import poseutils_to_json
from annotator.geometry.transforms import random_rotations
from annotator.parts import build_part
from annotator.symmetry import PoseSpace, finite_group

AUTHORS_SECONDS_PER_SCENE = 0.9  # the faster end of the authors' code, measured on this machine


def write_problem(
    root: Path,
    *,
    scenes: int,
    n_true: int,
    n_results: int,
    rng: np.random.Generator,
    part: str = "gear",
    ties: bool = True,
) -> tuple[Path, Path]:
    """A random evaluation problem in the paper's format: ``root/gt_folder`` (gt/ and
    poseutils.json) and ``root/results``. Results are near-copies of true poses (some
    duplicates), and random poses; scores are rounded so that some tie; occlusion rates
    include the bound 0.5 exactly."""
    p = build_part(part)
    space = PoseSpace.from_moments(p.mesh.moments, p.symmetry)
    data, res = root / "gt_folder", root / "results"
    (data / "gt").mkdir(parents=True)
    res.mkdir()
    (data / "poseutils.json").write_text(
        json.dumps(poseutils_to_json(space, threshold_mm=0.1 * space.diameter))
    )
    for k in range(scenes):
        Rg = random_rotations(n_true, rng)
        tg = rng.uniform(-150, 150, (n_true, 3)) + [0, 0, 600]
        occ = rng.choice([0.0, 0.2, 0.5, 0.5001, 0.7, 0.95], n_true)
        gt = [
            {"R": R.tolist(), "t": (t / 1000).tolist(), "occlusion_rate": float(o)}
            for R, t, o in zip(Rg, tg, occ)
        ]
        Rr = random_rotations(n_results, rng)
        tr = rng.uniform(-150, 150, (n_results, 3)) + [0, 0, 600]
        if n_true:
            pick = rng.integers(0, n_true, n_results)
            near = rng.random(n_results) < 0.7
            Rr = np.where(near[:, None, None], Rg[pick], Rr)
            tr = np.where(near[:, None], tg[pick] + rng.normal(0, 4, (n_results, 3)), tr)
        score = rng.random(n_results)
        if ties:
            score = np.round(score, 1)
        out = [
            {"R": R.tolist(), "t": (t / 1000).tolist(), "score": float(s)}
            for R, t, s in zip(Rr, tr, score)
        ]
        (data / "gt" / f"scene_{k:04d}.json").write_text(json.dumps(gt))
        (res / f"scene_{k:04d}.json").write_text(json.dumps(out))
    return data, res


def distances_per_second() -> None:
    rng = np.random.default_rng(0)
    part = build_part("gear")  # finite group of order 8: 8 representatives per pose
    space = PoseSpace.from_moments(part.mesh.moments, part.symmetry)
    n = 200_000
    R1, R2 = random_rotations(n, rng), random_rotations(n, rng)
    t1, t2 = rng.normal(size=(n, 3)) * 100, rng.normal(size=(n, 3)) * 100
    t0 = time.perf_counter()
    space.distance(R1, t1, R2, t2)
    rate = n / (time.perf_counter() - t0)
    # Brute force: per-vertex RMS, minimised over the group (what ADI-style code does).
    G = finite_group(part.symmetry.generators)
    v = part.mesh.vertices
    m = 2000
    t0 = time.perf_counter()
    for k in range(m):
        a = v @ R1[k].T + t1[k]
        min(np.sqrt(np.mean(np.sum((a - (v @ (R2[k] @ g).T + t2[k])) ** 2, axis=1))) for g in G)
    brute = m / (time.perf_counter() - t0)
    print(
        f"pose distance ({part.name}, {len(G)} symmetries): {rate:,.0f} per second "
        f"(target 1,000,000: ratio {rate / 1e6:.2f})"
    )
    print(
        f"  brute-force per-vertex symmetric RMS ({len(v)} vertices): {brute:,.0f} per second; "
        f"speed-up x{rate / brute:,.0f}"
    )


def whole_process(scenes: int = 100, n_true: int = 30, n_results: int = 50) -> None:
    annotator = Path(sys.executable).with_name("annotator")
    with tempfile.TemporaryDirectory() as tmp:
        data, res = write_problem(
            Path(tmp),
            scenes=scenes,
            n_true=n_true,
            n_results=n_results,
            rng=np.random.default_rng(1),
        )
        cmd = [str(annotator), "evaluate", str(data), "--results", str(res), "-n", "1", "3"]
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
            times.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        subprocess.run([str(annotator), "--help"], capture_output=True, check=True)
        startup = time.perf_counter() - t0
    best, median = min(times), float(np.median(times))
    authors = AUTHORS_SECONDS_PER_SCENE * scenes
    print(
        f"annotator evaluate, whole process, {scenes} scenes x {n_true} true poses x "
        f"{n_results} results (paper's folder format): median {median:.2f} s, best {best:.2f} s "
        f"(`annotator --help` alone: {startup:.2f} s)"
    )
    print(
        f"  vs the authors' code (~{authors:.0f} s at {AUTHORS_SECONDS_PER_SCENE} s per scene): "
        f"x{authors / median:.0f} faster (target x100: ratio {authors / median / 100:.2f})"
    )
    print("  " + out.strip().splitlines()[-1])


if __name__ == "__main__":
    distances_per_second()
    whole_process()
