"""Sequences of one moving rig (issue 34): every frame's rig pose and every instance's pose
from one solve, against the exact truth of rendered sequences; the bundle adjustment on its
own; what the solve refuses (a frame with no known marker, one it cannot fix, a part that
moved, a misread marker); everything downstream per frame (occlusion, BOP export with one
image per frame, evaluate, check, the review state)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from cli_calls import run_cli

from annotator.annotation.sequence import FrameReading, solve_sequence
from annotator.cli import main
from annotator.dataset import load_dataset, read_poses
from annotator.dataset.flags import Flag, FrameFlag
from annotator.dataset.frames import read_frames
from annotator.dataset.records import SceneAnnotation, frames_from_json
from annotator.detection.aruco import Detection, ImageReading
from annotator.geometry.camera import Camera
from annotator.geometry.lie import rotvec_to_matrix
from annotator.geometry.transforms import invert, make_transform
from annotator.pnp.bundle import BundleObservations, bundle_adjust
from devkit.sequence_truth import sequence_errors

pytestmark = pytest.mark.slow

SEQUENCE = ["--scenes", "1", "--frames", "8", "--size", "640x512", "--supersample", "1"]
SEQUENCE += ["--instances", "5-7", "--seed", "5", "--motion-blur", "0.25", "--quiet"]


@pytest.fixture(scope="module")
def annotated(tmp_path_factory) -> Path:
    """A rendered sequence (8 frames, two cameras and depth), annotated."""
    out = tmp_path_factory.mktemp("sequence") / "ds"
    assert main(["synth", str(out), *SEQUENCE, "--workers", "2"]) == 0
    assert main(["annotate", str(out), "--workers", "2", "--quiet"]) == 0
    return out


@pytest.fixture()
def copy(annotated: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "ds"
    shutil.copytree(annotated, dst)
    return dst


def test_a_rendered_sequence_is_annotated_frame_by_frame(annotated: Path) -> None:
    e = sequence_errors(annotated)
    pos, turn, errors = e.position_mm, e.turn_deg, e.error_pct
    ann = json.loads((annotated / "scenes" / "000000" / "annotation.json").read_text())
    gt = json.loads((annotated / "scenes" / "000000" / "gt.json").read_text())
    assert ann["scene_frame"] == "000000"
    assert sorted(ann["frames"]) == sorted(gt["frames"])
    assert sum(f["scene_T_rig"] is not None for f in ann["frames"].values()) >= 7
    # Small, aliased images (the benchmark renders 1280x720 supersampled): measured here
    # medians 0.36 mm, 0.04 degrees and 0.24 % of D, the worst part 1.9 % of D (its
    # uncertainty 1.4 %: two markers).
    assert np.median(pos) < 0.6 and np.median(turn) < 0.1
    assert np.median(errors) < 0.5 and max(errors) < 5.0
    assert e.extra == 0 and len(errors) >= len(gt["instances"]) - 1
    assert e.posed_visible == e.visible and e.gross_unflagged == 0
    # Honest uncertainties: as each frame sees the part, its markers' own errors counted.
    assert np.mean(np.array(errors) <= 3 * np.array(e.uncertainty_pct)) >= 0.85
    for name, entry in ann["frames"].items():
        if entry["scene_T_rig"] is None:  # said why, never guessed
            assert entry["flags"] in (["no_known_markers"], ["unconnected"], ["outlier"])
            assert entry["flags"] != ["outlier"] or entry["reason"]
            continue
        assert entry["reprojection_px"] < 1.5 and entry["markers_used"] > 0
        assert 0 < len(entry["instances"]) <= len(ann["instances"])
        if "weak_geometry" not in entry["flags"]:  # else posed on few corners, and says so
            assert entry["uncertainty_mm"] < 2 and entry["uncertainty_deg"] < 0.3
        else:
            assert entry["markers_used"] < 25 and "weak geometry" in entry["reason"]
        assert (entry["uncertainty_mm"] == 0) == (name == ann["scene_frame"])
        for seen in entry["instances"].values():
            assert set(seen["occlusion"]) == {"left", "right"}
    for inst in ann["instances"]:
        assert inst["frames_seen"] >= 1 and inst["uncertainty_mm"] > 0


def test_the_bundle_adjustment_finds_the_poses_and_says_how_well() -> None:
    rng = np.random.default_rng(0)
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    cams = [
        Camera("a", 640, 480, K, np.array([-0.05, 0.02, 0, 0, 0])),
        Camera("b", 640, 480, K, np.zeros(5), make_transform(np.eye(3), [100.0, 0, 0])),
    ]
    frames = np.stack(
        [
            make_transform(rotvec_to_matrix(rng.normal(0, 0.1, 3)), rng.normal(0, 30, 3))
            for _ in range(6)
        ]
    )
    frames[0] = np.eye(4)
    models = np.stack(
        [
            make_transform(rotvec_to_matrix(rng.normal(0, 1, 3)), np.r_[rng.normal(0, 40, 2), 500])
            for _ in range(4)
        ]
    )
    square = np.array([[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0.0]])
    rows = []
    for f in range(6):
        for i in range(4):
            for _ in range(3):
                X = square + np.r_[rng.normal(0, 15, 2), 0]
                for c, cam in enumerate(cams):
                    M = cam.cam_T_rig @ invert(frames[f]) @ models[i]
                    pc = X @ M[:3, :3].T + M[:3, 3]
                    x = cam.project(pc) + rng.normal(0, 0.3, (4, 2))
                    rows.append((f, i, c, X, x, pc[:, 2].mean() if c == 0 else np.nan))
    obs = BundleObservations(
        *(np.array([r[k] for r in rows]) for k in range(3)),
        np.stack([r[3] for r in rows]),
        np.stack([r[4] for r in rows]),
        np.array([r[5] for r in rows]),
    )
    start_f = np.stack(
        [
            make_transform(rotvec_to_matrix(rng.normal(0, 0.02, 3)), rng.normal(0, 3, 3)) @ T
            for T in frames
        ]
    )
    start_f[0] = np.eye(4)
    start_m = np.stack(
        [
            make_transform(rotvec_to_matrix(rng.normal(0, 0.02, 3)), rng.normal(0, 3, 3)) @ T
            for T in models
        ]
    )
    res = bundle_adjust(cams, obs, start_f, start_m, fixed_frame=0, depth_camera=0)
    assert np.allclose(res.scene_T_rig[0], np.eye(4))
    err = np.linalg.norm(res.scene_T_rig[:, :3, 3] - frames[:, :3, 3], axis=1)[1:]
    sigma = np.sqrt(np.trace(res.frame_covariance[1:, 3:, 3:], axis1=1, axis2=2))
    assert 0.25 < float(np.sqrt(np.mean((err / sigma) ** 2))) < 2.5  # honest, not flattering
    assert 0.2 < res.sigma_px < 0.4 and np.median(res.residual_px) < 0.6
    # A frame that sees only an instance no other frame sees: their common motion is free.
    lone = BundleObservations(
        np.r_[obs.frame, 6, 6],
        np.r_[obs.instance, 4, 4],
        np.r_[obs.camera, 0, 1],
        np.concatenate([obs.model_corners, obs.model_corners[:2]]),
        np.concatenate([obs.image_corners, obs.image_corners[:2]]),
        np.r_[obs.depth_mm, np.nan, np.nan],
    )
    res = bundle_adjust(
        cams,
        lone,
        np.concatenate([start_f, frames[:1]]),
        np.concatenate([start_m, models[:1]]),
        fixed_frame=0,
    )
    assert np.isinf(res.frame_covariance[6]).all() and np.isfinite(res.frame_covariance[3]).all()


def _fake_readings(ds, truth_frames, truth_poses, *, moved: str | None = None, misread=False):
    """What the cameras would read in each frame at these true poses (every site facing the
    camera, within the image, 0.2 px of noise); ``moved``: that instance 25 mm away from the
    fifth frame on; ``misread``: one frame reads one marker with another copy's id."""
    rng = np.random.default_rng(1)
    readings = []
    for k, (name, T) in enumerate(sorted(truth_frames.items())):
        per_cam = []
        for cam in ds.rig.cameras:
            found = []
            for p in truth_poses:
                pose = p.T.copy()
                if p.key == moved and k >= 4:
                    pose[:3, 3] += [25.0, 0, 0]
                obj = ds.objects[p.object]
                M = cam.cam_T_rig @ invert(T) @ pose
                for site, mid in zip(
                    obj.site_corners(p.instance), obj.instance(p.instance).marker_ids
                ):
                    pc = site @ M[:3, :3].T + M[:3, 3]
                    normal = np.cross(pc[1] - pc[0], pc[3] - pc[0])
                    if normal @ pc.mean(0) >= 0:  # seen from behind
                        continue
                    uv = cam.project(pc)
                    if (
                        np.isnan(uv).any()
                        or (uv < 5).any()
                        or (uv[:, 0] > cam.width - 5).any()
                        or (uv[:, 1] > cam.height - 5).any()
                    ):
                        continue
                    found.append(Detection(int(mid), uv + rng.normal(0, 0.2, uv.shape)))
            if misread and k == 2 and found:
                others = [m for o in ds.objects.values() for i in o.instances for m in i.marker_ids]
                used = {d.id for d in found}
                wrong = next(m for m in others if m not in used)
                found[0] = Detection(int(wrong), found[0].corners)
            per_cam.append(
                ImageReading(
                    found, np.zeros((0, 4, 2)), np.zeros((0, 1, 1), bool), np.zeros(0), None
                )
            )
        readings.append(FrameReading(name, per_cam, np.zeros(0), {}))
    return readings


