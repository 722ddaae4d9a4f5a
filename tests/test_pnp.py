"""Multi-view PnP on hand-made cases: known pose in, same pose out; ambiguity; uncertainty."""

from __future__ import annotations

import numpy as np
import pytest

from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.geometry.transforms import invert, make_transform, random_rotations, rotvec_to_matrix
from annotator.markers.layout import square_corners
from annotator.parts import build_part
from annotator.pnp import (
    Observation,
    candidate_poses,
    refine_pose,
    reprojection_errors,
    rms_uncertainty,
)

K = np.array([[1400.0, 0, 639.5], [0, 1400.0, 511.5], [0, 0, 1]])
DIST = np.array([-0.08, 0.06, 0.0004, -0.0003, -0.01])


def _rig() -> list[Camera]:
    right = make_transform(rotvec_to_matrix(np.array([0.0, -0.19, 0.0])), [100.0, 0.0, 0.0])
    return [Camera("left", 1280, 1024, K, DIST), Camera("right", 1280, 1024, K, DIST, right)]


def _sites(n: int, rng) -> np.ndarray:
    """Marker sites on a 60 mm cube-ish part facing roughly -z (towards the cameras)."""
    out = []
    for _k in range(n):
        normal = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), -1.0])
        centre = rng.uniform(-25, 25, 3)
        out.append(square_corners(centre, normal, np.array([1.0, 0, 0]), 10.0))
    return np.array(out)


def _observe(cams, sites, T, rng, noise=0.1) -> list[Observation]:
    obs = []
    for j, cam in enumerate(cams):
        M = cam.cam_T_rig @ T
        for k, s in enumerate(sites):
            uv = cam.project(s @ M[:3, :3].T + M[:3, 3]) + rng.normal(0, noise, (4, 2))
            obs.append(Observation(j, k, s, uv))
    return obs


def _true_pose(rng) -> np.ndarray:
    R = rotvec_to_matrix(np.array([0.3, -0.2, 0.1]) + rng.normal(0, 0.1, 3))
    return make_transform(R, [20.0, -10.0, 520.0])


@pytest.mark.parametrize("n_cams", [1, 2])
def test_known_pose_in_same_pose_out(n_cams: int) -> None:
    rng = np.random.default_rng(n_cams)
    cams = _rig()[:n_cams]
    T = _true_pose(rng)
    obs = _observe(cams, _sites(5, rng), T, rng, noise=0.0)
    best = min(candidate_poses(cams, obs), key=lambda c: reprojection_errors(cams, obs, c).sum())
    est = refine_pose(cams, obs, best)
    assert np.abs(est.T - T).max() < 1e-4
    assert reprojection_errors(cams, obs, est.T).max() < 1e-3


def test_joint_refinement_beats_noise_and_its_uncertainty_is_calibrated() -> None:
    rng = np.random.default_rng(7)
    cams = _rig()
    moments = build_part("brick").mesh.moments
    ratios = []
    for _trial in range(30):
        T = _true_pose(rng)
        obs = _observe(cams, _sites(4, rng), T, rng, noise=0.3)
        est = refine_pose(cams, obs, candidate_poses(cams, obs)[0])
        d = invert(T) @ est.T
        err = moments.rms_displacement(d[:3, :3], d[:3, 3])
        unc = rms_uncertainty(moments, est.T[:3, :3], est.covariance)
        ratios.append(err / unc)
    ratios = np.array(ratios)
    # Calibrated: errors rarely exceed 3x the estimate, and the estimate is not wildly pessimistic.
    assert np.mean(ratios <= 3.0) >= 0.9
    assert np.median(ratios) > 0.3


def test_lone_marker_gives_both_ippe_candidates() -> None:
    rng = np.random.default_rng(3)
    cams = _rig()[:1]
    T = _true_pose(rng)
    obs = _observe(cams, _sites(1, rng), T, rng, noise=0.05)
    cands = candidate_poses(cams, obs)
    assert len(cands) == 2
    errs = [reprojection_errors(cams, obs, c)[0] for c in cands]
    assert min(errs) < 0.2


def test_uncertainty_matches_the_rms_displacement_of_small_motions() -> None:
    moments = Mesh(*_box()).moments
    R = random_rotations(1, np.random.default_rng(0))[0]
    rng = np.random.default_rng(1)
    cov = np.diag([1e-6, 4e-6, 2e-6, 0.04, 0.01, 0.09])
    samples = rng.multivariate_normal(np.zeros(6), cov, size=4000)
    t = np.array([10.0, 20.0, 500.0])
    sq = []
    for w in samples:
        R2 = rotvec_to_matrix(w[:3]) @ R
        t2 = t + w[3:]
        d = np.linalg.inv(make_transform(R, t)) @ make_transform(R2, t2)
        sq.append(moments.rms_displacement(d[:3, :3], d[:3, 3]) ** 2)
    assert rms_uncertainty(moments, R, cov) == pytest.approx(np.sqrt(np.mean(sq)), rel=0.05)


def _box():
    import trimesh

    b = trimesh.creation.box((40, 30, 20))
    b.apply_translation([3.0, -2.0, 1.0])
    return np.asarray(b.vertices), np.asarray(b.faces, dtype=np.int32)
