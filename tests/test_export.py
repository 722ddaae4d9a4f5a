"""Occlusion exactness, export selection, and BOP / Siléane round trips."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import trimesh
import yaml

from annotator.cli import main
from annotator.dataset import load_dataset, read_poses
from annotator.dataset.model import DepthSpec, Rig
from annotator.dataset.review import Review, now_iso, poses_fingerprint, write_review
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


def _export(root, out, fmt, *extra) -> None:
    _review_all(root)
    assert (
        main(["export", str(root), str(out), "--format", fmt, "--poses", "gt", "--quiet", *extra])
        == 0
    )


def _remapped(root, scene_id, camera="left"):
    """The camera's image undistorted by the test itself: OpenCV's own maps from the raw K and
    dist of dataset.yaml, bilinear, as a pinhole camera with the same K."""
    raw = yaml.safe_load((root / "dataset.yaml").read_text())
    cam = next(c for c in raw["rig"]["cameras"] if c["name"] == camera)
    K = np.array(cam["K"], float).reshape(3, 3)
    w, h = cam["size"]
    mx, my = cv2.initUndistortRectifyMap(K, np.array(cam["dist"]), None, K, (w, h), cv2.CV_32FC1)
    img = cv2.imread(str(root / "scenes" / scene_id / f"{camera}.png"), cv2.IMREAD_UNCHANGED)
    return cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT), K


def _gt(root, scene_id):
    return json.loads((root / "scenes" / scene_id / "gt.json").read_text())["instances"]


@pytest.mark.slow
def test_bop_export_against_independent_truth(sample_copy, tmp_path, capsys) -> None:
    out = tmp_path / "bop"
    _export(sample_copy, out, "bop")
    ids = json.loads((out / "test" / "scene_ids.json").read_text())
    objects = yaml.safe_load((sample_copy / "dataset.yaml").read_text())["objects"]
    raw = yaml.safe_load((sample_copy / "dataset.yaml").read_text())["rig"]["cameras"]
    right_T = np.array(raw[1]["rig_T_cam"], float).reshape(4, 4)
    lines, of_interest = ["scene_id,im_id,obj_id,score,R,t,time"], 0
    for bop_id, sid in ids.items():
        d = out / "test" / bop_id
        truth = _gt(sample_copy, sid)
        for camera, cam_T_rig in (("left", np.eye(4)), ("right", np.linalg.inv(right_T))):
            gt = json.loads((d / f"scene_gt_{camera}.json").read_text())
            assert list(gt) == ["0"] and len(gt["0"]) == len(truth)
            for g, t in zip(gt["0"], truth):
                assert set(g) == {"cam_R_m2c", "cam_t_m2c", "obj_id"}
                assert g["obj_id"] == objects.index(t["object"]) + 1
                T = np.eye(4)
                T[:3, :3] = np.reshape(t["cam_R_m2c"], (3, 3))
                T[:3, 3] = t["cam_t_m2c"]
                T = cam_T_rig @ T  # mm, in that camera's frame
                assert np.allclose(np.reshape(g["cam_R_m2c"], (3, 3)), T[:3, :3], atol=1e-9)
                assert np.allclose(g["cam_t_m2c"], T[:3, 3], atol=1e-6)
            cam = json.loads((d / f"scene_camera_{camera}.json").read_text())["0"]
            assert len(cam["cam_K"]) == 9 and len(cam["cam_R_w2c"]) == 9
        img, K = _remapped(sample_copy, sid)
        assert np.array_equal(
            cv2.imread(str(d / "gray_left" / "000000.png"), cv2.IMREAD_UNCHANGED), img
        )
        cam = json.loads((d / "scene_camera_left.json").read_text())["0"]
        assert np.allclose(np.reshape(cam["cam_K"], (3, 3)), K) and cam["depth_scale"] > 0
        depth = cv2.imread(str(d / "depth_left" / "000000.png"), cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16
        infos = json.loads((d / "scene_gt_info_left.json").read_text())["0"]
        assert all(0 <= i["visib_fract"] <= 1 and i["px_count_all"] > 0 for i in infos)
        of_interest += sum(i["visib_fract"] >= 0.5 for i in infos)
        for g in json.loads((d / "scene_gt_left.json").read_text())["0"]:
            R, t = " ".join(map(str, g["cam_R_m2c"])), " ".join(map(str, g["cam_t_m2c"]))
            lines.append(f"{int(bop_id)},0,{g['obj_id']},1,{R},{t},-1")
    info = json.loads((out / "models" / "models_info.json").read_text())
    assert "symmetries_discrete" in info["2"] and "symmetries_continuous" in info["3"]
    cam_file = json.loads((out / "camera_left.json").read_text())
    assert set(cam_file) == {"width", "height", "fx", "fy", "cx", "cy", "depth_scale"}
    # The ground truth scored against itself finds every instance to find.
    (tmp_path / "r.csv").write_text("\n".join(lines) + "\n")
    args = [
        "evaluate",
        str(out),
        "--results",
        str(tmp_path / "r.csv"),
        "--json",
        str(tmp_path / "e.json"),
    ]
    assert main(args) == 0
    rep = json.loads((tmp_path / "e.json").read_text())["overall"]
    assert (rep["TP"], rep["FP"], rep["FN"]) == (of_interest, 0, 0) and of_interest > 0


@pytest.mark.slow
def test_sileane_export_against_independent_truth(sample_copy, tmp_path) -> None:
    out = tmp_path / "sil"
    _export(sample_copy, out, "sileane")
    of_interest = 0
    res = tmp_path / "res"
    for name in yaml.safe_load((sample_copy / "dataset.yaml").read_text())["objects"]:
        folder = out / name
        # Built-in parts are centred on their surface centroid, their axis on z: the
        # canonical frame of the export is their own, so poses are unchanged (in metres).
        mesh = trimesh.load(folder / "mesh.ply", process=False)
        assert np.abs(mesh.centroid).max() < 1e-6 and mesh.extents.max() < 1.0  # metres
        utils = json.loads((folder / "poseutils.json").read_text())
        assert utils["type"] in ("AffinePoseUtils", "RevolutionPoseUtils")
        assert 0 < utils["distance_threshold"] < 0.1
        for f in sorted((folder / "gt").glob("*.json")):
            sid = f.stem
            truth = [t for t in _gt(sample_copy, sid) if t["object"] == name]
            got = json.loads(f.read_text())
            assert len(got) == len(truth)
            for g, t in zip(got, truth):
                assert {"R", "t", "occlusion_rate", "segmentation_id"} <= set(g)
                assert np.allclose(g["R"], np.reshape(t["cam_R_m2c"], (3, 3)), atol=1e-9)
                assert np.allclose(np.array(g["t"]) * 1000.0, t["cam_t_m2c"], atol=1e-6)
            seg = cv2.imread(str(folder / "segmentation" / f"{sid}.PNG"), cv2.IMREAD_UNCHANGED)
            for g in got:
                assert (seg == g["segmentation_id"]).any() == (g["occlusion_rate"] < 1.0)
            img, _ = _remapped(sample_copy, sid)
            assert np.array_equal(
                cv2.imread(str(folder / "rgb" / f"{sid}.PNG"), cv2.IMREAD_UNCHANGED), img
            )
            of_interest += sum(g["occlusion_rate"] <= 0.5 for g in got)
            (res / name).mkdir(parents=True, exist_ok=True)
            (res / name / f.name).write_text(
                json.dumps([{"R": g["R"], "t": g["t"], "score": 1.0} for g in got])
            )
        assert (folder / "camera_params.txt").read_text().startswith("fu\t")
    # The ground truth scored against itself (results in metres, like it) finds every
    # instance to find.
    tp = 0
    for name in yaml.safe_load((sample_copy / "dataset.yaml").read_text())["objects"]:
        rep_path = tmp_path / f"{name}.json"
        assert (
            main(
                ["evaluate", str(out / name), "--results", str(res / name), "--json", str(rep_path)]
            )
            == 0
        )
        rep = json.loads(rep_path.read_text())["overall"]
        assert rep["FP"] == 0 and rep["FN"] == 0
        tp += rep["TP"]
    assert tp == of_interest > 0
