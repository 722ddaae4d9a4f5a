"""Synthetic twins of annotated scenes: they reproduce the measured depth, and a pose moved by
2 mm shows up as that instance's disagreement."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from annotator.cli import main
from annotator.dataset import load_dataset, read_poses
from annotator.dataset.poses import read_pose_file, write_poses
from annotator.dataset.review import Review, now_iso, poses_fingerprint, write_review

pytestmark = pytest.mark.slow  # twin scenes rendered first


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    """A copy of the sample's first scene, one pose moved 2 mm along the view, accepted; and
    its twin and report."""
    from conftest import SAMPLE

    root = tmp_path_factory.mktemp("twin") / "ds"
    shutil.copytree(SAMPLE, root)
    for extra in sorted((root / "scenes").iterdir())[1:]:
        shutil.rmtree(extra)
    ds = load_dataset(root)
    scene = ds.scenes()[0]
    poses, top = read_pose_file(scene.annotation_path)
    moved = max(poses, key=lambda p: p.extra["occlusion"]["per_camera"]["left"] < 0.05)
    moved.t = moved.t + 2.0 * moved.t / np.linalg.norm(moved.t)
    write_poses(scene.annotation_path, poses, **top)
    write_review(scene.review_path, Review("accepted", {}, now_iso(), poses_fingerprint(poses)))
    out = root.parent / "twin"
    assert main(["synth", str(out), "--twin", str(root), "--workers", "1", "--quiet"]) == 0
    return root, out, moved.key


def test_twin_reproduces_the_measured_depth(twin, capsys) -> None:
    root, out, moved = twin
    capsys.readouterr()
    assert main(["twin-report", str(root), str(out), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    o = rep["overall"]
    assert abs(o["valid_real"] - o["valid_twin"]) < 0.01
    assert o["median_abs_mm"] < 0.5
    # The twin's ground truth is the annotation it was made from.
    truth = {p.key: p for p in read_poses(out / "scenes" / "000000" / "gt.json")}
    ann = {p.key: p for p in read_poses(root / "scenes" / "000000" / "annotation.json")}
    assert set(truth) == set(ann)
    assert all(np.allclose(truth[k].t, ann[k].t) for k in truth)
    assert (out / "report" / "histogram.png").stat().st_size > 1000
    assert (out / "report" / "000000.png").stat().st_size > 1000


def test_a_pose_moved_by_2_mm_disagrees(twin, capsys) -> None:
    root, out, moved = twin
    capsys.readouterr()
    assert main(["twin-report", str(root), str(out), "--json"]) == 0
    (scene,) = json.loads(capsys.readouterr().out)["scenes"]
    disagreeing = {i["instance"] for i in scene["instances"] if i["disagrees"]}
    assert disagreeing == {moved}
    assert main(["twin-report", str(root), str(out)]) == 0
    assert "000000" in capsys.readouterr().out
    # Pictures never land among a dataset's own files (scene 000000's pictures in its folder).
    for folder in (root / "scenes", out / "scenes" / "000000", root):
        assert main(["twin-report", str(root), str(out), "--report", str(folder)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "--report" in err, err


def test_twin_bad_input(sample_copy, tmp_path, capsys) -> None:
    code = main(["synth", str(tmp_path / "t"), "--twin", str(sample_copy), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "no accepted scene to make a twin of (4 pending)" in err
    code = main(["synth", str(sample_copy / "t"), "--twin", str(sample_copy), "--include-pending"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "lies inside the input" in err and len(err.splitlines()) == 1