def test_a_part_that_moved_halfway_is_flagged_and_a_misread_marker_left_out(
    annotated: Path,
) -> None:
    ds = load_dataset(annotated)
    scene = ds.scenes()[0]
    truth = {n: f.scene_T_rig for n, f in read_frames(scene.gt_path).items()}
    poses = read_poses(scene.gt_path)
    moved = poses[0].key
    sol = solve_sequence(ds, _fake_readings(ds, truth, poses, moved=moved, misread=True))
    flags = {r.key: r.flags for r in sol.instances}
    assert Flag.MOVED in flags[moved]
    assert all(Flag.MOVED not in f for k, f in flags.items() if k != moved)
    assert any("moved" in w.message for w in sol.warnings)
    # The frames are placed from the parts that stayed: all of them, where they were.
    for name, T in truth.items():
        got = sol.frames[name].scene_T_rig
        assert got is not None and np.abs(got[:3, 3] - T[:3, 3]).max() < 0.5
    # The misread id belongs to a copy not in the scene: never posed from one reading.
    assert {r.key for r in sol.instances} <= {p.key for p in poses}


def test_a_frame_without_known_markers_is_flagged_not_guessed(annotated: Path) -> None:
    ds = load_dataset(annotated)
    scene = ds.scenes()[0]
    truth = {n: f.scene_T_rig for n, f in read_frames(scene.gt_path).items()}
    readings = _fake_readings(ds, truth, read_poses(scene.gt_path))
    empty = ImageReading([], np.zeros((0, 4, 2)), np.zeros((0, 1, 1), bool), np.zeros(0), None)
    readings[3] = FrameReading(readings[3].frame, [empty, empty], np.zeros(0), {})
    sol = solve_sequence(ds, readings)
    frame = sol.frames[readings[3].frame]
    assert frame.scene_T_rig is None and frame.flags == [FrameFlag.NO_KNOWN_MARKERS]
    assert sum(f.scene_T_rig is not None for f in sol.frames.values()) == len(readings) - 1


