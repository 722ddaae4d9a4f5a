"""Poses on few markers refined against the measured depth inside ``annotate``
(annotator.annotation.refine, over annotator.refinement), on the sample scenes: a lone
marker's pose, what its uncertainty counts, which poses may be refined, and a biased depth
map whose offset is solved for."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from annotator.annotation.refine import refinable
from annotator.annotation.scene import annotate_scene
from annotator.annotation.settings import AnnotateSettings
from annotator.dataset import load_dataset, read_poses
from annotator.dataset.figures import DepthCheck
from annotator.dataset.flags import Flag
from annotator.dataset.records import InstanceAnnotation, SceneAnnotation
from annotator.detection import MarkerDetector
from annotator.io.images import to_gray8
from annotator.noise import NOISE
from annotator.occlusion import CastMemo, scene_visibility
from annotator.pnp import rms_uncertainty
from annotator.refinement import DepthTerm, RefineSettings, measured_points, refine_instance
from annotator.refinement.depth import Known, pose_covariance
from annotator.rendering.raycast import PlacedMesh
from annotator.repair import instance_observations, used_observations
from annotator.symmetry import PoseSpace

#: In the sample scene 000003, brick/01 is posed on one marker.
SCENE, LONE = "000003", "brick/01"


@functools.cache
def _annotated(root: str, refine_max_markers: int) -> SceneAnnotation:
    ds = load_dataset(root)
    settings = AnnotateSettings(refine_max_markers=refine_max_markers)
    return annotate_scene(
        ds, ds.scene(SCENE), MarkerDetector(ds.dictionary), settings=settings
    ).annotation


def _error(ds, inst: InstanceAnnotation) -> float:
    """Pose error against gt.json, as a fraction of the diameter."""
    g = next(p for p in read_poses(ds.scene(SCENE).gt_path) if p.key == inst.key)
    o = ds.objects[inst.object]
    space = PoseSpace.from_moments(o.mesh.moments, o.symmetry)
    return float(space.distance(inst.R[None], inst.t[None], g.R[None], g.t[None])[0]) / (
        space.diameter
    )


def test_a_lone_marker_pose_is_refined_and_the_others_stay(sample) -> None:
    ds = load_dataset(sample)
    before = {i.key: i for i in _annotated(str(sample), 0).instances}
    after = {i.key: i for i in _annotated(str(sample), 2).instances}
    assert before.keys() == after.keys()
    b, a = before[LONE], after[LONE]
    assert len(a.marker_ids()) == 1
    # The depth makes it better, and good in itself (its marker alone: 0.8 % of D here, 2 %
    # before the edge fit's rounds; refined: 0.4-0.5 % either way).
    assert _error(ds, a) < min(0.75 * _error(ds, b), 0.006)
    # Its uncertainty says so, honestly: within 3x of the error, and no longer flagged.
    assert a.uncertainty_mm is not None and b.uncertainty_mm is not None
    assert a.uncertainty_mm < b.uncertainty_mm
    error_mm = _error(ds, a) * ds.objects[a.object].mesh.moments.diameter
    assert error_mm < 3 * a.uncertainty_mm
    assert Flag.HIGH_UNCERTAINTY in b.flags and Flag.HIGH_UNCERTAINTY not in a.flags
    assert a.depth is not None and b.depth is not None
    assert a.depth.median_abs_mm < b.depth.median_abs_mm
    # Poses on three markers or more are those of the markers alone, to the bit.
    for key, x in before.items():
        if len(x.marker_ids()) > 2:
            assert np.array_equal(x.T, after[key].T), key
            assert x.uncertainty_mm == after[key].uncertainty_mm, key


def _lone_inputs(sample):
    """The lone marker's pose as annotated, its observations and the depth term."""
    ds = load_dataset(sample)
    sc = ds.scene(SCENE)
    ann = _annotated(str(sample), 2)
    inst = next(i for i in ann.instances if i.key == LONE)
    detector = MarkerDetector(ds.dictionary)
    readings = [detector.read(to_gray8(sc.read_image(c))) for c in ds.rig.cameras]
    mesh = ds.objects[inst.object].mesh
    obs = instance_observations(ds, readings, inst.object, inst.instance)
    used = used_observations(ds.rig.cameras, mesh, obs, inst.markers)
    others = [PlacedMesh(ds.objects[i.object].mesh, i.T) for i in ann.instances if i is not inst]
    cam = ds.rig.depth_camera
    points = measured_points(cam, sc.read_depth(ds.rig), mesh, inst.T, others, RefineSettings())
    return ds, inst, used, DepthTerm(mesh, points, cam.rig_T_cam[:3, 3])


def test_the_measured_points_are_the_same_from_visibilitys_casts(sample) -> None:
    # Every part's points, with the casts scene_visibility kept (every other pixel) taken
    # instead of cast again: the same points, to the bit.
    ds = load_dataset(sample)
    sc = ds.scene(SCENE)
    depth = sc.read_depth(ds.rig)
    ann = _annotated(str(sample), 2)
    meshes = [ds.objects[i.object].mesh for i in ann.instances]
    memo: CastMemo = {}
    scene_visibility(ds.rig, meshes, [i.T for i in ann.instances], step=2, memo=memo)
    cam = ds.rig.depth_camera
    settings = RefineSettings(margin_px=-2)
    placed = [PlacedMesh(m, i.T) for m, i in zip(meshes, ann.instances)]
    for k, (mesh, inst) in enumerate(zip(meshes, ann.instances)):
        others = placed[:k] + placed[k + 1 :]
        alone = measured_points(cam, depth, mesh, inst.T, others, settings)
        known = measured_points(cam, depth, mesh, inst.T, others, settings, Known(memo, 2))
        assert len(alone) > 0 and np.array_equal(alone, known), inst.key


