"""Robust consensus: one instance's pose from all its marker observations, and its trust.

Every camera's candidate poses (see :mod:`annotator.pnp`) are scored by how many of the
instance's markers, in all cameras, they reproject within ``inlier_px``; the best is refined
on its inliers, all markers are re-tested against the refined pose, and refined again.
Markers left out are *rejected* (a misread id, a marker glued elsewhere, a false detection).
An id seen twice in one image keeps the detection consistent with the rest.

A pose resting on one blurred reading alone (a *soft* id, see
:mod:`annotator.detection.deblur`) is refused: at least two soft observations (two markers,
or one marker in two cameras) must agree on it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from annotator.annotation.settings import AnnotateSettings
from annotator.annotation.site_trust import SiteErrors, site_errors
from annotator.dataset import Dataset
from annotator.dataset.figures import MarkerUse, Reprojection
from annotator.dataset.flags import Flag
from annotator.dataset.records import InstanceAnnotation
from annotator.geometry.camera import Camera
from annotator.pnp import (
    Observation,
    PoseEstimate,
    iter_candidate_poses,
    refine_pose,
    reprojection_errors,
    rms_uncertainty,
)
from annotator.pnp.multiview import lone_marker_poses
from annotator.refinement.depth import pose_covariance
from annotator.symmetry import PoseSpace
from annotator.symmetry.space import MATCH_THRESHOLD_FRACTION


def pose_instance(
    ds: Dataset, obj: str, inst: str, obs: list[Observation], s: AnnotateSettings
) -> InstanceAnnotation | None:
    """Pose one instance from its observations, with its markers' use, reprojection error,
    uncertainty and flags (depth and occlusion are added later, with the whole scene)."""
    cams = ds.rig.cameras
    best = _best_candidate(cams, obs, s.inlier_px)
    if best is None:
        return None
    fit = _refine_on_inliers(cams, obs, best, s)
    if fit is None:
        return None
    est, inliers = fit
    used = [obs[k] for k in inliers]
    if all(o.soft for o in used) and len({(o.camera, o.marker_id) for o in used}) < 2:
        return None  # one blurred reading alone is not evidence enough
    err = reprojection_errors(cams, obs, est.T)
    model = ds.objects[obj]
    sites = site_errors(model, inst, used, s)
    unc = rms_uncertainty(model.mesh.moments, est.T[:3, :3], _covariance(cams, used, est, sites))
    reprojection = _reprojection(cams, obs, inliers, err)
    flags: list[Flag | str] = []
    if len(reprojection.per_camera) < 2:
        flags.append(Flag.SINGLE_VIEW)
    if _ambiguous(cams, used, est.T, s):
        flags.append(Flag.AMBIGUOUS)
    if float(np.sqrt(np.mean(err[inliers] ** 2))) > s.high_residual_px:
        flags.append(Flag.HIGH_RESIDUAL)
    # A blurred reading that disagrees is a misreading, not a marker glued elsewhere.
    if any(k not in inliers and not obs[k].soft for k in range(len(obs))):
        flags.append(Flag.REJECTED_MARKERS)
    if not unc < s.high_uncertainty_fraction * model.mesh.moments.diameter:
        flags.append(Flag.HIGH_UNCERTAINTY)
    if sites.unchecked:
        flags.append(Flag.UNCHECKED_SITES)
    return InstanceAnnotation(
        obj,
        inst,
        est.T[:3, :3].copy(),
        est.T[:3, 3].copy(),
        uncertainty_mm=round(unc, 4) if np.isfinite(unc) else None,
        reprojection=reprojection,
        markers=_marker_use(cams, obs, inliers),
        views=len(reprojection.per_camera),
        flags=flags,
    )


def _covariance(
    cams: Sequence[Camera], used: list[Observation], est: PoseEstimate, sites: SiteErrors
) -> np.ndarray:
    """The pose's covariance, with what its markers' site errors do to it where the sites
    are not exact (:mod:`annotator.annotation.site_trust`): the residuals cannot show them,
    the pose follows its sites."""
    if sites.exact:
        return est.covariance
    return pose_covariance(
        est.T,
        depth=None,
        cameras=cams,
        observations=used,
        site_sigmas=sites.taken,
        fitted_sites=sites.fitted,
    )


def _best_candidate(
    cams: Sequence[Camera], obs: list[Observation], inlier_px: float
) -> np.ndarray | None:
    """The candidate pose that most markers (then the smallest clipped error) support."""
    best, best_key = None, None
    everything = len({(o.camera, o.marker_id) for o in obs})
    for T in iter_candidate_poses(cams, obs):
        err = reprojection_errors(cams, obs, T)
        inl = _dedupe(obs, err, inlier_px)
        key = (len(inl), -float(np.sum(np.minimum(err, inlier_px))))
        if best_key is None or key > best_key:
            best, best_key = T, key
        if len(inl) == everything:
            break  # explains every marker: no other hypothesis can do better after refinement
    return best


def _refine_on_inliers(
    cams: Sequence[Camera], obs: list[Observation], T: np.ndarray, s: AnnotateSettings
) -> tuple[PoseEstimate, list[int]] | None:
    """Refine ``T`` on the markers it explains, re-test every marker and refine again (at
    most twice): the estimate and the indices of its inliers, or None if none is."""
    inliers = _dedupe(obs, reprojection_errors(cams, obs, T), s.inlier_px)
    if not inliers:
        return None
    est = refine_pose(cams, [obs[k] for k in inliers], T)
    for _ in range(2):
        err = reprojection_errors(cams, obs, est.T)
        new = _dedupe(obs, err, max(s.final_inlier_px, 4.0 * est.sigma_px))
        if not new or new == inliers:
            break
        inliers = new
        est = refine_pose(cams, [obs[k] for k in inliers], est.T)
    return est, inliers


def _marker_use(
    cams: Sequence[Camera], obs: list[Observation], inliers: list[int]
) -> dict[str, MarkerUse]:
    """Per camera, the observed markers used and rejected; soft ones used are recovered."""
    markers: dict[str, MarkerUse] = {}
    for k, o in enumerate(obs):
        use = markers.setdefault(cams[o.camera].name, MarkerUse())
        (use.used if k in inliers else use.rejected).append(o.marker_id)
        if o.soft and k in inliers:
            use.recovered.append(o.marker_id)
    return markers


def _reprojection(
    cams: Sequence[Camera], obs: list[Observation], inliers: list[int], err: np.ndarray
) -> Reprojection:
    """RMS and worst error of the inliers, and RMS per camera that has any."""
    used_err = err[inliers]
    per_cam = {}
    for j in sorted({obs[k].camera for k in inliers}):
        e = [err[k] for k in inliers if obs[k].camera == j]
        per_cam[cams[j].name] = round(float(np.sqrt(np.mean(np.square(e)))), 4)
    return Reprojection(
        round(float(np.sqrt(np.mean(used_err**2))), 4), round(float(np.max(used_err)), 4), per_cam
    )


def flag_overlaps(ds: Dataset, instances: list[InstanceAnnotation]) -> None:
    """Two copies of a part cannot be in the same place: when two instances' poses are within
    10% of the diameter (the paper's match threshold), a marker was glued on or read as the
    wrong copy. Both are flagged ``overlap``."""
    for obj in {r.object for r in instances}:
        mine = [r for r in instances if r.object == obj]
        if len(mine) < 2:
            continue
        model = ds.objects[obj]
        space = PoseSpace.from_moments(model.mesh.moments, model.symmetry)
        R = np.stack([r.R for r in mine])
        t = np.stack([r.t for r in mine])
        D = space.distance_matrix(R, t, R, t)
        np.fill_diagonal(D, np.inf)
        for k in np.flatnonzero(D.min(axis=1) < MATCH_THRESHOLD_FRACTION * space.diameter):
            mine[k].flags.append(Flag.OVERLAP)


def _dedupe(obs: list[Observation], err: np.ndarray, thr: float) -> list[int]:
    """Indices of observations within ``thr``, keeping one per (camera, marker id)."""
    best: dict[tuple[int, int], int] = {}
    for k, o in enumerate(obs):
        if not err[k] < thr:
            continue
        key = (o.camera, o.marker_id)
        if key not in best or err[k] < err[best[key]]:
            best[key] = k
    return sorted(best.values())


def _ambiguous(
    cams: Sequence[Camera], used: list[Observation], T: np.ndarray, s: AnnotateSettings
) -> bool:
    """True if a single marker in a single camera explains two different poses about equally
    well (the two IPPE solutions' reprojection errors within ``ambiguity_ratio``)."""
    if len({o.camera for o in used}) > 1 or len({o.marker_id for o in used}) > 1:
        return False
    o = used[0]
    cam = cams[o.camera]
    sols = lone_marker_poses(cam, o)
    if len(sols) < 2:
        return True
    alone = Observation(0, o.marker_id, o.model_corners, o.image_corners)
    errs = sorted(
        float(reprojection_errors([cam], [alone], cam.rig_T_cam @ S)[0]) for S in sols[:2]
    )
    return errs[1] / max(errs[0], 0.05) < s.ambiguity_ratio
