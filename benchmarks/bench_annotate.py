"""Auto-annotation on synthetic scenes with known truth: posed fraction, accuracy, honesty of
flags and warnings, uncertainty calibration, speed; on sharp scenes, on blurred ones
(sigma = 2 px over the renderer's own), and on sharp ones with injected faults (a marker id
moved to another instance, a stray marker of an absent instance on the bin wall, heavy blur
on every third scene).

Scenes: two 1280x1024 cameras, 12-20 parts of bracket, brick and cylinder (8-10 mm markers,
about 20-27 px), made by the synth library with its background depth.

    .venv/bin/python -m benchmarks.bench_annotate [--scenes N]

Targets: posed >= 95% sharp and >= 90% blurred of the parts at least half visible;
0 gross errors (> 5% of D) without a flag; every scene with an unposed visible part warned;
at most 1 complete scene in 8 warned; annotate time per scene no more than 25% above the
0.41 s of before (0.51 s); issue 55: 0.3 s per scene per worker, the physics check included.
Speed is printed as wall and CPU time (user + sys, worker processes included), the median of
three warm batches, with the load average beside it: the machine is shared.
"""

from __future__ import annotations

import os

# As the CLI does (annotator/cli.py): one BLAS thread, set before numpy is imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import resource  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402

from annotator.annotation.batch import AnnotateJob  # noqa: E402
from annotator.dataset import load_dataset, read_poses  # noqa: E402
from annotator.dataset.records import SceneAnnotation  # noqa: E402
from annotator.markers.texture import marker_image  # noqa: E402
from annotator.rendering.raycast import PlacedMesh, RayScene  # noqa: E402
from annotator.runner import run_batch  # noqa: E402
from annotator.symmetry import PoseSpace  # noqa: E402
from annotator.synthesis.generate import SynthSettings, plan_dataset, write_dataset_files  # noqa: E402

BASELINE_S = 0.41  # annotate, warm, one worker, per scene, before blur reading and completeness
TARGET_S = 0.3  # issue 55: per scene per worker, with the physics check
BATCHES = 3  # warm batches of the scenes per worker count (the median is reported)
CONFIG = SynthSettings(parts=("bracket", "brick", "cylinder"), instances=(12, 20), seed=11)


def make_dataset(root: Path, scenes: int, config: SynthSettings = CONFIG) -> None:
    plan = plan_dataset(config)
    write_dataset_files(plan, root)
    ids = [f"{k:06d}" for k in range(scenes)]

    from annotator.synthesis.generate import SceneJob

    report = run_batch(SceneJob(config, str(root)), ids, workers=2, quiet=True)
    assert not report.failed, report.failed


def markable(root: Path) -> dict[tuple[str, str], bool]:
    """For each true instance: does some camera see one of its markers (centre unoccluded,
    within 60 degrees of face-on, side >= 14 px)? Parts whose markers all face away cannot
    be posed from markers, whatever the reader."""
    ds = load_dataset(root)
    out = {}
    for sc in ds.scenes():
        gt = read_poses(sc.gt_path)
        for cam in ds.rig.cameras:
            scene = RayScene(
                [PlacedMesh(ds.objects[q.object].mesh, cam.cam_T_rig @ q.T) for q in gt]
            )
            for p in gt:
                obj = ds.objects[p.object]
                T = cam.cam_T_rig @ p.T
                seen = out.get((sc.id, p.key), False)
                for site in range(len(obj.instance(p.instance).marker_ids)):
                    if seen:
                        break
                    C = obj.markers.corners[site] @ T[:3, :3].T + T[:3, 3]
                    n, c = np.cross(C[3] - C[0], C[1] - C[0]), C.mean(axis=0)
                    if -(n / np.linalg.norm(n)) @ (c / np.linalg.norm(c)) < math.cos(
                        math.radians(60)
                    ):
                        continue
                    hit = scene.cast((c / c[2])[None, None, :]).depth[0, 0]
                    uv = cam.project(C)
                    seen = bool(np.isfinite(hit) and abs(hit - c[2]) < 2.0)
                    seen &= bool(np.linalg.norm(uv[1] - uv[0]) >= 14)
                out[(sc.id, p.key)] = seen
    return out


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
    can = markable(root)
    visible = posed = visible_m = posed_m = absent = 0
    errs, gross_silent, flagged, covered, with_unc = [], 0, 0, 0, 0
    incomplete = incomplete_warned = complete = complete_warned = total = 0
    for sc in ds.scenes():
        gt = {p.key: p for p in read_poses(sc.gt_path)}
        ann = SceneAnnotation.read(sc.annotation_path)
        posed_keys = {i.key for i in ann.instances}
        missing = False
        for key, g in gt.items():
            if g.extra["occlusion"]["rate"] >= 0.5:
                continue
            visible += 1
            posed += key in posed_keys
            if can[(sc.id, key)]:
                visible_m += 1
                posed_m += key in posed_keys
            missing |= key not in posed_keys
        warned = bool(ann.warnings)
        if missing:
            incomplete += 1
            incomplete_warned += warned
        else:
            complete += 1
            complete_warned += warned
        for i in ann.instances:
            total += 1
            flagged += bool(i.flags)
            g = gt.get(i.key)
            sp = spaces[i.object]
            if g is None:
                absent += 1
                gross_silent += not i.flags
                continue
            err = float(sp.distance(i.R[None], i.t[None], g.R[None], g.t[None])[0])
            if g.extra["occlusion"]["rate"] < 0.5:
                errs.append(err / sp.diameter)
            gross_silent += err > 0.05 * sp.diameter and not i.flags
            if i.uncertainty_mm is not None:
                with_unc += 1
                covered += err <= 3 * i.uncertainty_mm
    print(f"[{label}] {len(ds.scenes())} scenes, {total} poses ({absent} for absent instances)")
    print(
        f"  posed: {posed}/{visible} = {posed / max(visible, 1):.1%} of the parts at least half "
        f"visible; {posed_m}/{visible_m} = {posed_m / max(visible_m, 1):.1%} of those with a "
        "marker in view (within 60 degrees of face-on, >= 14 px)"
    )
    print(f"  median error (half visible): {100 * np.median(errs):.3f}% of D (target < 0.5%)")
    print(f"  gross errors (> 5% of D) without a flag: {gross_silent} (target 0)")
    print(
        f"  instances without a flag: {1 - flagged / max(total, 1):.1%}; error <= 3x estimated "
        f"uncertainty: {covered / max(with_unc, 1):.1%}"
    )
    print(
        f"  scenes with an unposed visible part that carry a warning: {incomplete_warned}/"
        f"{incomplete} (target all); complete scenes that carry none: "
        f"{complete - complete_warned}/{complete} (target at most 1 in 8 warned)"
    )


