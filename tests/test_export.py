"""Occlusion exactness, export selection, and BOP / Siléane round trips."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from annotator.cli import main
from annotator.dataset import load_dataset, read_poses
from annotator.dataset.model import DepthSpec, Rig
from annotator.dataset.review import Review, now_iso, poses_fingerprint, write_review
from annotator.export.bop import read_bop_scene
from annotator.export.sileane import read_sileane_scene
from annotator.export.undistort import pinhole_rig, undistort_depth
from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.geometry.transforms import make_transform
from annotator.occlusion import scene_visibility

K = np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]])


def _box(size) -> Mesh:
    b = trimesh.creation.box(size)
    return Mesh(np.asarray(b.vertices), np.asarray(b.faces, dtype=np.int32))


def test_occlusion_zero_in_view_and_known_fraction_behind_another() -> None:
    rig = Rig((Camera("c", 640, 480, K),))
    back = make_transform(np.eye(3), [0.0, 0.0, 600.0])
    # A 40 mm square face at 600 mm spans 53.3 px; the occluder covers x in [0, 30] of it at
    # 300 mm, i.e. exactly its right half.
    front = make_transform(np.eye(3), [15.0, 0.0, 300.0])
    vis = scene_visibility(rig, [_box((40, 40, 10)), _box((30, 80, 4))], [back, front])
    alone = scene_visibility(rig, [_box((40, 40, 10))], [back])
    assert alone[0].occlusion == 0.0
    assert vis[1].occlusion == 0.0
    assert vis[0].occlusion == pytest.approx(0.5, abs=0.02)
    # A wall nobody annotated, 200 mm in front of the left half, seen only in the depth map.
    depth = np.full((480, 640), np.nan, np.float32)
    depth[:, :320] = 400.0
    rig_d = Rig((Camera("c", 640, 480, K),), depth=DepthSpec("c", 0.1))
    (v,) = scene_visibility(rig_d, [_box((40, 40, 10))], [back], depth=depth)
    assert v.cameras[0].occlusion == 0.0
    assert v.cameras[0].occlusion_depth == pytest.approx(0.5, abs=0.02)
    assert v.occlusion == v.cameras[0].occlusion_depth


def _review_all(root, status="accepted", instances=None) -> None:
    ds = load_dataset(root)
    for sc in ds.scenes():
        poses = read_poses(sc.annotation_path)
        write_review(
            sc.review_path, Review(status, instances or {}, now_iso(), poses_fingerprint(poses))
        )


def test_selection_and_bad_inputs(sample_copy, tmp_path, capsys) -> None:
    out = tmp_path / "bop"
    assert main(["export", str(sample_copy), str(out), "--format", "bop"]) == 2
    assert "no accepted scene to export (4 pending)" in capsys.readouterr().err
    assert main(["export", str(sample_copy), str(out), "--format", "coco"]) == 2
    assert "unknown format 'coco'" in capsys.readouterr().err
    _review_all(sample_copy)
    scenes = load_dataset(sample_copy).scenes()
    fp1 = poses_fingerprint(read_poses(scenes[1].annotation_path))
    write_review(scenes[1].review_path, Review("rejected", {}, now_iso(), fp1))
    key = read_poses(scenes[2].annotation_path)[0].key
    fp = poses_fingerprint(read_poses(scenes[2].annotation_path))
    write_review(scenes[2].review_path, Review("accepted", {key: "rejected"}, now_iso(), fp))
    write_review(scenes[3].review_path, Review("accepted", {}, now_iso(), "stale-fingerprint"))
    assert main(["export", str(sample_copy), str(out), "--format", "bop", "--json", "--quiet"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["exported"] == 1
    assert s["left_out"] == {
        "rejected": 1,
        "has a rejected instance": 1,
        "stale review (annotation changed since)": 1,
    }
    assert main(["export", str(sample_copy), str(out), "--format", "bop"]) == 2  # not empty
    assert "not empty" in capsys.readouterr().err
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["export", str(sample_copy), str(blocker / "sub"), "--format", "bop"]) == 2
    assert "file" in capsys.readouterr().err


def _expected(root, cameras=None):
    """What the export of scene 0 must contain: its poses and their masks, computed directly
    with the pinhole (undistorted) cameras."""
    ds = load_dataset(root)
    scene = ds.scenes()[0]
    poses = read_poses(scene.annotation_path)
    rig = pinhole_rig(ds.rig)
    depth = undistort_depth(scene.read_depth(ds.rig), ds.rig.depth_camera)
    meshes = [ds.objects[p.object].mesh for p in poses]
    vis = scene_visibility(
        rig, meshes, [p.T for p in poses], depth=depth, cameras=cameras, masks=True
    )
    return ds, scene, poses, rig, vis


def test_bop_round_trip(sample_copy, tmp_path, capsys) -> None:
    _review_all(sample_copy)
    out = tmp_path / "bop"
    assert main(["export", str(sample_copy), str(out), "--format", "bop", "--quiet"]) == 0
    ds, scene, poses, rig, vis = _expected(sample_copy)
    for ci, cam in enumerate(rig.cameras):
        back = read_bop_scene(out, "000000", cam.name)
        for k, p in enumerate(poses):
            M = cam.cam_T_rig @ p.T
            assert np.allclose(back["R"][k], M[:3, :3], atol=1e-9) and np.allclose(
                back["t"][k], M[:3, 3], atol=1e-6
            )
            assert np.array_equal(back["masks"][k], vis[k].cameras[ci].mask_all)
            assert np.array_equal(back["masks_visib"][k], vis[k].cameras[ci].mask_visib)
    info = json.loads((out / "models" / "models_info.json").read_text())
    assert "symmetries_discrete" in info["2"] and "symmetries_continuous" in info["3"]
    # Our evaluator reads the export back as a BOP dataset: the exported poses score perfectly.
    lines = ["scene_id,im_id,obj_id,score,R,t,time"]
    for sid in ("000000",):
        gt = json.loads((out / "test" / sid / "scene_gt_left.json").read_text())["0"]
        for g in gt:
            lines.append(
                f"{int(sid)},0,{g['obj_id']},1,{' '.join(map(str, g['cam_R_m2c']))},{' '.join(map(str, g['cam_t_m2c']))},-1"
            )
    (tmp_path / "r.csv").write_text("\n".join(lines) + "\n")
    assert (
        main(
            [
                "evaluate",
                str(out),
                "--results",
                str(tmp_path / "r.csv"),
                "--json",
                str(tmp_path / "e.json"),
            ]
        )
        == 0
    )
    rep = json.loads((tmp_path / "e.json").read_text())["overall"]
    assert rep["FP"] == 0 and rep["TP"] > 0


def test_sileane_round_trip(sample_copy, tmp_path) -> None:
    _review_all(sample_copy)
    out = tmp_path / "sil"
    assert main(["export", str(sample_copy), str(out), "--format", "sileane", "--quiet"]) == 0
    ds, scene, poses, rig, vis = _expected(sample_copy, cameras=["left"])
    for name in ds.objects:
        back = read_sileane_scene(out / name, scene.id)
        mine = [(p, v) for p, v in zip(poses, vis) if p.object == name]
        assert len(back["R"]) == len(mine)
        for k, (p, v) in enumerate(mine):
            assert np.allclose(back["R"][k], p.R) and np.allclose(back["t"][k], p.t, atol=1e-6)
            assert back["occlusion_rate"][k] == pytest.approx(v.occlusion)
            assert np.array_equal(back["masks_visib"][k], v.cameras[0].mask_visib)
    assert (out / "cylinder" / "camera_params.txt").read_text().startswith("fu\t")
