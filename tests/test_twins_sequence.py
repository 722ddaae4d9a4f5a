"""Synthetic twins of a moving rig's sequence: every posed frame a reviewer did not reject
rendered from the annotation (scene frame) through the frame's ``scene_T_rig`` into
``frames/<frame>/``, gt.json with ``frames``, and twin-report comparing frame by frame."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from annotator.cli import main
from annotator.dataset import load_dataset, read_poses
from annotator.dataset.frames import read_frames
from annotator.dataset.poses import read_pose_file, write_poses
from annotator.dataset.review import (
    Review,
    ReviewStatus,
    now_iso,
    poses_fingerprint,
    write_review,
)

pytestmark = pytest.mark.slow

REJECTED = "000001"


@pytest.fixture(scope="module")
def sequence_twin(tmp_path_factory):
    """A synthetic sequence of 4 frames, annotated, its least occluded instance moved 2 mm
    along the scene frame's view, frame REJECTED rejected on its own, the scene accepted; and
    its twin."""
    root = tmp_path_factory.mktemp("twinseq") / "ds"
    synth = ["synth", str(root), "--scenes", "1", "--frames", "4", "--size", "640x512"]
    synth += ["--supersample", "1", "--instances", "4-6", "--seed", "5", "--quiet"]
    assert main(synth) == 0
    assert main(["annotate", str(root), "--quiet"]) == 0
    scene = load_dataset(root).scenes()[0]
    poses, top = read_pose_file(scene.annotation_path)
    moved = min(poses, key=lambda p: p.extra["occlusion"]["rate"])
    moved.t = moved.t + 2.0 * moved.t / np.linalg.norm(moved.t)
    write_poses(scene.annotation_path, poses, **top)
    review = Review("accepted", {}, now_iso(), poses_fingerprint(poses))
    write_review(scene.review_path, replace(review, frames={REJECTED: ReviewStatus.REJECTED}))
    out = root.parent / "twin"
    assert main(["synth", str(out), "--twin", str(root), "--workers", "1", "--quiet"]) == 0
    return root, out, moved.key


def test_the_twin_of_a_sequence_has_its_posed_frames(sequence_twin, capsys) -> None:
    root, out, _ = sequence_twin
    real = read_frames(root / "scenes" / "000000" / "annotation.json")
    expected = sorted(f for f, e in real.items() if e.scene_T_rig is not None and f != REJECTED)
    assert len(expected) >= 2
    twin = load_dataset(out)
    assert twin.rig.moving
    (scene,) = twin.scenes()
    assert [f.name for f in scene.frames()] == expected
    for frame in scene.frames():
        for name in ("left.png", "right.png", "depth.png", "depth_ideal.png"):
            assert (frame.path / name).stat().st_size > 1000, (frame.id, name)
        assert not (scene.path / "left.png").exists()  # a sequence's scene holds no images
    # gt.json: the annotation's poses in the scene frame, each frame where the real one was.
    truth = {p.key: p for p in read_poses(scene.gt_path)}
    ann = {p.key: p for p in read_poses(root / "scenes" / "000000" / "annotation.json")}
    assert set(truth) == set(ann)
    assert all(np.allclose(truth[k].T, ann[k].T) for k in truth)
    frames = read_frames(scene.gt_path)
    assert sorted(frames) == expected
    for name, entry in frames.items():
        assert np.allclose(entry.scene_T_rig, real[name].scene_T_rig)
        assert entry.instances, name  # the instances in the frame's view
    capsys.readouterr()
    assert main(["check", str(out)]) == 0


def test_twin_report_compares_frame_by_frame(sequence_twin, capsys) -> None:
    root, out, moved = sequence_twin
    twin_frames = [f.name for f in load_dataset(out).scenes()[0].frames()]
    capsys.readouterr()
    assert main(["twin-report", str(root), str(out), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert [r["scene"] for r in rep["scenes"]] == [f"000000/{f}" for f in twin_frames]
    assert rep["overall"]["median_abs_mm"] < 1.0
    checked = 0
    for row in rep["scenes"]:
        assert row["part_pixels"] > 1000, row["scene"]
        seen = {i["instance"]: i for i in row["instances"]}
        # The pose moved by 2 mm disagrees wherever the frame sees it.
        if seen[moved]["pixels"] > 500:
            assert seen[moved]["disagrees"], row["scene"]
            checked += 1
        frame = row["scene"].split("/")[1]
        assert (out / "report" / "000000" / f"{frame}.png").stat().st_size > 1000
    assert checked >= 2
    assert (out / "report" / "histogram.png").stat().st_size > 1000
    assert main(["twin-report", str(root), str(out)]) == 0
    assert f"000000/{twin_frames[0]}" in capsys.readouterr().out


def test_the_twin_of_a_one_camera_sequence(tmp_path, capsys) -> None:
    """One camera with depth (an RGB-D sensor's colour camera): the twin's depth comes from a
    simulated stereo partner that is rendered for the depth only, never written."""
    root = tmp_path / "ds"
    synth = ["synth", str(root), "--scenes", "1", "--frames", "3", "--cameras", "1"]
    synth += ["--size", "640x512", "--supersample", "1", "--instances", "4-6", "--seed", "5"]
    assert main([*synth, "--quiet"]) == 0
    assert main(["annotate", str(root), "--quiet"]) == 0
    out = tmp_path / "twin"
    args = ["synth", str(out), "--twin", str(root), "--include-pending", "--quiet"]
    assert main(args) == 0
    frames = load_dataset(out).scenes()[0].frames()
    assert frames
    for frame in frames:
        assert sorted(p.name for p in frame.path.iterdir()) == [
            "depth.png",
            "depth_ideal.png",
            "left.png",
        ]
    capsys.readouterr()
    assert main(["twin-report", str(root), str(out), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert [r["scene"] for r in rep["scenes"]] == [f"000000/{f.name}" for f in frames]
    assert rep["overall"]["valid_twin"] > 0.3 and rep["overall"]["median_abs_mm"] < 1.0
