"""Poses on few markers refined against the measured depth (:mod:`annotator.refinement`).

A pose on one or two markers is known from a few corners: its tilt and its distance along the
view are poorly pinned down, most of all when the part is mostly hidden. The measured depth
of its visible surface pins them; the refinement keeps its markers in the fit
(:func:`annotator.refinement.refine_instance`, the review viewer's "R"), the other posed parts
hide the depth they explain.

The refined pose is kept only when it is really better: the refinement converged, more of
the measured points lie on the refined surface and closer to it than before, and the markers
still reproject within their noise (``AnnotateSettings.refine_marker_px``). The measured
points are those of the part's visible region shrunk by ``refine_inner_px`` (depth is least
sure at its edges). A pose the depth contradicts (``depth_disagreement``), one that overlaps
another copy, one of the blur model's readings alone, is left as it is: the refinement
polishes a pose, it does not rescue one; but a lone marker's ``ambiguous`` pose may flip to
the solution the depth shows (it keeps its flag).

The depth's points share an offset along their rays (a face seen flat gets one disparity),
solved for with a prior of ``AnnotateSettings.depth_bias_mm``. The refined pose's uncertainty
is that of both terms together (:func:`annotator.refinement.depth.pose_covariance`), with what
such an offset and the markers' site errors do to it (how well each site is known:
:mod:`annotator.annotation.site_trust`). A pose that is really uncertain (a lone marker on a
site nobody measured, a surface that pins nothing) keeps ``high_uncertainty``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from annotator.annotation.settings import AnnotateSettings
from annotator.annotation.site_trust import site_errors
from annotator.dataset import Dataset
from annotator.dataset.figures import Reprojection
from annotator.dataset.flags import Flag, sort_flags
from annotator.dataset.records import InstanceAnnotation
from annotator.noise import NOISE
from annotator.pnp import Observation, reprojection_errors, rms_uncertainty
from annotator.refinement import (
    DepthTerm,
    RefineSettings,
    Residuals,
    measured_points,
    refine_instance,
)
from annotator.refinement.depth import Known, KnownCasts, pose_covariance
from annotator.rendering.raycast import PlacedMesh


def refine_few_marker_poses(
    ds: Dataset,
    instances: list[InstanceAnnotation],
    observations: dict[tuple[str, str], list[Observation]],
    depth: np.ndarray | None,
    settings: AnnotateSettings,
    casts: KnownCasts | None = None,
) -> int:
    """Refine, in place, the poses of ``instances`` on at most
    ``settings.refine_max_markers`` marker ids against ``depth`` (see the module docstring);
    ``observations`` are each instance's markers as detected. ``casts``: the instances'
    casts that their visibility made (at ``settings.visibility_step``, see
    :func:`annotator.occlusion.scene_visibility`'s ``memo``): their rays are not cast again
    for the measured points. How many poses changed."""
    cam = ds.rig.depth_camera
    if depth is None or cam is None or settings.refine_max_markers <= 0:
        return 0
    placed = [PlacedMesh(ds.objects[r.object].mesh, r.T) for r in instances]
    changed = 0
    known = None if casts is None else Known(casts, settings.visibility_step)
    rs = RefineSettings(
        margin_px=-settings.refine_inner_px, depth_offset_sigma_mm=settings.depth_bias_mm
    )
    for k, r in enumerate(instances):
        if len(r.marker_ids()) > settings.refine_max_markers:
            continue
        if not refinable(r):
            continue
        used = _used(ds, r, observations.get((r.object, r.instance), []))
        if not used or all(o.soft for o in used):
            continue
        model = ds.objects[r.object]
        others = placed[:k] + placed[k + 1 :]
        points = measured_points(cam, depth, model.mesh, r.T, others, rs, known)
        term = DepthTerm(model.mesh, points, cam.rig_T_cam[:3, 3])
        result = refine_instance(
            model.mesh,
            r.T,
            depth_camera=cam,
            depth=depth,
            others=others,
            cameras=ds.rig.cameras,
            observations=used,
            settings=rs,
            term=term,
        )
        if not _better(result.converged, result.before, result.after, settings):
            continue
        term.offset = result.depth_offset_mm  # (what it holds already: it converged)
        sites = site_errors(model, r.instance, used, settings)
        cov = pose_covariance(
            result.T,
            depth=term,
            cameras=ds.rig.cameras,
            observations=used,
            site_sigmas=sites.taken,
            fitted_sites=sites.fitted,
            noise=replace(
                NOISE,
                depth_correlation=settings.depth_correlation,
                depth_bias_mm=settings.depth_bias_mm,
            ),
            settings=rs,
        )
        _update(ds, r, result.T, used, cov, settings)
        placed[k] = PlacedMesh(model.mesh, result.T)
        changed += 1
    return changed


def refinable(r: InstanceAnnotation) -> bool:
    """Whether the depth may refine ``r``: it has a depth check, it overlaps no other copy,
    and the depth does not contradict it, unless it is the lone marker's ``ambiguous`` flip
    (which the depth settles; the pose keeps its ``ambiguous`` flag)."""
    if r.depth is None or Flag.OVERLAP in r.flags:
        return False
    return Flag.DEPTH_DISAGREEMENT not in r.flags or Flag.AMBIGUOUS in r.flags


def _used(ds: Dataset, r: InstanceAnnotation, obs: Sequence[Observation]) -> list[Observation]:
    """The observations the consensus used for ``r`` (one per camera and marker id)."""
    names = [c.name for c in ds.rig.cameras]
    keep = {(names.index(c), int(i)) for c, m in r.markers.items() if c in names for i in m.used}
    out: dict[tuple[int, int], Observation] = {}
    for o in obs:
        key = (o.camera, o.marker_id)
        if key in keep and key not in out:
            out[key] = o
    return list(out.values())


def _better(converged: bool, before: Residuals, after: Residuals, s: AnnotateSettings) -> bool:
    """The refined pose is kept: converged, more and closer measured points on its
    surface, its markers within their noise (at most ``refine_marker_px`` RMS more than
    before, and not ``high_residual``)."""
    if not converged or before.depth_rms_mm is None or after.depth_rms_mm is None:
        return False
    if before.marker_rms_px is None or after.marker_rms_px is None:
        return False
    return (
        (after.depth_inliers or 0.0) >= (before.depth_inliers or 0.0)
        and after.depth_rms_mm < before.depth_rms_mm
        and after.marker_rms_px <= before.marker_rms_px + s.refine_marker_px
        and after.marker_rms_px <= s.high_residual_px
    )


def _update(
    ds: Dataset,
    r: InstanceAnnotation,
    T: np.ndarray,
    used: list[Observation],
    cov: np.ndarray,
    s: AnnotateSettings,
) -> None:
    """Give ``r`` the refined pose, its reprojection and uncertainty, and the flag it earns
    (depth agreement and occlusion are computed again afterwards, with the whole scene)."""
    cams = ds.rig.cameras
    model = ds.objects[r.object]
    r.R, r.t = T[:3, :3].copy(), T[:3, 3].copy()
    err = reprojection_errors(cams, used, T)
    per_cam = {}
    for j in sorted({o.camera for o in used}):
        e = err[[i for i, o in enumerate(used) if o.camera == j]]
        per_cam[cams[j].name] = round(float(np.sqrt(np.mean(e**2))), 4)
    rms = float(np.sqrt(np.mean(err**2)))
    r.reprojection = Reprojection(round(rms, 4), round(float(np.max(err)), 4), per_cam)
    unc = rms_uncertainty(model.mesh.moments, T[:3, :3], cov)
    r.uncertainty_mm = round(unc, 4) if np.isfinite(unc) else None
    flags = [f for f in r.flags if f not in (Flag.HIGH_UNCERTAINTY, Flag.HIGH_RESIDUAL)]
    if rms > s.high_residual_px:
        flags.append(Flag.HIGH_RESIDUAL)
    if not unc < s.high_uncertainty_fraction * model.mesh.moments.diameter:
        flags.append(Flag.HIGH_UNCERTAINTY)
    r.flags = sort_flags(flags)