def _cpu_s() -> float:
    """User + sys seconds of this process and of its children waited for."""
    own, kids = (
        resource.getrusage(resource.RUSAGE_SELF),
        resource.getrusage(resource.RUSAGE_CHILDREN),
    )
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def speed(root: Path, ids: list[str]) -> None:
    """Seconds per scene, warm (in-process, start-up paid) and cold (the CLI, everything):
    wall and CPU, with the load average."""
    job = AnnotateJob.for_dataset(load_dataset(root))
    job.prepare()  # imports, dataset, ray tables: once per process
    job(ids[0])
    single = 0.0
    for workers in (1, 2):
        # Several batches: the machine is shared, and a neighbour's burst can slow one by a
        # third; the median batch judges the target. Each batch forks its own workers, whose
        # first scene faults their pages in, and ends with its last scene alone: over 8
        # scenes both weigh on the time per worker (a user's hundreds of scenes hardly see
        # them).
        walls, cpus = [], []
        for _ in range(BATCHES):
            t0, c0 = time.perf_counter(), _cpu_s()
            report = run_batch(job, ids, workers=workers, quiet=True)
            walls.append((time.perf_counter() - t0) / len(ids))
            cpus.append((_cpu_s() - c0) / len(ids))
            assert not report.failed, report.failed
        per, cpu = float(np.median(walls)), float(np.median(cpus))
        single = single or per
        print(
            f"speed, warm, --workers {workers}: {per:.3f} s per scene = {per * workers:.3f} s per"
            f" scene per worker, CPU {cpu:.3f} s per scene (median of {BATCHES} batches; load"
            f" {os.getloadavg()[0]:.1f}; before: {BASELINE_S} s; ratio"
            f" {per * workers / BASELINE_S:.2f}, target <= 1.25)"
            + (f"; speed-up x{single / per:.2f}" if workers == 2 else "")
        )
        batches = ", ".join(f"{w * workers:.3f}" for w in walls)
        print(
            f"  issue 55, --workers {workers}: {per * workers:.3f} s per scene per worker (CPU"
            f" {cpu:.3f} s; batches {batches}), target {TARGET_S} s:"
            f" {'met' if per * workers <= TARGET_S else 'NOT met'}"
            f"{' (CPU time within it)' if per * workers > TARGET_S >= cpu else ''}"
        )
    for workers in (1, 2):
        t0, c0 = time.perf_counter(), _cpu_s()
        cmd = [sys.executable, "-m", "annotator", "annotate", str(root), "--force", "--quiet"]
        subprocess.run([*cmd, "--workers", str(workers)], check=True, capture_output=True)
        dt, cpu = time.perf_counter() - t0, _cpu_s() - c0
        print(
            f"speed, cold CLI (Python start, imports, dataset, ray tables included), --workers"
            f" {workers}: {dt:.1f} s for {len(ids)} scenes = {dt / len(ids):.3f} s per scene;"
            f" CPU {cpu:.1f} s (load {os.getloadavg()[0]:.1f})"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--keep", metavar="DIR", help="make (or reuse) the scenes in DIR")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        tmp = args.keep or scratch
        sets = {
            "sharp": CONFIG,
            "blurred (sigma 2 px)": replace(CONFIG, seed=12, blur=2.0),
        }
        roots = {}
        for label, config in sets.items():
            root = roots[label] = Path(tmp) / label.split()[0]
            if (root / "dataset.yaml").exists():
                continue
            t0 = time.perf_counter()
            make_dataset(root, args.scenes, config)
            print(f"made {args.scenes} {label} scenes in {time.perf_counter() - t0:.0f} s")
        ids = [s.id for s in load_dataset(roots["sharp"]).scenes()]
        speed(roots["sharp"], ids)
        for label, root in roots.items():
            if label != "sharp":
                report = run_batch(
                    AnnotateJob.for_dataset(load_dataset(root)), ids, workers=2, quiet=True
                )
                assert not report.failed, report.failed
            assess(root, label)
        faulty = Path(tmp) / "faulty"
        shutil.rmtree(faulty, ignore_errors=True)
        shutil.copytree(roots["sharp"], faulty)
        inject_faults(faulty)
        report = run_batch(
            AnnotateJob.for_dataset(load_dataset(faulty)), ids, workers=2, quiet=True
        )
        assert not report.failed, report.failed
        assess(faulty, "sharp, faults injected")


if __name__ == "__main__":
    main()
