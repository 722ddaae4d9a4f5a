"""Multi-view PnP on hand-made cases: known pose in, same pose out; ambiguity; uncertainty."""

from __future__ import annotations

import numpy as np
import pytest

from annotator.geometry.camera import Camera
from annotator.geometry.lie import rotvec_to_matrix
from annotator.geometry.mesh import Mesh
from annotator.geometry.transforms import invert, make_transform, random_rotations
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


# --- Robust per-instance pose (annotator.annotation.consensus) on the same hand-made geometry ---


def _fake_dataset(cams):
    """What the per-instance pipeline reads from a Dataset: cameras, the mesh and the marker
    sites (none measured: the layout is exact)."""
    from types import SimpleNamespace

    mesh = Mesh(*_box())
    return SimpleNamespace(
        rig=SimpleNamespace(cameras=cams), objects={"box": SimpleNamespace(mesh=mesh, markers=None)}
    )


def test_a_mislabeled_marker_is_rejected_and_flagged() -> None:
    from annotator.annotation.consensus import pose_instance
    from annotator.annotation.settings import AnnotateSettings

    rng = np.random.default_rng(11)
    cams = _rig()
    T = _true_pose(rng)
    sites = _sites(5, rng)
    obs = _observe(cams, sites, T, rng, noise=0.2)
    # Marker 2 in the left image really belongs to another copy 40 mm away.
    other = make_transform(T[:3, :3], T[:3, 3] + [40.0, 10.0, 0.0])
    uv = cams[0].project(sites[2] @ other[:3, :3].T + other[:3, 3])
    obs = [o if (o.camera, o.marker_id) != (0, 2) else Observation(0, 2, sites[2], uv) for o in obs]
    r = pose_instance(_fake_dataset(cams), "box", "01", obs, AnnotateSettings())
    assert np.abs(r.T[:3, 3] - T[:3, 3]).max() < 0.5
    assert r.markers["left"].rejected == [2]
    assert 2 in r.markers["right"].used
    assert "rejected_markers" in r.flags


def test_an_id_seen_twice_keeps_the_consistent_detection() -> None:
    from annotator.annotation.consensus import pose_instance
    from annotator.annotation.settings import AnnotateSettings

    rng = np.random.default_rng(12)
    cams = _rig()
    T = _true_pose(rng)
    sites = _sites(4, rng)
    obs = _observe(cams, sites, T, rng, noise=0.2)
    copy = next(o for o in obs if (o.camera, o.marker_id) == (1, 0))
    obs.append(Observation(1, 0, copy.model_corners, copy.image_corners + [-300.0, 150.0]))
    r = pose_instance(_fake_dataset(cams), "box", "01", obs, AnnotateSettings())
    assert np.abs(r.T[:3, 3] - T[:3, 3]).max() < 0.5
    assert r.markers["right"].used.count(0) == 1
    assert r.markers["right"].rejected == [0]
    assert r.flags == ["rejected_markers"]


def test_a_lone_fronto_parallel_marker_is_flagged_ambiguous_not_guessed() -> None:
    from annotator.annotation.consensus import pose_instance
    from annotator.annotation.settings import AnnotateSettings

    rng = np.random.default_rng(13)
    cams = _rig()[:1]
    # A stray marker alone on a wall facing the camera, far away: its two IPPE poses tie.
    site = square_corners(np.zeros(3), np.array([0.0, 0, -1]), np.array([1.0, 0, 0]), 10.0)
    T = make_transform(rotvec_to_matrix(np.array([0.05, 0.0, 0.0])), [0.0, 0.0, 900.0])
    obs = _observe(cams, site[None], T, rng, noise=0.2)
    r = pose_instance(_fake_dataset(cams), "box", "01", obs, AnnotateSettings())
    assert {"ambiguous", "single_view", "high_uncertainty"} <= set(r.flags)
    # Seen by two cameras the same instance is not ambiguous.
    cams2 = _rig()
    obs2 = _observe(cams2, _sites(3, rng), _true_pose(rng), rng, noise=0.2)
    r2 = pose_instance(_fake_dataset(cams2), "box", "01", obs2, AnnotateSettings())
    assert r2.flags == [] and r2.views == 2


def test_uncertainty_grows_with_corner_noise() -> None:
    rng = np.random.default_rng(14)
    cams = _rig()
    moments = Mesh(*_box()).moments
    T = _true_pose(rng)
    sites = _sites(4, rng)
    unc = []
    for noise in (0.5, 2.0):
        obs = _observe(cams, sites, T, rng, noise=noise)
        est = refine_pose(cams, obs, candidate_poses(cams, obs)[0])
        unc.append(rms_uncertainty(moments, est.T[:3, :3], est.covariance))
    assert 2.0 < unc[1] / unc[0] < 8.0


def test_analytic_jacobian_matches_finite_differences() -> None:
    # The refinement's Jacobian (OpenCV's projection derivatives chained with the pose
    # perturbation, distortion included) against central differences of the residuals.
    from annotator.geometry.lie import perturb
    from annotator.pnp.multiview import residuals_jacobian

    rng = np.random.default_rng(11)
    cams = _rig()
    T = _true_pose(rng)
    obs = _observe(cams, _sites(4, rng), T, rng, noise=0.5)
    x = np.stack([o.image_corners for o in obs])
    _, J = residuals_jacobian(cams, obs, T, x)
    eps = np.array([1e-6] * 3 + [1e-4] * 3)
    numeric = np.column_stack(
        [
            (
                residuals_jacobian(cams, obs, perturb(T, e), x)[0]
                - residuals_jacobian(cams, obs, perturb(T, -e), x)[0]
            )
            / (2 * e[k])
            for k, e in enumerate(np.diag(eps))
        ]
    )
    assert np.abs(J - numeric).max() < 1e-3 * np.abs(numeric).max()


def test_a_marker_misread_as_another_of_the_parts_ids_is_forgiven() -> None:
    # Marker 3, read in the left image as id 2 (a few bits off): the consensus leaves the
    # reading out, and since it lies exactly where marker 3 is kept in the right image, it
    # says nothing about the pose: no rejected_markers. A sticker of id 2 on another copy
    # (read where no kept marker is) keeps its flag.
    from annotator.annotation.consensus import pose_instance
    from annotator.annotation.misreads import forgive_misreadings
    from annotator.annotation.settings import AnnotateSettings

    rng = np.random.default_rng(11)
    cams = _rig()
    T = _true_pose(rng)
    sites = _sites(5, rng)
    obs = _observe(cams, sites, T, rng, noise=0.2)
    three = next(o for o in obs if (o.camera, o.marker_id) == (0, 3))
    misread = [o for o in obs if o.camera != 0 or o.marker_id not in (2, 3)]
    misread.append(Observation(0, 2, sites[2], three.image_corners))
    other = make_transform(T[:3, :3], T[:3, 3] + [40.0, 10.0, 0.0])
    uv = cams[0].project(sites[2] @ other[:3, :3].T + other[:3, 3])
    elsewhere = [o for o in obs if (o.camera, o.marker_id) != (0, 2)]
    elsewhere.append(Observation(0, 2, sites[2], uv))
    for case, forgiven in ((misread, True), (elsewhere, False)):
        r = pose_instance(_fake_dataset(cams), "box", "01", case, AnnotateSettings())
        assert r.markers["left"].rejected == [2] and "rejected_markers" in r.flags
        forgive_misreadings(cams, [r], {("box", "01"): case})
        assert ("rejected_markers" not in r.flags) == forgiven
