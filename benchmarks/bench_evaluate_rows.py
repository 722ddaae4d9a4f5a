"""``annotator evaluate`` on a million result rows: the whole process's seconds and peak memory.

A BOP dataset of 3 scenes (10 true poses each, two objects: one without symmetry, one with a
half-turn symmetry) and a BOP CSV of ``--rows`` results (near-copies of the true poses and
random poses, scores with ties), written with a header whose columns are reordered and a
UTF-8 byte-order mark, as files met in the wild are. Time and memory should grow linearly
with the rows.

Targets: 1M rows under 20 s and under 2 GB peak resident memory, whole process.

    .venv/bin/python -m benchmarks.bench_evaluate_rows [--rows 1000000]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh

from annotator.geometry.transforms import random_rotations

TARGET_SECONDS = 20.0
TARGET_GB = 2.0


def write_dataset(root: Path, *, scenes: int, n_true: int, rng: np.random.Generator) -> list:
    (root / "models").mkdir(parents=True)
    trimesh.creation.box(extents=(60, 40, 20)).export(root / "models" / "obj_000001.ply")
    trimesh.creation.box(extents=(50, 50, 10)).export(root / "models" / "obj_000002.ply")
    half_turn = [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
    info = {
        "1": {"diameter": 76.3},
        "2": {"diameter": 71.4, "symmetries_discrete": [half_turn]},
    }
    (root / "models" / "models_info.json").write_text(json.dumps(info))
    truth = []
    for s in range(scenes):
        folder = root / "test" / f"{s + 1:06d}"
        folder.mkdir(parents=True)
        R = random_rotations(n_true, rng)
        t = rng.uniform(-150, 150, (n_true, 3)) + [0, 0, 600]
        obj = rng.integers(1, 3, n_true)
        gt = [
            {"obj_id": int(o), "cam_R_m2c": r.ravel().tolist(), "cam_t_m2c": v.tolist()}
            for o, r, v in zip(obj, R, t)
        ]
        (folder / "scene_gt.json").write_text(json.dumps({"0": gt}))
        info = [{"visib_fract": float(v)} for v in rng.uniform(0.2, 1.0, n_true)]
        (folder / "scene_gt_info.json").write_text(json.dumps({"0": info}))
        truth.append((obj, R, t))
    return truth


def write_results(path: Path, truth: list, *, rows: int, rng: np.random.Generator) -> None:
    per_scene = rows // len(truth)
    lines = ["\ufeffscore,scene_id,obj_id,im_id,R,t,time"]
    for s, (obj, R, t) in enumerate(truth):
        pick = rng.integers(0, len(obj), per_scene)
        Rs = random_rotations(per_scene, rng)
        near = rng.random(per_scene) < 0.5
        Rs[near] = R[pick[near]]
        ts = t[pick] + rng.normal(0, 2.0, (per_scene, 3))
        ts[~near] += rng.uniform(-100, 100, (int((~near).sum()), 3))
        scores = np.round(rng.random(per_scene), 3)
        for k in range(per_scene):
            r = " ".join(f"{v:.6f}" for v in Rs[k].ravel())
            v = " ".join(f"{x:.3f}" for x in ts[k])
            lines.append(f"{scores[k]},{s + 1},{obj[pick[k]]},0,{r},{v},-1")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=1_000_000)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "bop"
        truth = write_dataset(root, scenes=3, n_true=10, rng=rng)
        csv = Path(tmp) / "results.csv"
        t0 = time.perf_counter()
        write_results(csv, truth, rows=args.rows, rng=rng)
        print(
            f"wrote {args.rows} rows ({csv.stat().st_size / 1e6:.0f} MB) in "
            f"{time.perf_counter() - t0:.1f} s"
        )
        exe = Path(sys.executable).with_name("annotator")
        report = Path(tmp) / "report.json"
        t0 = time.perf_counter()
        proc = subprocess.run(
            [str(exe), "evaluate", str(root), "--results", str(csv), "--json", str(report)],
            capture_output=True,
            text=True,
        )
        seconds = time.perf_counter() - t0
        peak_gb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1e6  # KiB -> GB
        if proc.returncode != 0:
            print(proc.stdout, proc.stderr, sep="\n")
            return 1
        overall = json.loads(report.read_text())["overall"]
    print(
        f"evaluate, whole process: {seconds:.1f} s, peak memory {peak_gb:.2f} GB "
        f"(AP {overall['AP']:.4f}, TP {overall['TP']}, FP {overall['FP']})"
    )
    print(
        f"ratio to the targets: time {seconds / TARGET_SECONDS:.2f} of {TARGET_SECONDS:g} s, "
        f"memory {peak_gb / TARGET_GB:.2f} of {TARGET_GB:g} GB "
        f"({'met' if seconds <= TARGET_SECONDS and peak_gb <= TARGET_GB else 'NOT met'})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