def test_a_sequence_exports_one_bop_image_per_frame(copy: Path, tmp_path: Path) -> None:
    scene = copy / "scenes" / "000000"
    review = {"status": "accepted", "instances": {}, "frames": {"000002": "rejected"}}
    ann = SceneAnnotation.read(scene / "annotation.json")
    from annotator.dataset.review import poses_fingerprint

    review["annotation_fingerprint"] = poses_fingerprint(ann.instances)
    (scene / "review.json").write_text(json.dumps(review))
    out = tmp_path / "bop"
    assert main(["export", str(copy), str(out), "--format", "bop", "--quiet"]) == 0
    cams = json.loads((out / "test" / "000000" / "scene_camera_left.json").read_text())
    gts = json.loads((out / "test" / "000000" / "scene_gt_left.json").read_text())
    frames = read_frames(scene / "annotation.json")
    posed = [n for n, f in sorted(frames.items()) if f.scene_T_rig is not None and n != "000002"]
    names = sorted(frames)
    assert sorted(cams, key=int) == [str(names.index(n)) for n in posed]  # 000002 left out
    scene_poses = {p.key: p for p in read_poses(scene / "annotation.json")}
    for im, rec in cams.items():
        w2c = make_transform(np.reshape(rec["cam_R_w2c"], (3, 3)), rec["cam_t_w2c"])
        assert np.allclose(w2c, invert(frames[names[int(im)]].scene_T_rig), atol=1e-6)
        for gt in gts[im]:  # each image's pose is the scene pose seen from that frame
            pose = make_transform(np.reshape(gt["cam_R_m2c"], (3, 3)), gt["cam_t_m2c"])
            world = invert(w2c) @ pose
            assert min(np.abs(world - p.T).max() for p in scene_poses.values()) < 1e-6
        assert (out / "test" / "000000" / "gray_left" / f"{int(im):06d}.png").is_file()
    targets = json.loads((out / "test_targets_bop24.json").read_text())
    assert sorted(t["im_id"] for t in targets) == sorted(int(i) for i in cams)


