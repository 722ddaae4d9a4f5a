"""Symmetry-aware duplicate removal and mode finding (paper section 4.2), and the PPF baseline
estimator whose results ``annotator evaluate`` scores."""

from __future__ import annotations

import doctest
import json
import time
from pathlib import Path

import numpy as np
import pytest

from annotator.cli import main
from annotator.dataset.model import Symmetry
from annotator.geometry.transforms import axis_angle, random_rotations
from annotator.parts import build_part
from annotator.symmetry import PoseSpace, filter_duplicates, find_modes

CASES = ["bracket", "brick", "gear", "cup", "cylinder", "ball"]
Z = np.array([0.0, 0.0, 1.0])


def _poses(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(R), 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R, t
    return T


def _space(name: str, *, symmetric: bool = True) -> PoseSpace:
    part = build_part(name)
    return PoseSpace.from_moments(part.mesh.moments, part.symmetry if symmetric else Symmetry())


def _symmetric_equivalents(name: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` random elements (rotations about the centroid, model frame) of the part's group."""
    part = build_part(name)
    sym = part.symmetry
    if sym.kind == "none":
        return np.repeat(np.eye(3)[None], n, 0)
    if sym.kind == "finite":
        from annotator.symmetry import finite_group

        G = finite_group(sym.generators)
        return G[rng.integers(0, len(G), n)]
    if sym.kind == "spherical":
        return random_rotations(n, rng)
    G = np.stack([axis_angle(sym.axis, a) for a in rng.uniform(0, 2 * np.pi, n)])
    if sym.kind == "revolution_flip":
        flip = rng.random(n) < 0.5
        G[flip] = G[flip] @ axis_angle([1.0, 0, 0], np.pi)
    return G


def _apply_about_centroid(name: str, T: np.ndarray, G: np.ndarray) -> np.ndarray:
    """Poses ``T`` composed with group elements ``G`` about the surface centroid: the same
    poses of the part, as other rigid transforms."""
    c = build_part(name).mesh.moments.centroid
    out = T.copy()
    out[:, :3, :3] = T[:, :3, :3] @ G
    out[:, :3, 3] = T[:, :3, 3] + np.einsum("nij,nj->ni", T[:, :3, :3], c - G @ c)
    return out


# -------------------------------------------------------------------- filter_duplicates


def test_filter_duplicates_keeps_one_of_eight_gear_poses_45_degrees_apart() -> None:
    gear = build_part("gear")
    R = np.stack([axis_angle(Z, k * np.pi / 4) for k in range(8)])
    T = _apply_about_centroid(
        "gear", _poses(np.repeat(np.eye(3)[None], 8, 0), [[0, 0, 500]] * 8), R
    )
    scores = np.array([3.0, 1.0, 7.0, 2.0, 5.0, 0.5, 4.0, 6.0])
    assert filter_duplicates(T, scores, gear, 1.0).tolist() == [2]  # the best scored
    rigid = _space("gear", symmetric=False)
    kept = filter_duplicates(T, scores, rigid, 1.0)
    assert sorted(kept.tolist()) == list(range(8))
    assert kept.tolist() == np.argsort(-scores).tolist()  # best first


@pytest.mark.parametrize("name", CASES)
def test_filter_duplicates_is_the_greedy_suppression_by_the_papers_distance(name: str) -> None:
    rng = np.random.default_rng(CASES.index(name))
    space = _space(name)
    n = 300
    T = _poses(random_rotations(n, rng), rng.uniform(-40, 40, (n, 3)) + [0, 0, 500])
    scores = rng.random(n)
    radius = 0.3 * space.diameter
    kept = filter_duplicates(T, scores, space, radius)
    # The reference: all pairs, in score order.
    D = space.distance_matrix(T[:, :3, :3], T[:, :3, 3], T[:, :3, :3], T[:, :3, 3])
    ref: list[int] = []
    for i in np.argsort(-scores):
        if all(D[i, j] > radius for j in ref):
            ref.append(int(i))
    assert kept.tolist() == ref
    assert 1 < len(kept) < n


def test_filter_duplicates_takes_ten_thousand_hypotheses() -> None:
    rng = np.random.default_rng(3)
    space = _space("gear")
    n = 10_000
    T = _poses(random_rotations(n, rng), rng.uniform(-100, 100, (n, 3)) + [0, 0, 500])
    start = time.perf_counter()
    kept = filter_duplicates(T, rng.random(n), space, 0.1 * space.diameter)
    assert time.perf_counter() - start < 10.0  # all pairs would be 8 x 10^8 distances
    assert 0 < len(kept) <= n


def test_filter_duplicates_checks_its_input() -> None:
    space = _space("brick")
    assert filter_duplicates(np.zeros((0, 4, 4)), [], space, 1.0).tolist() == []
    with pytest.raises(ValueError, match="scores"):
        filter_duplicates(np.tile(np.eye(4), (2, 1, 1)), [1.0], space, 1.0)
    with pytest.raises(TypeError, match="PoseSpace"):
        filter_duplicates(np.eye(4)[None], [1.0], "brick", 1.0)


# ----------------------------------------------------------------------------- find_modes


@pytest.mark.parametrize("name", CASES)
def test_find_modes_recovers_planted_modes_for_every_symmetry_class(name: str) -> None:
    rng = np.random.default_rng(20 + CASES.index(name))
    space = _space(name)
    D = space.diameter
    k, per_mode = 4, 60
    # Modes far apart (centroids on a line, 1.5 D apart), votes around them with noise on the
    # position and the rotation, each vote a random symmetric equivalent of its mode.
    truth = _poses(random_rotations(k, rng), np.c_[1.5 * D * np.arange(k), np.zeros((k, 2))])
    truth[:, :3, 3] += [0, 0, 600]
    votes = np.repeat(truth, per_mode, axis=0)
    noise = np.stack([axis_angle(a, 0.02) for a in rng.normal(size=(k * per_mode, 3))])
    votes[:, :3, :3] = votes[:, :3, :3] @ noise
    votes[:, :3, 3] += rng.normal(0, 0.01 * D, (k * per_mode, 3))
    votes = _apply_about_centroid(name, votes, _symmetric_equivalents(name, k * per_mode, rng))
    # Outliers: scattered votes of small weight.
    m = 100
    clutter = _poses(random_rotations(m, rng), rng.uniform(-D, 6 * D, (m, 3)) + [0, 0, 600])
    poses = np.concatenate([votes, clutter])
    weights = np.concatenate([rng.uniform(1.0, 2.0, k * per_mode), np.full(m, 0.1)])
    modes = find_modes(poses, weights, space, 0.1 * D)
    found = modes.poses[:k]
    d = space.distance_matrix(found[:, :3, :3], found[:, :3, 3], truth[:, :3, :3], truth[:, :3, 3])
    assert sorted(d.argmin(axis=1).tolist()) == list(range(k))  # one mode per planted mode
    assert d.min(axis=1).max() < 0.02 * D
    for i in range(k):
        j = int(d[i].argmin())
        planted = weights[j * per_mode : (j + 1) * per_mode].sum()
        assert modes.weights[i] == pytest.approx(planted, rel=0.05)
    assert modes.weights[k:].max(initial=0) < 0.1 * modes.weights[:k].min()
    assert np.all(np.diff(modes.weights) <= 0)
    assert np.all(modes.labels[: k * per_mode] >= 0)


def test_find_modes_in_se3_splits_the_votes_of_a_symmetric_part() -> None:
    """The paper's point: in SE(3) the votes for one gear scatter over its 8 equivalent
    rigid transforms, each mode with an eighth of the support."""
    rng = np.random.default_rng(4)
    truth = _poses(random_rotations(1, rng), [[0.0, 0.0, 500.0]])
    votes = _apply_about_centroid(
        "gear", np.repeat(truth, 80, 0), _symmetric_equivalents("gear", 80, rng)
    )
    votes[:, :3, 3] += rng.normal(0, 0.5, (80, 3))
    sym = find_modes(votes, np.ones(80), _space("gear"), 5.0)
    rigid = find_modes(votes, np.ones(80), _space("gear", symmetric=False), 5.0)
    assert sym.weights.tolist() == [80.0]
    assert len(rigid.weights) == 8 and rigid.weights.max() < 20


def test_the_docstring_examples_run() -> None:
    import annotator.symmetry.duplicates as dup
    import annotator.symmetry.modes as modes

    for module in (dup, modes):
        result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE)
        assert result.attempted > 0 and result.failed == 0, module.__name__


# ------------------------------------------------------------------------ the estimator


def test_voting_finds_a_posed_part_in_its_own_points() -> None:
    from annotator.estimation.cloud import OrientedCloud, voxel_subsample
    from annotator.estimation.estimator import PPFSettings
    from annotator.estimation.model import surface_samples, train_model
    from annotator.estimation.voting import vote

    part = build_part("bracket")
    D = part.mesh.moments.diameter
    s = PPFSettings()
    rng = np.random.default_rng(1)
    T = _poses(random_rotations(1, rng), [[10.0, -20.0, 500.0]])[0]
    p, n = surface_samples(part.mesh, s.sampling * D, seed=7)  # other samples than the model's
    p, n = p @ T[:3, :3].T + T[:3, 3], n @ T[:3, :3].T
    seen = np.einsum("ij,ij->i", n, p) < 0  # the side facing the camera
    cloud = voxel_subsample(p[seen], n[seen], s.sampling * D)
    model = train_model(part.mesh, distance_step=s.sampling * D)
    votes = vote(model, OrientedCloud(cloud.points, cloud.normals))
    space = _space("bracket")
    modes = find_modes(votes.poses, votes.weights, space, s.bandwidth * D)
    best = modes.poses[0]
    d = space.distance(best[None, :3, :3], best[None, :3, 3], T[None, :3, :3], T[None, :3, 3])
    assert d[0] < 0.05 * D


@pytest.fixture(scope="module")
def easy_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One small synthetic scene of three bricks, with depth."""
    out = tmp_path_factory.mktemp("estimate") / "ds"
    args = ["synth", str(out), "--parts", "brick", "--scenes", "1", "--instances", "3-3"]
    assert main(args + ["--size", "320x256", "--seed", "2", "--workers", "1", "--quiet"]) == 0
    return out


@pytest.mark.parametrize("flags", [[], ["--symmetric"], ["--symmetric", "--post-process"]])
def test_estimate_results_pass_evaluate(
    easy_scene: Path, tmp_path: Path, flags: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "results.csv"
    args = ["estimate", str(easy_scene), str(out), "--workers", "1", "--quiet", "--json"]
    assert main(args + flags) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["done"] == 1 and summary["failed"] == 0 and summary["results"] > 0
    lines = out.read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time"
    coco = json.loads((tmp_path / "results.json").read_text())  # BOP's 2D results beside it
    assert len(coco) == len(lines) - 1 and summary["coco"] == str(tmp_path / "results.json")
    assert all(r["image_id"] == 0 and len(r["bbox"]) == 4 and r["segmentation"] for r in coco)
    report = tmp_path / "report.json"
    assert main(["evaluate", str(easy_scene), "--results", str(out), "--json", str(report)]) == 0
    ap = json.loads(report.read_text())["overall"]["AP"]
    assert ap > 0, lines[:5]


def test_estimate_bad_input_is_one_line_and_exit_2(
    easy_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["estimate", str(easy_scene), str(tmp_path), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path) in err[0] and "folder" in err[0]
    assert main(["estimate", str(tmp_path / "nothing"), str(tmp_path / "r.csv")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nothing" in err[0]


def test_estimate_reports_a_scene_without_depth_and_goes_on(
    easy_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import shutil

    ds = tmp_path / "ds"
    shutil.copytree(easy_scene, ds)
    shutil.copytree(ds / "scenes" / "000000", ds / "scenes" / "000001")
    (ds / "scenes" / "000001" / "depth.png").unlink()
    out = tmp_path / "r.csv"
    assert main(["estimate", str(ds), str(out), "--workers", "2", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "failed: scene 000001" in err and "depth.png" in err
    assert {line.split(",")[0] for line in out.read_text().splitlines()[1:]} == {"0"}
