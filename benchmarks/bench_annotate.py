"""Auto-annotation on synthetic scenes with known truth: accuracy, honesty, calibration, speed.

Scenes: two 1280x1024 cameras, 20 instances (bracket + cylinder), made by the synth library.
Then the same scenes with injected faults: a marker id moved to another instance, a stray
marker of an absent instance pasted on the bin wall, heavy blur.

    .venv/bin/python benchmarks/bench_annotate.py [--scenes N]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import yaml

from annotator.annotation.batch import AnnotateJob
from annotator.batch import run_batch
from annotator.dataset import load_dataset, read_poses
from annotator.markers.texture import marker_image
from annotator.symmetry import PoseSpace
from annotator.synthesis.generate import SynthConfig, make_scene, plan_dataset, write_dataset_files


def make_dataset(root: Path, scenes: int) -> None:
    plan = plan_dataset(SynthConfig(parts=("bracket", "cylinder"), instances=(20, 20), seed=11))
    write_dataset_files(plan, root)
    for k in range(scenes):
        folder = root / "scenes" / f"{k:06d}"
        folder.mkdir(parents=True)
        make_scene(plan, k, folder)


def inject_faults(root: Path) -> None:
    ds = load_dataset(root)
    rng = np.random.default_rng(0)
    # 1. A marker id moved to another (absent) instance of the same part, in object.yaml.
    doc = yaml.safe_load((root / "objects/bracket/object.yaml").read_text())
    a, b = doc["instances"][0], doc["instances"][-1]
    for site in range(0, len(a["marker_ids"]), 5):
        a["marker_ids"][site], b["marker_ids"][site] = b["marker_ids"][site], a["marker_ids"][site]
    (root / "objects/bracket/object.yaml").write_text(yaml.safe_dump(doc))
    for k, scene in enumerate(ds.scenes()):
        present = {p.key for p in read_poses(scene.gt_path)}
        absent = [
            i for i in ds.objects["cylinder"].instances if f"cylinder/{i.name}" not in present
        ]
        img = cv2.imread(str(scene.image_path("left")), cv2.IMREAD_GRAYSCALE)
        if absent:
            # 2. A stray marker of an absent instance on the bin wall (top band of the image).
            m = marker_image(ds.dictionary, absent[0].marker_ids[0], 30)
            x, y = int(rng.integers(200, 1000)), 60
            img[y : y + 30, x : x + 30] = (m.astype(np.float32) * 0.8).astype(np.uint8)
        if k % 3 == 2:
            # 3. Heavy blur on both images of every third scene.
            img = cv2.GaussianBlur(img, (0, 0), 1.6)
            right = cv2.imread(str(scene.image_path("right")), cv2.IMREAD_GRAYSCALE)
            cv2.imwrite(str(scene.image_path("right")), cv2.GaussianBlur(right, (0, 0), 1.6))
        cv2.imwrite(str(scene.image_path("left")), img)


def assess(root: Path, label: str) -> None:
    ds = load_dataset(root)
    spaces = {n: PoseSpace.from_moments(o.mesh.moments, o.symmetry) for n, o in ds.objects.items()}
    rows, missing, wrong_id = [], 0, 0
    for sc in ds.scenes():
        gt = {p.key: p for p in read_poses(sc.gt_path)}
        ann = (
            {p.key: p for p in read_poses(sc.annotation_path)}
            if sc.annotation_path.exists()
            else {}
        )
        for key, g in gt.items():
            if g.extra["occlusion"]["rate"] < 0.5 and key not in ann:
                missing += 1
        for key, p in ann.items():
            sp = spaces[p.object]
            g = gt.get(key)
            if g is None:  # a pose for an instance that is not there (misread or stray marker)
                wrong_id += 1
                rows.append(
                    (
                        np.inf,
                        sp.diameter,
                        p.extra.get("uncertainty_mm") or np.inf,
                        1.0,
                        p.extra["flags"],
                    )
                )
                continue
            err = float(sp.distance(p.R[None], p.t[None], g.R[None], g.t[None])[0])
            rows.append(
                (
                    err,
                    sp.diameter,
                    p.extra.get("uncertainty_mm") or np.inf,
                    g.extra["occlusion"]["rate"],
                    p.extra["flags"],
                )
            )
    err = np.array([r[0] for r in rows])
    diam = np.array([r[1] for r in rows])
    unc = np.array([r[2] for r in rows])
    occ = np.array([r[3] for r in rows])
    flagged = np.array([bool(r[4]) for r in rows])
    interest = occ < 0.5
    n_interest = interest.sum() + missing
    gross = err > 0.05 * diam
    finite = np.isfinite(err)
    print(
        f"[{label}] {len(rows)} poses ({wrong_id} for absent instances), {n_interest} instances < 50% occluded"
    )
    print(
        f"  median error (< 50% occluded): {100 * np.median(err[interest] / diam[interest]):.3f}% of D (target < 0.5%)"
    )
    print(
        f"  posed: {interest.sum()}/{n_interest} = {interest.sum() / max(n_interest, 1):.1%} (target >= 95%)"
    )
    print(
        f"  gross errors (> 5% of D): {gross.sum()}, unflagged: {(gross & ~flagged).sum()} (target 0)"
    )
    ok = finite & np.isfinite(unc)
    print(
        f"  calibration: error <= 3x estimated uncertainty for {np.mean(err[ok] <= 3 * unc[ok]):.1%} (target >= 95%)"
    )


def speed(root: Path, ids: list[str]) -> None:
    """Seconds per scene, warm (in-process, start-up paid) and cold (the CLI, everything)."""
    job = AnnotateJob.for_dataset(load_dataset(root))
    job.prepare()  # imports, dataset, ray tables: once per process
    job(ids[0])
    single = 0.0
    for workers in (1, 2):
        t0 = time.perf_counter()
        report = run_batch(job, ids, workers=workers, quiet=True)
        per = (time.perf_counter() - t0) / len(ids)
        assert not report.failed, report.failed
        single = single or per
        print(
            f"speed, warm, --workers {workers}: {per:.3f} s per scene = {per * workers:.3f} s per"
            f" scene per worker (target < 0.5)"
            + (f"; speed-up x{single / per:.2f} (target close to 2)" if workers == 2 else "")
        )
    for workers in (1, 2):
        t0 = time.perf_counter()
        cmd = [sys.executable, "-m", "annotator", "annotate", str(root), "--force", "--quiet"]
        subprocess.run([*cmd, "--workers", str(workers)], check=True, capture_output=True)
        dt = time.perf_counter() - t0
        print(
            f"speed, cold CLI (Python start, imports, dataset, ray tables included), --workers"
            f" {workers}: {dt:.1f} s for {len(ids)} scenes = {dt / len(ids):.3f} s per scene"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", type=int, default=12)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "clean"
        t0 = time.perf_counter()
        make_dataset(root, args.scenes)
        print(f"made {args.scenes} scenes in {time.perf_counter() - t0:.0f} s")
        ids = [s.id for s in load_dataset(root).scenes()]
        speed(root, ids)
        assess(root, "clean")
        faulty = Path(tmp) / "faulty"
        shutil.copytree(root, faulty)
        inject_faults(faulty)
        report = run_batch(
            AnnotateJob.for_dataset(load_dataset(faulty)), ids, workers=2, quiet=True
        )
        assert not report.failed, report.failed
        assess(faulty, "faults injected")


if __name__ == "__main__":
    main()