def test_evaluate_and_occlusion_work_per_frame(copy: Path, capsys) -> None:
    assert main(["evaluate", str(copy), "--json", str(copy.parent / "e.json")]) == 0
    report = json.loads((copy.parent / "e.json").read_text())
    frames = read_frames(copy / "scenes" / "000000" / "gt.json")
    assert report["overall"]["scenes"] >= len(frames) - 1  # one evaluation scene per frame
    assert "median error" in capsys.readouterr().out
    assert main(["occlusion", str(copy), "--poses", "gt", "--quiet"]) == 0
    vis = json.loads((copy / "scenes" / "000000" / "visibility.json").read_text())
    assert sorted(vis["frames"]) == sorted(frames)
    entry = next(iter(vis["frames"].values()))["instances"][0]
    assert set(entry["cameras"]) == {"left", "right"} and 0 <= entry["occlusion"] <= 1


def test_bad_frames_get_one_line_and_keep_the_old_annotation(copy: Path, capsys) -> None:
    scene = copy / "scenes" / "000000"
    before = (scene / "annotation.json").read_bytes()
    (scene / "frames" / "000003" / "right.png").unlink()
    assert main(["check", str(copy)]) == 1
    assert "frames/000003/right.png" in capsys.readouterr().out
    code, _, err = run_cli(["annotate", str(copy), "--force", "--quiet"], capsys)
    failures = [line for line in err.splitlines() if line.startswith("failed:")]
    assert code == 1 and len(failures) == 1, err
    assert "frame 000003" in failures[0] and "right.png" in failures[0]
    assert (scene / "annotation.json").read_bytes() == before  # nothing lost
    empty = copy / "scenes" / "000001"
    empty.mkdir()
    assert main(["check", str(copy)]) == 1
    assert "frames/<frame>/: none found" in capsys.readouterr().out


def test_the_review_state_shows_frames_in_the_scene_frame_and_rejects_one(copy: Path) -> None:
    from annotator.review import ReviewState
    from viewer.drawing.overlays import prepare

    state = ReviewState(copy)
    sid = state.ids[0]
    info = state.info(sid)
    assert len(info.shown) == 3 and info.view.endswith(",".join(info.shown))
    ds = state.dataset_of(sid)
    assert [c.name for c in ds.rig.cameras][:2] == [
        f"{info.shown[0]}:left",
        f"{info.shown[0]}:right",
    ]
    prep = prepare(ds, state.scene(sid), list(info.poses))
    assert not prep.messages and len(prep.layers) == 6 and prep.depth is not None
    # Each frame's silhouettes are where that frame's cameras see the parts.
    assert all((layer.instance >= 0).sum() > 500 for layer in prep.layers)
    first = info.shown[0]
    assert state.toggle_frame(sid, first)
    doc = json.loads((copy / "scenes" / sid / "review.json").read_text())
    assert doc["frames"] == {first: "rejected"} and doc["status"] == "pending"
    assert state.info(sid, 1).shown != info.shown
    assert not state.toggle_frame(sid, first)
    assert "frames" not in json.loads((copy / "scenes" / sid / "review.json").read_text())
    frames = frames_from_json(
        json.loads((copy / "scenes" / sid / "annotation.json").read_text())["frames"], copy
    )
    assert set(frames) == {f.name for f in load_dataset(copy).scenes()[0].frames()}


