"""How well each marker's site is known, as a pose's uncertainty counts it
(annotator.annotation.site_trust, annotator.refinement.depth.pose_covariance's fitted sites):
the layout exact until ``annotator sites`` ran, then by how many scenes measured each site;
a site fitted to the one scene it was seen in shares its error with the pose; a pose that
rests on such sites only is flagged ``unchecked_sites``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from annotator.annotation.scene import annotate_scene
from annotator.annotation.settings import AnnotateSettings
from annotator.annotation.site_trust import site_errors
from annotator.dataset import load_dataset
from annotator.dataset.flags import Flag
from annotator.dataset.model import ObjectModel
from annotator.dataset.records import SceneAnnotation
from annotator.detection import MarkerDetector
from annotator.pnp import Observation, rms_uncertainty
from annotator.refinement.depth import pose_covariance


def _annotate(ds, scene: str = "000000") -> SceneAnnotation:
    return annotate_scene(ds, ds.scene(scene), MarkerDetector(ds.dictionary)).annotation


def _obs(marker_id: int) -> Observation:
    return Observation(0, marker_id, np.zeros((4, 3)), np.zeros((4, 2)))


def _measured(model: ObjectModel, scenes: list[int] | None, move: float = 0.5) -> ObjectModel:
    """``model`` whose first instance's first two sites were measured ``move`` mm off the
    layout (from ``scenes`` scenes each, None: not recorded); its other sites left alone."""
    assert model.markers is not None
    first = model.instances[0]
    sites = model.markers.corners.copy()
    sites[:2] += [move, 0.0, 0.0]
    counts = None if scenes is None else tuple(scenes + [0] * (len(sites) - len(scenes)))
    inst = dataclasses.replace(first, sites=sites, site_scenes=counts)
    return dataclasses.replace(model, instances=(inst, *model.instances[1:]))


def test_which_sites_are_known_how_well(sample) -> None:
    brick = load_dataset(sample).objects["brick"]
    assert brick.markers is not None
    s = AnnotateSettings()
    first, second = brick.instances[0], brick.instances[1]
    ids = first.marker_ids
    reach = brick.markers.size / np.sqrt(2)
    # Nothing measured: the layout is exact.
    exact = site_errors(brick, first.name, [_obs(ids[0])], s)
    assert exact.exact and not exact.unchecked
    # Measured from 4 scenes: 0.25 / 4 mm is below the floor of 0.1 mm.
    got = site_errors(_measured(brick, [4, 1]), first.name, [_obs(m) for m in ids[:3]], s)
    assert got.taken[ids[0]] == (s.measured_site_mm, pytest.approx(s.measured_site_mm / reach))
    assert got.checked == {ids[0]} and not got.unchecked
    # From one scene: fitted to it, s.one_scene_site_mm.
    assert got.fitted == {ids[1]: (s.one_scene_site_mm, pytest.approx(s.one_scene_site_mm / reach))}
    # Left on the layout: the spread of the object's measured sites.
    shift, turn = got.taken[ids[2]]
    assert shift == pytest.approx(0.5 / np.sqrt(2)) and turn == pytest.approx(shift / reach)
    # Another copy without sites of its own: as doubtful, and nothing checks it.
    other = site_errors(_measured(brick, [4, 1]), second.name, [_obs(second.marker_ids[0])], s)
    assert other.taken[second.marker_ids[0]] == (shift, pytest.approx(turn))
    assert other.unchecked
    # A pose on its one-scene site alone is unchecked.
    assert site_errors(_measured(brick, [4, 1]), first.name, [_obs(ids[1])], s).unchecked
    # object.yaml written before site_scenes: a measured site counts as measured.
    old = site_errors(_measured(brick, None), first.name, [_obs(ids[1])], s)
    assert old.taken[ids[1]] == (s.measured_site_mm, pytest.approx(np.radians(0.5)))
    assert not old.unchecked


def _one_marker_pose(sample):
    """Scene 000000's brick/01 and one of its markers as the left camera saw it."""
    ds = load_dataset(sample)
    ann = _annotate(ds)
    inst = next(i for i in ann.instances if i.object == "brick" and len(i.marker_ids()) >= 2)
    cam = ds.rig.cameras[0]
    model = ds.objects["brick"]
    ids = model.instance(inst.instance).marker_ids
    corners = model.site_corners(inst.instance)
    obs = []
    for mid in sorted(inst.marker_ids())[:1]:
        X = corners[ids.index(mid)]
        uv = cam.project_from_rig((inst.T[:3, :3] @ X.T).T + inst.T[:3, 3])
        obs.append(Observation(0, mid, X, uv))
    return ds, inst, obs


def test_a_site_fitted_to_the_pose_leaves_it_less_known(sample) -> None:
    ds, inst, obs = _one_marker_pose(sample)
    moments = ds.objects["brick"].mesh.moments
    (mid,) = {o.marker_id for o in obs}

    def unc(**sites) -> float:
        cov = pose_covariance(inst.T, depth=None, cameras=ds.rig.cameras, observations=obs, **sites)
        return rms_uncertainty(moments, inst.R, cov)

    alone = unc()
    assert unc(fitted_sites={mid: (0.0, 0.0)}) == pytest.approx(alone)
    fitted = unc(fitted_sites={mid: (0.25, np.radians(2.0))})
    taken = unc(site_sigmas={mid: (0.25, np.radians(2.0))})
    assert alone < fitted and alone < taken
    # The freer the site, the less the lone marker says of the pose.
    assert unc(fitted_sites={mid: (2.5, np.radians(20.0))}) > 2 * fitted


def test_poses_on_one_scene_sites_are_flagged_unchecked(sample) -> None:
    ds = load_dataset(sample)
    brick = ds.objects["brick"]
    assert brick.markers is not None
    n = len(brick.markers.corners)

    def measured(move_mm: float, scenes: int) -> ObjectModel:
        """Every copy's sites measured ``move_mm`` off the layout, all one way (the poses
        follow: the images agree as well), each from ``scenes`` scenes."""
        sites = brick.markers.corners + [move_mm, 0.0, 0.0]
        instances = tuple(
            dataclasses.replace(i, sites=sites, site_scenes=(scenes,) * n) for i in brick.instances
        )
        return dataclasses.replace(brick, instances=instances)

    ds.objects["brick"] = measured(0.3, 1)
    ann = _annotate(ds)
    bricks = [i for i in ann.instances if i.object == "brick"]
    others = [i for i in ann.instances if i.object != "brick"]
    assert bricks and all(Flag.UNCHECKED_SITES in i.flags for i in bricks)
    assert not any(Flag.UNCHECKED_SITES in i.flags for i in others)
    # Two scenes each: checked, and the uncertainty counts them.
    plain = {i.key: i.uncertainty_mm for i in _annotate(load_dataset(sample)).instances}
    ds.objects["brick"] = measured(0.3, 2)
    again = [i for i in _annotate(ds).instances if i.object == "brick"]
    assert not any(Flag.UNCHECKED_SITES in i.flags for i in again)
    assert all(i.uncertainty_mm > plain[i.key] for i in again)
    # Sites that gluing hardly moved (0.02 mm) cannot be far off, even from one scene.
    ds.objects["brick"] = measured(0.02, 1)
    near = [i for i in _annotate(ds).instances if i.object == "brick"]
    assert not any(Flag.UNCHECKED_SITES in i.flags for i in near)
