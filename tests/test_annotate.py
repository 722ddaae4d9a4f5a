"""``annotator annotate`` end to end on the sample scenes: accuracy, faults, resumability,
bad input."""

from __future__ import annotations

import json
import os
import time

import cv2
import numpy as np
import pytest
import yaml

from annotator.cli import main
from annotator.dataset import load_dataset, read_poses
from annotator.dataset.poses import read_pose_file
from annotator.detection import MarkerDetector
from annotator.symmetry import PoseSpace


def _errors(root, scene_ids=None) -> list[tuple[str, float, float, list[str]]]:
    """(instance, error mm, diameter, flags) of each annotated instance with a true pose."""
    ds = load_dataset(root)
    out = []
    for sc in ds.scenes():
        if scene_ids and sc.id not in scene_ids:
            continue
        gt = {p.key: p for p in read_poses(sc.gt_path)}
        for p in read_poses(sc.annotation_path):
            obj = ds.objects[p.object]
            space = PoseSpace.from_moments(obj.mesh.moments, obj.symmetry)
            g = gt.get(p.key)
            err = (
                np.inf
                if g is None
                else float(space.distance(p.R[None], p.t[None], g.R[None], g.t[None])[0])
            )
            out.append((p.key, err, space.diameter, p.extra["flags"]))
    return out


