"""The pose refinement alone (annotator.repair), on the sample scenes: its basin of
convergence, a symmetric part, a part mostly hidden, the candidates from the markers, a start
pose for a part without one, and the nudges."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from annotator.dataset import load_dataset, read_poses
from annotator.dataset.records import SceneAnnotation
from annotator.detection import MarkerDetector
from annotator.geometry.lie import matrix_to_rotvec
from annotator.geometry.transforms import axis_angle, make_transform
from annotator.io.images import to_gray8
from annotator.refinement import measured_points
from annotator.rendering.raycast import PlacedMesh
from annotator.repair import (
    Nudge,
    alternatives,
    instance_observations,
    nudged,
    refine_instance,
    start_pose,
    used_observations,
)
from annotator.symmetry import PoseSpace


@functools.cache
def _scene(root: str, sid: str):
    ds = load_dataset(root)
    sc = next(s for s in ds.scenes() if s.id == sid)
    detector = MarkerDetector(ds.dictionary)
    readings = [detector.read(to_gray8(sc.read_image(c))) for c in ds.rig.cameras]
    gt = read_poses(sc.gt_path)
    auto = {i.key: i for i in SceneAnnotation.read(sc.annotation_path).instances}
    return ds, readings, sc.read_depth(ds.rig), gt, auto


def _space(ds, obj: str) -> PoseSpace:
    o = ds.objects[obj]
    return PoseSpace.from_moments(o.mesh.moments, o.symmetry)


def _off(T: np.ndarray, centroid: np.ndarray, seed: int, mm: float, deg: float) -> np.ndarray:
    """``T`` moved by ``mm`` and turned by ``deg`` about the part's centre, in a direction
    drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    a, d = rng.normal(size=3), rng.normal(size=3)
    dR = axis_angle(a, np.radians(deg))
    c = T[:3, :3] @ centroid + T[:3, 3]
    return make_transform(dR @ T[:3, :3], dR @ (T[:3, 3] - c) + c + mm * d / np.linalg.norm(d))


def _refine(root, sid: str, key: str, start: np.ndarray, *, markers: bool = True):
    ds, readings, depth, gt, auto = _scene(str(root), sid)
    p = next(q for q in gt if q.key == key)
    mesh = ds.objects[p.object].mesh
    obs = instance_observations(ds, readings, p.object, p.instance) if markers else []
    used = used_observations(ds.rig.cameras, mesh, obs, auto[key].markers if markers else None)
    others = [PlacedMesh(ds.objects[q.object].mesh, q.T) for q in gt if q.key != key]
    result = refine_instance(
        mesh,
        start,
        depth_camera=ds.rig.depth_camera,
        depth=depth,
        others=others,
        cameras=ds.rig.cameras,
        observations=used,
    )
    space = _space(ds, p.object)
    error = float(space.distance(result.T[:3, :3], result.T[:3, 3], p.R, p.t)[0])
    return result, error / space.diameter, p


@pytest.mark.parametrize(
    "key", ["bracket/01", "bracket/02", "bracket/03", "brick/01", "cylinder/01", "cylinder/02"]
)
def test_convergence_basin_five_mm_ten_degrees(sample, key) -> None:
    ds, *_, gt, _ = _scene(str(sample), "000000")
    p = next(q for q in gt if q.key == key)
    centroid = ds.objects[p.object].mesh.moments.centroid
    for seed in (1, 2):
        start = _off(p.T, centroid, seed, 5.0, 10.0)
        result, error, _ = _refine(sample, "000000", key, start)
        assert result.converged, result.why
        assert error < 0.005, f"{key} seed {seed}: {100 * error:.2f}% of D"
        # The residuals say so: the markers and the depth fit after, not before.
        assert result.after.marker_rms_px < 1.5 < result.before.marker_rms_px
        assert result.after.depth_rms_mm < result.before.depth_rms_mm


def test_a_symmetric_part_converges_to_a_symmetric_equivalent(sample) -> None:
    """A cylinder with depth only: its turn about its axis is not seen, and need not be."""
    ds, *_, gt, _ = _scene(str(sample), "000003")
    key = "cylinder/03"
    p = next(q for q in gt if q.key == key)
    obj = ds.objects["cylinder"]
    axis = p.R @ np.asarray(obj.symmetry.axis, float)
    turned = make_transform(axis_angle(axis, np.radians(40.0)) @ p.R, p.t)
    c = p.R @ obj.mesh.moments.centroid + p.t
    turned[:3, 3] = axis_angle(axis, np.radians(40.0)) @ (p.t - c) + c
    start = _off(turned, obj.mesh.moments.centroid, 3, 5.0, 10.0)
    result, error, _ = _refine(sample, "000003", key, start, markers=False)
    assert result.converged, result.why
    assert error < 0.005
    # Not the pose of gt.json, but one the symmetry maps onto it.
    angle = np.degrees(np.linalg.norm(matrix_to_rotvec(result.T[:3, :3] @ p.R.T)))
    assert angle > 20.0