def test_the_depth_bias_and_the_site_errors_widen_the_uncertainty(sample) -> None:
    ds, inst, used, term = _lone_inputs(sample)
    moments = ds.objects[inst.object].mesh.moments
    (marker,) = inst.marker_ids()

    def unc(sites=None, bias: float = 0.0) -> float:
        cov = pose_covariance(
            inst.T,
            depth=term,
            cameras=ds.rig.cameras,
            observations=used,
            site_sigmas=sites,
            noise=dataclasses.replace(NOISE, depth_bias_mm=bias),
        )
        return rms_uncertainty(moments, inst.R, cov)

    alone = unc()
    assert np.isfinite(alone) and alone > 0
    assert unc({marker: (0.0, 0.0)}) == pytest.approx(alone)
    assert unc(bias=0.3) > alone
    glued = unc({marker: (0.7, np.radians(2.0))})
    measured = unc({marker: (0.1, np.radians(0.5))})
    assert alone < measured < glued
    # A lone marker's site error goes into the pose whole: at least the shift itself.
    assert glued > 0.7


def test_which_poses_the_depth_may_refine() -> None:
    def inst(*flags: Flag, depth: bool = True) -> InstanceAnnotation:
        check = DepthCheck(0.9, 0.5, 1000) if depth else None
        return InstanceAnnotation("o", "1", np.eye(3), np.zeros(3), depth=check, flags=[*flags])

    assert refinable(inst())
    assert refinable(inst(Flag.HIGH_UNCERTAINTY, Flag.SINGLE_VIEW))
    assert not refinable(inst(depth=False))
    assert not refinable(inst(Flag.DEPTH_DISAGREEMENT))  # a stray or misread marker, maybe
    assert not refinable(inst(Flag.OVERLAP))
    assert refinable(inst(Flag.AMBIGUOUS, Flag.DEPTH_DISAGREEMENT))  # the flip the depth shows


def test_a_biased_depth_map_does_not_pull_the_pose_with_its_offset_solved(sample) -> None:
    ds = load_dataset(sample)
    sc = ds.scene(SCENE)
    gt = read_poses(sc.gt_path)
    g = next(p for p in gt if p.key == LONE)
    mesh = ds.objects[g.object].mesh
    others = [PlacedMesh(ds.objects[p.object].mesh, p.T) for p in gt if p.key != LONE]
    _, _, used, _ = _lone_inputs(sample)
    depth = sc.read_depth(ds.rig)
    assert depth is not None
    far = depth + 1.0  # the whole map 1 mm too far along the optical axis (near the rays)

    def refined(offset_sigma: float):
        return refine_instance(
            mesh,
            g.T,
            depth_camera=ds.rig.depth_camera,
            depth=far,
            others=others,
            cameras=ds.rig.cameras,
            observations=used,
            settings=RefineSettings(margin_px=-2, depth_offset_sigma_mm=offset_sigma),
        )

    plain, solved = refined(0.0), refined(5.0)
    assert plain.converged and solved.converged
    assert plain.depth_offset_mm == 0.0
    # Seen only through one marker's two views: a tenth of a pixel of disparity is about
    # 0.2 mm along the view here, so the offset is found to a few tenths.
    assert solved.depth_offset_mm == pytest.approx(-1.0, abs=0.35)
    moved = [np.linalg.norm(r.T[:3, 3] - g.t) for r in (plain, solved)]
    assert moved[1] < 0.5 * moved[0]


def test_tracked_nearest_samples_are_the_k_d_trees_own() -> None:
    """A cloud moved a little at a time, as a refinement's measured points are: the same
    nearest samples and distances as a query of the tree each time, gate included, with most
    points not searched again once the steps are small."""
    from scipy.spatial import cKDTree

    from annotator.geometry.lie import perturb
    from annotator.refinement.nearest import TrackedNearest

    rng = np.random.default_rng(3)
    samples = rng.uniform(-20, 20, (5000, 3))
    tree = cKDTree(samples)
    points = samples[rng.choice(len(samples), 800)] + rng.normal(0, 0.5, (800, 3))
    points[:20] += 30.0  # beyond every gate at first
    tracked = TrackedNearest(tree, samples, len(points))
    T = np.eye(4)
    for k, gate in enumerate([15.0, 9.0, 3.0, 3.0, 3.0, 5.0, 3.0, 3.0]):
        q = points @ T[:3, :3].T + T[:3, 3]
        got = tracked.query(q, gate)
        want = tree.query(q, k=1, distance_upper_bound=gate)
        np.testing.assert_array_equal(got[1], want[1])
        np.testing.assert_allclose(got[0], want[0], rtol=1e-12)
        T = perturb(T, np.r_[0.02, -0.01, 0.01, 0.5, 0.2, -0.3] * 0.3**k)
    assert tracked.searched < 0.6 * 8 * len(points)


def test_norms_are_numpys_own_bits() -> None:
    """The refinement's written-out norms of (N, 3) vectors: np.linalg.norm's, bit for bit
    (its sum of squares in its order), over magnitudes from microns to metres."""
    from annotator.geometry.lie import norms

    rng = np.random.default_rng(7)
    v = rng.normal(size=(50_000, 3)) * rng.uniform(1e-3, 1e3, (50_000, 1))
    np.testing.assert_array_equal(norms(v), np.linalg.norm(v, axis=1))
    np.testing.assert_array_equal(norms(v[::3]), np.linalg.norm(v[::3], axis=1))
