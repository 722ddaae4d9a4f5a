"""Synthetic sequences (`synth --frames`): a moving rig's dataset that loads, whose truth
projected through every frame's rig pose lands on the markers OpenCV detects, the same
bytes with any number of workers, a smooth hand-held path, truthful motion blur."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from cli_calls import one_error_line
from test_synth import _digest  # the same bytes, counted the same way

from annotator.cli import main
from annotator.dataset import load_dataset, read_poses
from annotator.dataset.frames import poses_in_frame
from annotator.dataset.records import frames_from_json
from annotator.detection import MarkerDetector
from annotator.ingest.selection import sharpness
from annotator.synthesis.sequence import (
    DISTANCE_MM,
    TILT,
    PathKnots,
    draw_knots,
    motion_blur,
    rig_path,
)

SMALL = ["--scenes", "2", "--frames", "4", "--size", "320x256", "--supersample", "1"]
SMALL += ["--instances", "4-6", "--seed", "3", "--motion-blur", "0.5", "--quiet"]


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("seq") / "ds"
    assert main(["synth", str(out), *SMALL, "--workers", "2"]) == 0
    return out


@pytest.mark.slow
def test_the_sequences_load_as_a_moving_rig_dataset(small: Path) -> None:
    ds = load_dataset(small)
    assert ds.rig.moving and ds.rig.depth is not None and ds.rig.depth.background is None
    scenes = ds.scenes()
    assert [s.id for s in scenes] == ["000000", "000001"]
    for scene in scenes:
        frames = scene.frames()
        assert [f.name for f in frames] == ["000000", "000001", "000002", "000003"]
        assert not list(scene.path.glob("*.png"))  # a moving dataset's scene has no images
        for f in frames:
            for cam in ds.rig.cameras:
                assert scene.frames()[0].read_image(cam).shape[:2] == (256, 320)
            depth = f.read_depth(ds.rig)
            assert depth is not None and np.isfinite(depth).mean() > 0.5
        doc = json.loads(scene.gt_path.read_text())
        poses = read_poses(scene.gt_path)
        assert 4 <= len(poses) <= 6
        table = frames_from_json(doc["frames"], scene.gt_path)
        assert sorted(table) == [f.name for f in frames]
        assert np.array_equal(table["000000"].scene_T_rig, np.eye(4))
        moved = [np.linalg.norm(table[n].scene_T_rig[:3, 3]) for n in sorted(table)[1:]]
        assert min(moved) > 1.0  # the rig really moves
        blurred = [n for n in table if (table[n].motion_blur_px or 0) > 0]
        assert len(blurred) == 2  # --motion-blur 0.5 of 4 frames
        for n in blurred:
            assert (table[n].exposure_s or 0) > 0
        # The frames said to be blurred are the blurred ones (ingest's sharpness measure).
        left = ds.rig.cameras[0]
        sharp = {f.name: sharpness(f.read_image(left)) for f in frames}
        assert max(sharp[n] for n in blurred) < min(v for n, v in sharp.items() if n not in blurred)
        for p in poses:
            assert 0.0 <= p.extra["occlusion"]["rate"] <= 1.0
            assert set(p.extra["occlusion"]["per_camera"]) == {"left", "right"}


@pytest.mark.slow
def test_same_bytes_with_one_worker_and_the_summary(small: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "again"
    assert main(["synth", str(out), *SMALL, "--workers", "1", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["scenes"] == 2 and summary["frames"] == 8 and summary["failed"] == 0
    assert set(summary["seconds_per_frame"]) == {"rendering", "depth", "occlusion"}
    assert _digest(out) == _digest(small)


@pytest.mark.slow
def test_truth_through_each_frame_lands_on_the_detected_corners(tmp_path: Path) -> None:
    out = tmp_path / "big"
    args = ["synth", str(out), "--scenes", "1", "--frames", "3", "--size", "960x768"]
    args += ["--supersample", "1", "--no-depth", "--instances", "10-12", "--seed", "2"]
    assert main([*args, "--motion-blur", "0", "--workers", "2", "--quiet"]) == 0
    ds = load_dataset(out)
    scene = ds.scenes()[0]
    poses = {p.key: p for p in read_poses(scene.gt_path)}
    table = frames_from_json(json.loads(scene.gt_path.read_text())["frames"], scene.gt_path)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_1000)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    opencv = cv2.aruco.ArucoDetector(dictionary, params, cv2.aruco.RefineParameters())
    ours = MarkerDetector(ds.dictionary)
    for frame in scene.frames():
        rig_T = {
            p.key: p.T for p in poses_in_frame(list(poses.values()), table[frame.name].scene_T_rig)
        }
        errors: dict[str, list[float]] = {"opencv": [], "ours": []}
        for cam in ds.rig.cameras:
            img = frame.read_image(cam)
            corners, ids, _ = opencv.detectMarkers(img)
            found = [("opencv", int(i), c.reshape(4, 2)) for c, i in zip(corners, _ids(ids))]
            found += [("ours", d.id, d.corners) for d in ours.detect(img)]
            for who, marker, seen in found:
                ref = ds.marker_table.get(marker)
                if ref is None or f"{ref.object}/{ref.instance}" not in rig_T:
                    continue  # a false detection: not a test of the renderer
                X = ds.objects[ref.object].markers.corners[ref.site]
                T = cam.cam_T_rig @ rig_T[f"{ref.object}/{ref.instance}"]
                uv = cam.project(X @ T[:3, :3].T + T[:3, 3])
                errors[who] += list(np.linalg.norm(seen - uv, axis=1))
        for who, limit in (("opencv", 0.8), ("ours", 0.35)):
            e = errors[who]
            assert len(e) >= 100, (frame.name, who, len(e))
            assert np.median(e) < limit and np.percentile(e, 90) < 1.5, (frame.name, who)
    # Different frames see the parts from different places: the truth is not one camera's.
    first = poses_in_frame(list(poses.values()), table["000002"].scene_T_rig)[0].t
    assert np.linalg.norm(first - next(iter(poses.values())).t) > 5.0


def _ids(ids: np.ndarray | None) -> list[int]:
    return [] if ids is None else [int(i) for i in np.asarray(ids).reshape(-1)]


def test_the_path_is_smooth_and_stays_over_the_bin() -> None:
    rng = np.random.default_rng(4)
    knots = draw_knots(60, rng)
    t = np.linspace(0.0, 59 * 0.25, 2000)
    T = rig_path(knots, t)
    eyes = T[:, :3, 3]
    dt = t[1] - t[0]
    speed = np.linalg.norm(np.diff(eyes, axis=0), axis=1) / dt
    accel = np.abs(np.diff(speed)) / dt
    assert speed.max() < 800.0 and 50.0 < np.median(speed) < 300.0  # mm/s: a hand
    assert np.percentile(accel, 99) < 5000.0  # no jumps in velocity
    for k in range(len(T)):
        assert np.allclose(T[k, :3, :3] @ T[k, :3, :3].T, np.eye(3), atol=1e-9)
    # Every eye is within the distance range of its target, the sight tilted within range.
    q = np.array(knots.values)
    assert DISTANCE_MM[0] - 1 <= np.linalg.norm(eyes - [0, 0, 30], axis=1).min()
    axis = T[:, :3, 2]
    tilt = np.arccos(np.clip(-axis[:, 2], -1, 1))
    assert tilt.max() < TILT[1] + np.radians(8.0)
    # A pure function: the same knots, the same poses.
    assert np.array_equal(rig_path(PathKnots(knots.times, q), t), T)


def test_motion_blur_spreads_a_dot_along_its_streak() -> None:
    img = np.zeros((40, 60), np.float32)
    img[20, 30] = 1.0
    flow = np.zeros((40, 60, 2), np.float32)
    flow[..., 0] = 8.0  # 8 px to the right over the exposure
    out = motion_blur(img, flow)
    row = out[20]
    assert abs(out.sum() - 1.0) < 1e-4  # nothing lost
    lit = np.flatnonzero(row > 1e-3)
    assert 7 <= lit.max() - lit.min() + 1 <= 10 and out[19].max() < 1e-6
    assert abs((row * np.arange(60)).sum() / row.sum() - 30.0) < 0.2  # centred on the dot


def test_frames_with_calibration_or_twin_is_one_line(tmp_path: Path, capsys, sample) -> None:
    line = one_error_line(["synth", str(tmp_path / "x"), "--calibration", "--frames", "3"], capsys)
    assert "--frames does not apply to --calibration" in line
    line = one_error_line(
        ["synth", str(tmp_path / "x"), "--twin", str(sample), "--frames", "3"], capsys
    )
    assert "--frames does not apply to --twin" in line
    line = one_error_line(["synth", str(tmp_path / "x"), "--motion-blur", "0.5"], capsys)
    assert "--motion-blur applies to sequences only" in line
    assert not (tmp_path / "x").exists()


def test_one_camera_like_an_rgbd_sensor(tmp_path: Path) -> None:
    out = tmp_path / "one"
    args = ["synth", str(out), "--scenes", "1", "--frames", "2", "--cameras", "1"]
    args += ["--size", "320x256", "--supersample", "1", "--instances", "4-5", "--quiet"]
    assert main([*args, "--workers", "1"]) == 0
    ds = load_dataset(out)
    assert [c.name for c in ds.rig.cameras] == ["left"] and ds.rig.moving
    for frame in ds.scenes()[0].frames():
        assert sorted(p.name for p in frame.path.iterdir()) == [
            "depth.png",
            "depth_ideal.png",
            "left.png",
        ]
        depth = frame.read_depth(ds.rig)
        assert depth is not None and np.isfinite(depth).mean() > 0.5  # the stereo pair's
    for p in read_poses(ds.scenes()[0].gt_path):
        assert set(p.extra["occlusion"]["per_camera"]) == {"left"}