def test_a_mostly_hidden_part_does_not_drift_into_its_neighbour(sample) -> None:
    """brick/01 of scene 000003 is 65% hidden under its neighbours; their pixels are left out
    of the refinement, and its two markers hold it."""
    ds, readings, depth, gt, auto = _scene(str(sample), "000003")
    key = "brick/01"
    p = next(q for q in gt if q.key == key)
    assert auto[key].occlusion_rate > 0.6
    start = auto[key].T  # annotate's pose, 2.3 mm off
    result, error, _ = _refine(sample, "000003", key, start)
    space = _space(ds, "brick")
    before = float(space.distance(start[:3, :3], start[:3, 3], p.R, p.t)[0]) / space.diameter
    assert result.converged, result.why
    assert error < 0.005 and error < before
    # No measured point it was refined against lies on a neighbour's surface.
    mesh = ds.objects["brick"].mesh
    others = [PlacedMesh(ds.objects[q.object].mesh, q.T) for q in gt if q.key != key]
    pts = measured_points(ds.rig.depth_camera, depth, mesh, result.T, others)[:, :3]
    assert len(pts) > 100
    for q in gt:
        if q.key == key:
            continue
        local = (pts - q.t) @ q.R  # into the neighbour's model frame
        verts = ds.objects[q.object].mesh.vertices
        lo, hi = verts.min(axis=0) + 2.0, verts.max(axis=0) - 2.0
        inside = np.all((local > lo) & (local < hi), axis=1)
        assert inside.mean() < 0.02, q.key
    # Depth alone, too, stays where it is instead of sliding onto a neighbour.
    result, error, _ = _refine(sample, "000003", key, start, markers=False)
    assert error < 0.01


def test_no_convergence_keeps_the_pose_and_says_why(sample) -> None:
    ds, *_, gt, _ = _scene(str(sample), "000000")
    p = next(q for q in gt if q.key == "bracket/01")
    far = make_transform(p.R, p.t + [0.0, 0.0, 400.0])  # nothing measured there
    result = refine_instance(ds.objects["bracket"].mesh, far, depth_camera=None, depth=None)
    assert not result.converged and np.array_equal(result.T, far)
    assert result.why == "no measured depth and no marker on it"


def test_alternatives_hold_the_second_ippe_solution_of_a_lone_marker(sample) -> None:
    ds, readings, *_ = _scene(str(sample), "000003")
    obs = instance_observations(ds, readings, "brick", "05")  # one marker, 82% hidden
    assert len({(o.camera, o.marker_id) for o in obs}) == 1
    found = alternatives(ds.rig.cameras, ds.objects["brick"].mesh, obs)
    assert len(found) >= 2
    assert all(c.support == 1 and c.source == "one marker (IPPE)" for c in found)
    assert found[0].reprojection_px <= found[1].reprojection_px


def _start_at_truth(sample, key: str, *, markers: bool = True):
    """A start pose for ``key`` (of scene 000000) from a click on its true centre in the
    left camera, with the markers as read or with none read; and its true pose."""
    ds, readings, depth, gt, _ = _scene(str(sample), "000000")
    p = next(q for q in gt if q.key == key)
    cam = ds.rig.cameras[0]
    pixel = tuple(cam.project((p.R @ ds.objects[p.object].mesh.moments.centroid + p.t)[None])[0])
    if not markers:
        readings = [
            dataclasses.replace(r, markers=[], unread=r.unread[:0], unread_bits=r.unread_bits[:0])
            for r in readings
        ]
    found = start_pose(
        ds,
        p.object,
        p.instance,
        camera=cam,
        pixel=pixel,
        readings=readings,
        depth=depth,
        others=[PlacedMesh(ds.objects[q.object].mesh, q.T) for q in gt if q.key != key],
    )
    return found, p, ds


def test_a_start_pose_from_the_part_s_markers_refines_to_the_truth(sample) -> None:
    found, p, _ = _start_at_truth(sample, "cylinder/04")
    assert found is not None and found.source == "consensus"
    result, error, _ = _refine(sample, "000000", p.key, found.T)
    assert result.converged and error < 0.005


def test_a_start_pose_from_the_depth_under_the_click_without_markers(sample) -> None:
    """No marker read: the part starts at the depth under the click, the best of the axes'
    rotations; it lies on the measured surface there."""
    found, p, ds = _start_at_truth(sample, "bracket/02", markers=False)
    assert found is not None and found.source == "the depth under the click"
    assert found.support > 50
    moments = ds.objects["bracket"].mesh.moments
    start_c = found.T[:3, :3] @ moments.centroid + found.T[:3, 3]
    assert np.linalg.norm(start_c - (p.R @ moments.centroid + p.t)) < moments.radius


def test_nudges_are_exact_steps_in_the_camera_frame() -> None:
    T = make_transform(axis_angle([1.0, 2.0, 3.0], 0.7), np.array([10.0, -20.0, 500.0]))
    centroid = np.array([1.0, 2.0, 3.0])
    moved = nudged(T, Nudge("move", 2, -10.0), centroid)
    assert np.allclose(moved[:3, :3], T[:3, :3]) and np.allclose(
        moved[:3, 3] - T[:3, 3], [0, 0, -10]
    )
    turned = nudged(T, Nudge("turn", 0, 1.0), centroid)
    w = matrix_to_rotvec(turned[:3, :3] @ T[:3, :3].T)
    assert np.allclose(w, [np.radians(1.0), 0.0, 0.0], atol=1e-12)
    # About the part's centre: the centre stays.
    c = T[:3, :3] @ centroid + T[:3, 3]
    assert np.allclose(turned[:3, :3] @ centroid + turned[:3, 3], c)
