"""Synthetic scenes: marker corners match the ground truth, stereo depth matches the ideal
depth, the output is deterministic, bad options change nothing."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from annotator.cli import main
from annotator.dataset import load_dataset, read_poses
from annotator.detection import MarkerDetector
from annotator.rendering.raycast import PlacedMesh, render

pytestmark = pytest.mark.slow  # scenes rendered first


@pytest.fixture(scope="module")
def fresh(tmp_path_factory):
    """Two scenes made now by the renderer under test (not the committed sample: a broken
    renderer that stays deterministic would pass on those)."""
    out = tmp_path_factory.mktemp("fresh") / "ds"
    args = ["synth", str(out), "--parts", "bracket,brick,cylinder", "--scenes", "2"]
    assert main(args + ["--instances", "8-10", "--seed", "17", "--workers", "2", "--quiet"]) == 0
    return out


def test_detected_corners_match_projected_ground_truth(fresh) -> None:
    ds = load_dataset(fresh)
    detector = MarkerDetector(ds.dictionary)
    errors = []
    for scene in ds.scenes():
        poses = {p.key: p for p in read_poses(scene.gt_path)}
        for cam in ds.rig.cameras:
            for det in detector.detect(scene.read_image(cam)):
                ref = ds.marker_table[det.id]
                key = f"{ref.object}/{ref.instance}"
                if key not in poses:  # a false detection (rare): not a test of the renderer
                    continue
                X = ds.objects[ref.object].markers.corners[ref.site]
                T = cam.cam_T_rig @ poses[key].T
                uv = cam.project(X @ T[:3, :3].T + T[:3, 3])
                errors += list(np.linalg.norm(det.corners - uv, axis=1))
    assert len(errors) > 200
    assert np.median(errors) < 0.3, np.median(errors)


def test_stereo_depth_agrees_with_ideal_depth(fresh) -> None:
    ds = load_dataset(fresh)
    cam = ds.rig.depth_camera
    scene = ds.scenes()[0]
    depth = scene.read_depth(ds.rig)
    poses = read_poses(scene.gt_path)
    ideal = render(
        cam, [PlacedMesh(ds.objects[p.object].mesh, cam.cam_T_rig @ p.T) for p in poses]
    ).depth
    parts = np.isfinite(ideal)
    valid = np.isfinite(depth) & parts
    valid_fraction = valid.sum() / parts.sum()
    close = np.abs(depth[valid] - ideal[valid]) < 2.0
    print(
        f"valid on parts: {valid_fraction:.3f}; within 2 mm of the ideal depth: {close.mean():.3f}"
    )
    assert valid_fraction > 0.8
    assert close.mean() > 0.9
    # The exact depth of everything in view (bin and table too) is written beside it.
    from annotator.io.images import read_depth

    exact = read_depth(scene.path / "depth_ideal.png", ds.rig.depth.scale)
    both = np.isfinite(exact) & np.isfinite(depth)
    assert np.mean(np.abs(exact[both] - depth[both]) < 2.0) > 0.9


def _digest(folder) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(p.relative_to(folder).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def test_same_seed_same_bytes_and_reported_summary(tmp_path, capsys) -> None:
    args = [
        "--scenes",
        "2",
        "--instances",
        "3-4",
        "--size",
        "320x256",
        "--seed",
        "5",
        "--json",
        "--quiet",
    ]
    assert main(["synth", str(tmp_path / "a"), *args]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["scenes"] == 2 and summary["failed"] == 0
    assert main(["synth", str(tmp_path / "b"), *args, "--workers", "2"]) == 0
    assert _digest(tmp_path / "a") == _digest(tmp_path / "b")
    ds = load_dataset(tmp_path / "a")
    gt = read_poses(ds.scenes()[0].gt_path)
    assert 3 <= len(gt) <= 4 and all(0 <= p.extra["occlusion"]["rate"] <= 1 for p in gt)
    assert {o.symmetry.kind for o in ds.objects.values()} == {"none", "revolution_flip"}


def test_one_camera_fixed_rig_has_the_empty_bins_depth(tmp_path) -> None:
    """``--cameras 1`` on a fixed rig: the empty bin's depth still comes from the stereo
    pair (it once asked the one written camera for a second image)."""
    out = tmp_path / "one"
    args = ["synth", str(out), "--scenes", "1", "--instances", "3-3", "--size", "320x256"]
    assert main(args + ["--cameras", "1", "--quiet"]) == 0
    ds = load_dataset(out)
    assert [c.name for c in ds.rig.cameras] == ["left"]
    assert ds.rig.depth is not None and ds.rig.depth.background is not None
    assert (out / ds.rig.depth.background).is_file()


def test_bad_options_give_one_line_and_change_nothing(tmp_path, capsys) -> None:
    existing = tmp_path / "exists"
    existing.mkdir()
    (existing / "keep.txt").write_text("mine")
    cases = [
        (["synth", str(tmp_path / "x"), "--parts", "sprocket"], "unknown part 'sprocket'"),
        (["synth", str(tmp_path / "x"), "--instances", "0-3"], "--instances"),
        (["synth", str(tmp_path / "x"), "--instances", "5-2"], "--instances"),
        (["synth", str(tmp_path / "x"), "--size", "20x10"], "--size"),
        (["synth", str(tmp_path / "x"), "--noise", "-1"], "--noise"),
        (["synth", str(existing)], "exists and is not empty"),
    ]
    for argv, message in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "x").exists()
    assert [p.name for p in existing.iterdir()] == ["keep.txt"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_marker_texture_matches_a_point_by_point_reference() -> None:
    """The renderer's texturing (candidate sites per face, affine in the barycentric
    coordinates) against the definition: a point shows site j's cell if it lies in j's printed
    square, within 2 mm of its plane, on a face turned the same way (cosine > 0.7)."""
    from scipy.spatial.transform import Rotation

    from annotator.geometry.camera import Camera
    from annotator.geometry.transforms import make_transform
    from annotator.markers.texture import marker_bits
    from annotator.synthesis.generate import DICTIONARY, SynthSettings, plan_dataset
    from annotator.synthesis.shading import Surface, render_view

    plan = plan_dataset(SynthSettings(parts=("cylinder", "brick"), instances=(2, 2), seed=4))
    cam = Camera("c", 480, 400, np.array([[900.0, 0, 239.5], [0, 900.0, 199.5], [0, 0, 1]]))
    rng = np.random.default_rng(0)
    for part, layout in zip(plan.parts, plan.layouts):
        sites = layout.corners
        bits = np.stack([marker_bits(DICTIONARY, 10 + j) for j in range(len(sites))])
        for _ in range(3):
            T = make_transform(Rotation.random(random_state=rng).as_matrix(), [0, 0, 350.0])
            surf = Surface(part.mesh, T, 0.8, sites, bits)
            view = render_view(cam, np.eye(4), [surf])
            p = view.hits.model_points(view.placed)[view.hits.hit]
            normal_of_hit = part.mesh.face_normals[view.hits.triangle[view.hits.hit]]
            expected = np.full(len(p), 0.8, np.float32)
            for j, sq in enumerate(sites):
                ex, ey = sq[1] - sq[0], sq[3] - sq[0]
                n = np.cross(ey, ex) / np.linalg.norm(np.cross(ey, ex))
                s = (p - sq[0]) @ ex / (ex @ ex)
                t = (p - sq[0]) @ ey / (ey @ ey)
                d = (p - sq[0]) @ n
                on = (s >= 0) & (s < 1) & (t >= 0) & (t < 1) & (np.abs(d) < 2.0)
                on &= normal_of_hit @ n > 0.7
                c = bits.shape[1]
                i, k = (
                    np.minimum((s[on] * c).astype(int), c - 1),
                    np.minimum((t[on] * c).astype(int), c - 1),
                )
                expected[on] = np.where(bits[j, k, i] > 0, 0.92, 0.04)
            got = view.albedo[view.hits.hit]
            assert np.mean(expected != 0.8) > 0.02  # markers are in view
            # Points within float rounding of a cell edge may fall either side.
            assert np.mean(got != expected) < 2e-3
            assert np.array_equal(view.on_marker[view.hits.hit], got != 0.8)


def test_projector_pattern_is_sampled_like_scipy() -> None:
    from scipy.ndimage import map_coordinates

    from annotator.synthesis.stereo import _bilinear, dot_pattern

    pattern = dot_pattern(64, 48, seed=3)
    rng = np.random.default_rng(1)
    u = rng.uniform(-3, 67, 5000).astype(np.float32)
    v = rng.uniform(-3, 51, 5000).astype(np.float32)
    ref = map_coordinates(pattern, [v, u], order=1, mode="constant", cval=0.0)
    assert np.allclose(_bilinear(pattern, u, v), ref, atol=1e-5)