def test_annotate_sample_is_accurate_and_honest(sample_copy, capsys) -> None:
    assert main(["annotate", str(sample_copy), "--force", "--json", "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["done"] == 4 and summary["failed"] == 0
    errs = _errors(sample_copy)
    rel = np.array([e / d for _, e, d, _ in errs])
    assert np.median(rel) < 0.005
    assert all(flags for _, e, d, flags in errs if e > 0.05 * d), "a gross error without a flag"
    poses, top = read_pose_file(sample_copy / "scenes" / "000000" / "annotation.json")
    extra = poses[0].extra
    for key in (
        "uncertainty_mm",
        "reprojection_px",
        "markers",
        "views",
        "depth",
        "occlusion",
        "flags",
    ):
        assert key in extra
    assert {"unknown_markers", "duplicates", "errors", "created_at"} <= set(top)
    # Measured and rendered depth agree where the poses are right.
    depths = [p.extra["depth"] for p in poses if p.extra["depth"] is not None]
    assert len(depths) >= len(poses) // 2 and np.median([d["agreement"] for d in depths]) > 0.8


def test_resumable_skips_up_to_date_scenes(sample_copy, capsys) -> None:
    assert main(["annotate", str(sample_copy), "--scenes", "00000[01]", "--force", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["annotate", str(sample_copy), "--scenes", "00000[01]", "--json", "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out)["skipped"] == 2
    later = time.time() + 5
    os.utime(sample_copy / "scenes" / "000001" / "right.png", (later, later))
    assert main(["annotate", str(sample_copy), "--scenes", "00000[01]", "--json", "--quiet"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["done"] == 1 and s["skipped"] == 1
    assert (
        main(
            ["annotate", str(sample_copy), "--scenes", "00000[01]", "--force", "--json", "--quiet"]
        )
        == 0
    )
    assert json.loads(capsys.readouterr().out)["done"] == 2


def test_bad_scenes_are_reported_and_the_rest_is_done(sample_copy, capsys) -> None:
    scenes = sample_copy / "scenes"
    # Scene 3 annotated now, so that it is up to date whatever the files' checkout times.
    assert main(["annotate", str(sample_copy), "--scenes", "000003", "--force", "--quiet"]) == 0
    capsys.readouterr()
    (scenes / "000000" / "right.png").unlink()
    cv2.imwrite(str(scenes / "000001" / "left.png"), np.zeros((50, 60), np.uint8))
    (scenes / "000002" / "left.png").write_bytes(b"\x89PNG\r\n\x1a\ncorrupt")
    before = (scenes / "000003" / "annotation.json").read_bytes()
    assert main(["annotate", str(sample_copy), "--quiet"]) == 1
    captured = capsys.readouterr()
    err = captured.err.splitlines()
    assert any("000000/right.png: image file is missing" in line for line in err)
    assert any("000001/left.png: image is 60x50" in line for line in err)
    assert any("000002/left.png: unreadable or corrupt image" in line for line in err)
    # Scene 3 is up to date and untouched; the failed scenes keep their earlier annotation.
    assert "1 up to date" in captured.out and "3 failed" in captured.out
    assert (scenes / "000003" / "annotation.json").read_bytes() == before
    for sid in ("000000", "000001", "000002"):
        assert read_poses(scenes / sid / "annotation.json")


def test_mislabeled_and_duplicated_markers_are_caught(sample_copy, capsys) -> None:
    ds = load_dataset(sample_copy)
    scene = ds.scene("000000")
    img = cv2.imread(str(scene.image_path("left")), cv2.IMREAD_GRAYSCALE)
    dets = MarkerDetector(ds.dictionary).detect(img)
    table = ds.marker_table
    # A marker id moved to another instance: swap it with the same site of an absent instance
    # of the same part, so that this detection now claims a wrong instance.
    gt_keys = {p.key for p in read_poses(scene.gt_path)}
    victim = next(d for d in dets if table[d.id].object == "bracket")
    ref = table[victim.id]
    obj_path = sample_copy / "objects" / ref.object / "object.yaml"
    doc = yaml.safe_load(obj_path.read_text())
    other = next(i for i in doc["instances"] if f"{ref.object}/{i['name']}" not in gt_keys)
    mine = next(i for i in doc["instances"] if i["name"] == ref.instance)
    mine["marker_ids"][ref.site], other["marker_ids"][ref.site] = (
        other["marker_ids"][ref.site],
        mine["marker_ids"][ref.site],
    )
    obj_path.write_text(yaml.safe_dump(doc))
    # The same marker printed twice: paste a copy of another detected marker elsewhere.
    dup = next(d for d in dets if d.id != victim.id)
    x0, y0 = np.floor(dup.corners.min(axis=0)).astype(int) - 3
    x1, y1 = np.ceil(dup.corners.max(axis=0)).astype(int) + 3
    patch = img[y0:y1, x0:x1].copy()
    img[20 : 20 + patch.shape[0], 100 : 100 + patch.shape[1]] = patch
    cv2.imwrite(str(scene.image_path("left")), img)
    assert main(["annotate", str(sample_copy), "--scenes", "000000", "--quiet"]) == 0
    poses, top = read_pose_file(scene.annotation_path)
    assert dup.id in top["duplicates"]["left"]
    by_key = {p.key: p for p in poses}
    assert victim.id in by_key[f"{ref.object}/{ref.instance}"].extra["markers"]["left"][
        "rejected"
    ] or (f"{ref.object}/{other['name']}" in by_key)
    for key, err, diameter, flags in _errors(sample_copy, {"000000"}):
        if err > 0.05 * diameter:
            assert flags, f"{key} is {err:.1f} mm off without a flag"


@pytest.mark.slow
def test_two_workers_give_the_same_annotations_as_one(sample_copy, capsys) -> None:
    # Workers are forked from a parent that has already used OpenCV's thread pool and open3d
    # (as here, after other tests): they must neither hang nor differ from a single process.
    from annotator.rendering.raycast import PlacedMesh, RayScene

    ds = load_dataset(sample_copy)
    cv2.GaussianBlur(np.random.default_rng(0).random((1500, 1500), np.float32), (0, 0), 4)
    obj = next(iter(ds.objects.values()))
    at = np.eye(4)
    at[2, 3] = 500.0
    assert RayScene([PlacedMesh(obj.mesh, at)]).cast(ds.rig.cameras[0].pixel_rays()).hit.any()
    threads = cv2.getNumThreads()
    results = []
    for workers in ("1", "2"):
        assert main(["annotate", str(sample_copy), "--force", "--quiet", "--workers", workers]) == 0
        results.append(
            {
                (sc.id, p.key): (p.R, p.t, p.extra["flags"])
                for sc in ds.scenes()
                for p in read_poses(sc.annotation_path)
            }
        )
    assert cv2.getNumThreads() == threads
    one, two = results
    assert one.keys() == two.keys() and len(one) > 30
    for key, (R, t, flags) in one.items():
        assert np.allclose(R, two[key][0], atol=1e-9) and np.allclose(t, two[key][1], atol=1e-6)
        assert flags == two[key][2]
