"""Foundation dataset contract: reading, writing, pose files and review decisions."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import trimesh
import yaml

from annotator.dataset import InstancePose, load_dataset, read_dataset, read_poses, write_poses
from annotator.dataset.model import Instance, MarkerSites, Rig, Symmetry
from annotator.dataset.review import Review, poses_fingerprint, read_review, write_review
from annotator.dataset.write import write_dataset_yaml, write_object_yaml
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import make_transform


def _make(tmp_path):
    root = tmp_path / "ds"
    (root / "objects" / "box").mkdir(parents=True)
    trimesh.creation.box((30, 20, 10)).export(root / "objects" / "box" / "model.ply")
    site = np.array([[[-5, 5, 5], [5, 5, 5], [5, -5, 5], [-5, -5, 5]]], float)
    write_object_yaml(
        root / "objects" / "box",
        mesh_file="model.ply",
        symmetry=Symmetry("finite", ((np.array([0, 0, 1.0]), 2),)),
        markers=MarkerSites(10.0, site),
        instances=[Instance("01", (3,)), Instance("02", (4,))],
    )
    K = np.array([[500.0, 0, 159.5], [0, 500, 119.5], [0, 0, 1]])
    rig = Rig(
        (
            Camera("left", 320, 240, K),
            Camera("right", 320, 240, K, rig_T_cam=make_transform(np.eye(3), [100, 0, 0])),
        )
    )
    write_dataset_yaml(root, name="t", dictionary="DICT_4X4_50", rig=rig, objects=["box"])
    (root / "scenes" / "000").mkdir(parents=True)
    return root


def test_written_dataset_reads_back(tmp_path) -> None:
    root = _make(tmp_path)
    ds = load_dataset(root)
    assert [c.name for c in ds.rig.cameras] == ["left", "right"]
    assert np.allclose(ds.rig.camera("right").rig_T_cam[:3, 3], [100, 0, 0])
    box = ds.objects["box"]
    assert box.symmetry.kind == "finite" and box.symmetry.generators[0][1] == 2
    assert box.markers.corners.shape == (1, 4, 3)
    assert ds.marker_table[4].instance == "02" and ds.marker_table[4].site == 0
    assert box.mesh.faces.shape[0] == 12
    assert [s.id for s in ds.scenes()] == ["000"]


def test_every_problem_is_listed_with_its_file(tmp_path) -> None:
    root = _make(tmp_path)
    doc = yaml.safe_load((root / "dataset.yaml").read_text())
    doc["rig"]["cameras"][1]["K"] = [1, 2, 3]
    doc["rig"]["depth"] = {"camera": "left"}
    (root / "dataset.yaml").write_text(yaml.safe_dump(doc))
    obj = yaml.safe_load((root / "objects/box/object.yaml").read_text())
    obj["symmetry"] = {"class": "helical"}
    obj["instances"][1]["marker_ids"] = [3]
    (root / "objects/box/object.yaml").write_text(yaml.safe_dump(obj))
    _, problems = read_dataset(root)
    text = "\n".join(map(str, problems))
    assert "rig.cameras[1].K must have 9" in text
    assert "rig.depth.scale is missing" in text
    assert "unknown symmetry class 'helical'" in text
    assert "marker id 3 of box/02 is also used by box/01" in text
    with pytest.raises(UserError, match="dataset.yaml"):
        load_dataset(root)


def test_poses_round_trip_and_reject_bad_rotations(tmp_path) -> None:
    p = InstancePose("box", "01", np.eye(3), np.array([1.0, 2, 300]), {"flags": ["ambiguous"]})
    write_poses(tmp_path / "a.json", [p], format=1)
    (back,) = read_poses(tmp_path / "a.json")
    assert (
        back.key == "box/01"
        and np.allclose(back.t, [1, 2, 300])
        and back.extra["flags"] == ["ambiguous"]
    )
    doc = json.loads((tmp_path / "a.json").read_text())
    doc["instances"][0]["cam_R_m2c"] = [2, 0, 0, 0, 1, 0, 0, 0, 1]
    (tmp_path / "b.json").write_text(json.dumps(doc))
    with pytest.raises(UserError, match="b.json.*not a rotation"):
        read_poses(tmp_path / "b.json")


def test_review_staleness_and_corruption(tmp_path) -> None:
    poses = [InstancePose("box", "01", np.eye(3), np.array([0, 0, 300.0]))]
    fp = poses_fingerprint(poses)
    write_review(tmp_path / "review.json", Review("accepted", {"box/01": "accepted"}, "now", fp))
    r = read_review(tmp_path / "review.json")
    assert r is not None and not r.is_stale(fp)
    moved = [InstancePose("box", "01", np.eye(3), np.array([0, 0, 301.0]))]
    assert r.is_stale(poses_fingerprint(moved))
    assert read_review(tmp_path / "none.json") is None
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(UserError, match="bad.json: corrupt review file"):
        read_review(tmp_path / "bad.json")


def test_cached_dataset_is_reloaded_when_its_description_changes(sample_copy) -> None:
    from annotator.dataset import cached_dataset

    first = cached_dataset(sample_copy)
    assert cached_dataset(sample_copy) is first  # batch workers load once
    obj = next(iter(first.objects.values()))
    path = obj.folder / "object.yaml"
    stat = path.stat()
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000_000))
    again = cached_dataset(sample_copy)
    assert again is not first and again.objects.keys() == first.objects.keys()
