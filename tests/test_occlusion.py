"""Occlusion masks follow OpenCV's pixel convention, lens distortion included.

(Exact occlusion fractions and the depth test are checked in test_export.py.)
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh

from annotator.dataset import load_dataset, read_poses
from annotator.dataset.model import Rig
from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.geometry.transforms import make_transform
from annotator.occlusion import scene_visibility

K = np.array([[700.0, 0, 300.3], [0, 710.0, 231.7], [0, 0, 1]])
DIST = np.array([-0.12, 0.05, 0.001, -0.002, 0.0])


def _plate(w: float, h: float) -> Mesh:
    b = trimesh.creation.box((w, h, 1e-3))
    return Mesh(np.asarray(b.vertices), np.asarray(b.faces, dtype=np.int32))


def test_mask_matches_opencv_undistortion_and_projected_corners() -> None:
    cam = Camera("c", 640, 480, K, DIST)
    x0, x1, y0, y1, z = -90.0, 60.0, -40.0, 70.0, 500.0
    pose = make_transform(np.eye(3), [(x0 + x1) / 2, (y0 + y1) / 2, z])
    (vis,) = scene_visibility(Rig((cam,)), [_plate(x1 - x0, y1 - y0)], [pose], masks=True)
    mask = vis.cameras[0].mask_all
    assert mask is not None and mask.shape == (480, 640)
    # Independent of the renderer: undistort every pixel centre with OpenCV and test it against
    # the plate's extent in normalised coordinates (pixels within 0.02 px of an edge ignored).
    v, u = np.mgrid[0:480, 0:640].astype(np.float64)
    uv = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2)
    n = cv2.undistortPoints(uv, K, DIST).reshape(480, 640, 2)
    margin = 0.02 / 700.0
    inside = (
        (n[..., 0] > x0 / z + margin)
        & (n[..., 0] < x1 / z - margin)
        & (n[..., 1] > y0 / z + margin)
        & (n[..., 1] < y1 / z - margin)
    )
    outside = (
        (n[..., 0] < x0 / z - margin)
        | (n[..., 0] > x1 / z + margin)
        | (n[..., 1] < y0 / z - margin)
        | (n[..., 1] > y1 / z + margin)
    )
    assert mask[inside].all()
    assert not mask[outside].any()
    assert inside.sum() > 20000
    # The mask's box is the box of the corners projected by cv2.projectPoints (the plate's
    # edges bulge with barrel distortion, so compare with the edges' dense projection).
    t = np.linspace(0, 1, 400)
    edges = np.concatenate(
        [
            np.stack([x0 + (x1 - x0) * t, np.full_like(t, y0), np.full_like(t, z)], 1),
            np.stack([x0 + (x1 - x0) * t, np.full_like(t, y1), np.full_like(t, z)], 1),
            np.stack([np.full_like(t, x0), y0 + (y1 - y0) * t, np.full_like(t, z)], 1),
            np.stack([np.full_like(t, x1), y0 + (y1 - y0) * t, np.full_like(t, z)], 1),
        ]
    )
    proj, _ = cv2.projectPoints(edges, np.zeros(3), np.zeros(3), K, DIST)
    proj = proj.reshape(-1, 2)
    bx, by, bw, bh = vis.cameras[0].bbox_all
    assert bx == int(np.ceil(proj[:, 0].min())) and by == int(np.ceil(proj[:, 1].min()))
    assert bx + bw - 1 == int(np.floor(proj[:, 0].max()))
    assert by + bh - 1 == int(np.floor(proj[:, 1].max()))
    assert vis.cameras[0].px_all == int(mask.sum()) and vis.occlusion == 0.0


def test_subsampled_visibility_estimates_the_exact_rates() -> None:
    # Annotation casts every 2nd pixel of every 2nd row; its rates must stay close to the exact
    # ones that exports use (sample scene: 20 parts in a bin, depth map included).
    ds = load_dataset("sample_scenes")
    scene = ds.scenes()[0]
    poses = read_poses(scene.gt_path)
    meshes = [ds.objects[p.object].mesh for p in poses]
    Ts = [make_transform(p.R, p.t) for p in poses]
    depth = scene.read_depth(ds.rig)
    exact = scene_visibility(ds.rig, meshes, Ts, depth=depth)
    rough = scene_visibility(ds.rig, meshes, Ts, depth=depth, step=2)
    compared = 0
    for e, r in zip(exact, rough):
        for ce, cr in zip(e.cameras, r.cameras):
            if ce.px_all < 500:
                continue
            compared += 1
            assert abs(ce.occlusion - cr.occlusion) < 0.01
            assert abs(cr.px_all / ce.px_all - 1) < 0.02
            if ce.depth_agreement is not None and ce.depth_pixels > 500:
                assert abs(ce.depth_agreement - cr.depth_agreement) < 0.01
    assert compared >= 10
    with pytest.raises(ValueError):
        scene_visibility(ds.rig, meshes, Ts, masks=True, step=2)


def test_occlusion_command_writes_exact_rates_and_resumes(sample_copy, capsys) -> None:
    import json

    from annotator.cli import main

    assert main(["occlusion", str(sample_copy), "--poses", "gt", "--workers", "2", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["done"] == 4
    ds = load_dataset(sample_copy)
    scene = ds.scenes()[1]
    poses = read_poses(scene.gt_path)
    exact = scene_visibility(
        ds.rig,
        [ds.objects[p.object].mesh for p in poses],
        [make_transform(p.R, p.t) for p in poses],
        depth=scene.read_depth(ds.rig),
    )
    written = json.loads((scene.path / "visibility.json").read_text())["instances"]
    assert [w["occlusion"] for w in written] == [round(v.occlusion, 5) for v in exact]
    assert main(["occlusion", str(sample_copy), "--poses", "gt", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["skipped"] == 4