def test_sites_are_measured_from_one_sequence(tmp_path: Path, capsys) -> None:
    """Markers glued by hand (0.7 mm, 2 degrees): ``sites`` measures them from the frames of
    one sequence, and the poses annotated again are better."""
    root = tmp_path / "glued"
    args = [*SEQUENCE, "--glue", "0.7,2", "--seed", "31", "--frames", "6"]
    assert main(["synth", str(root), *args, "--workers", "2"]) == 0
    capsys.readouterr()
    assert main(["annotate", str(root), "--workers", "2", "--quiet"]) == 0
    said = capsys.readouterr().err  # the user is told, not only the file
    assert "scene 000000: " in said and "`annotator sites`" in said
    before = sequence_errors(root)
    # The first pass poses the frames, moves no part, and says what will tighten the poses.
    ann = json.loads((root / "scenes" / "000000" / "annotation.json").read_text())
    truth = json.loads((root / "scenes" / "000000" / "gt.json").read_text())["frames"]
    sharp = [n for n, f in truth.items() if not f.get("motion_blur_px")]
    posed = [n for n in sharp if ann["frames"][n]["scene_T_rig"] is not None]
    assert len(posed) >= 0.85 * len(sharp)
    assert all("moved" not in i["flags"] for i in ann["instances"])
    assert any("`annotator sites`" in w["message"] for w in ann["warnings"])
    capsys.readouterr()
    assert main(["sites", str(root), "--yes", "--json", "--workers", "2", "--quiet"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["written"] and report["instances"], report
    truth = json.loads((root / "glued_sites.json").read_text())
    ds = load_dataset(root)
    layout_err, measured_err = [], []
    for obj in ds.objects.values():
        for inst in obj.instances:
            if inst.sites is None:
                continue
            true = np.asarray(truth[obj.name][inst.name])
            seen = np.abs(inst.sites - obj.markers.corners).max(axis=(1, 2)) > 1e-6
            layout_err += np.linalg.norm(obj.markers.corners - true, axis=-1)[seen].ravel().tolist()
            measured_err += np.linalg.norm(inst.sites - true, axis=-1)[seen].ravel().tolist()
    # The sites its frames read, nearer the truth than the layout (the others stay).
    assert measured_err and np.mean(measured_err) < 0.8 * np.mean(layout_err)
    assert main(["annotate", str(root), "--workers", "2", "--quiet"]) == 0
    after = sequence_errors(root)
    assert np.median(after.error_pct) < 0.8 * np.median(before.error_pct)
    assert after.gross_unflagged == 0


def test_the_moved_split_is_the_one_the_plain_count_finds() -> None:
    """The split of a part's frames into agreeing and disagreeing (counted at every moment at
    once) is the first best one a plain count over every moment and both ways finds."""
    from annotator.annotation.sequence.adjustment import _moved_run

    def plain(order: list[int], agree: list[bool], share: float) -> list[int] | None:
        best: tuple[int, list[int]] | None = None
        for k in range(1, len(order)):
            for before_agrees in (True, False):
                score = sum(a == before_agrees for a in agree[:k])
                score += sum(a != before_agrees for a in agree[k:])
                if best is None or score > best[0]:
                    best = (score, order[k:] if before_agrees else order[:k])
        if best is None or best[0] < 0.9 * len(order):
            return None
        side = best[1]
        return None if len(side) < 2 or len(side) < share * len(order) else side

    rng = np.random.default_rng(3)
    for case in range(3000):
        n = int(rng.integers(0, 30))
        order = sorted(rng.choice(500, n, replace=False).tolist())
        cut = int(rng.integers(0, n + 1))
        if case % 2:  # a part that moved at ``cut``, a few frames misread
            agree = [(i < cut) != bool(rng.uniform() < 0.05) for i in range(n)]
        else:
            agree = [bool(a) for a in rng.uniform(size=n) < rng.uniform()]
        share = float(rng.uniform(0, 0.5))
        assert _moved_run(order, agree, share) == plain(order, agree, share)


def test_depths_at_the_markers_are_numpys_medians() -> None:
    """The depth at every marker of a frame, taken at once: each the median of the measured
    pixels of the 5x5 round its centre, as ``np.median`` gives it (NaN under 5 measured),
    at the image's borders too."""
    from annotator.annotation.sequence.reading import _depths_at

    rng = np.random.default_rng(11)
    for _ in range(200):
        depth = rng.uniform(300, 900, (48, 64)).astype(np.float32)
        depth[rng.uniform(size=depth.shape) < rng.uniform(0, 0.9)] = np.nan
        centres = np.column_stack([rng.integers(0, 64, 12), rng.integers(0, 48, 12)])
        # Four corners round each centre (their mean the centre, to rounding).
        spread = [rng.normal(0, 3, (4, 2)) for _ in centres]
        corners = [c + s - s.mean(axis=0) for c, s in zip(centres, spread)]
        want = []
        for u, v in centres:
            patch = depth[max(v - 2, 0) : v + 3, max(u - 2, 0) : u + 3]
            good = patch[np.isfinite(patch)]
            want.append(float(np.median(good)) if good.size >= 5 else np.nan)
        np.testing.assert_array_equal(_depths_at(depth, corners), want)
