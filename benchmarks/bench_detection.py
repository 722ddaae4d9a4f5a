"""Marker detection on rendered bin scenes whose marker corners are known exactly: our detector
(OpenCV's candidates, codebook lookup, edge fit) against OpenCV's own (full dictionary search,
sub-pixel corners). Time per image, markers found, corner error against the truth.

    .venv/bin/python -m benchmarks.bench_detection [--scenes N]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from annotator.dataset import load_dataset, read_poses
from annotator.detection import MarkerDetector
from benchmarks.bench_annotate import make_dataset


def corner_errors(ds, scene, cam, detections) -> tuple[list[float], int]:
    """Distances (px) of detected corners to the true ones, and the number of detections of
    markers of instances absent from the scene (false identifications)."""
    poses = {p.key: p for p in read_poses(scene.gt_path)}
    errors: list[float] = []
    false = 0
    for d in detections:
        ref = ds.marker_table.get(d.id)
        pose = None if ref is None else poses.get(f"{ref.object}/{ref.instance}")
        if pose is None:
            false += 1
            continue
        X = ds.objects[ref.object].markers.corners[ref.site]
        M = cam.cam_T_rig @ pose.T
        truth = cam.project(X @ M[:3, :3].T + M[:3, 3])
        errors += list(np.linalg.norm(d.corners - truth, axis=1))
    return errors, false


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", type=int, default=4)
    args = ap.parse_args()
    cv2.setNumThreads(1)  # per-core figures, as in batch workers
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "ds"
        make_dataset(root, args.scenes)
        ds = load_dataset(root)
        detectors = {
            "ours": MarkerDetector(ds.dictionary),
            "OpenCV": MarkerDetector(ds.dictionary, opencv_only=True),
        }
        seconds = dict.fromkeys(detectors, 0.0)
        errors: dict[str, list[float]] = {k: [] for k in detectors}
        false = dict.fromkeys(detectors, 0)
        found: dict[str, set[tuple[str, str, int]]] = {k: set() for k in detectors}
        images = 0
        for scene in ds.scenes():
            for cam in ds.rig.cameras:
                image = scene.read_image(cam)
                images += 1
                for name, det in detectors.items():
                    t0 = time.perf_counter()
                    dets = det.detect(image)
                    seconds[name] += time.perf_counter() - t0
                    e, f = corner_errors(ds, scene, cam, dets)
                    errors[name] += e
                    false[name] += f
                    found[name] |= {(scene.id, cam.name, d.id) for d in dets}
        for name in detectors:
            e = np.array(errors[name])
            print(
                f"{name:>6}: {seconds[name] / images * 1000:.0f} ms per 1280x1024 image;"
                f" {len(e) // 4} markers of present instances, {false[name]} of absent ones;"
                f" corner error median {np.median(e):.3f} px, p95 {np.percentile(e, 95):.2f} px"
            )
        ours, ref = found["ours"], found["OpenCV"]
        print(
            f"markers OpenCV finds that we miss: {len(ref - ours)}; we find and OpenCV misses:"
            f" {len(ours - ref)}; speed-up x{seconds['OpenCV'] / seconds['ours']:.1f}"
            " (target: corner median < 0.3 px)"
        )


if __name__ == "__main__":
    main()
