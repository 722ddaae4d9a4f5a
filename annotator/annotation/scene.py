"""Annotating one scene: detection in every camera, consensus per instance, refinement, trust.

Robust consensus: every camera's candidate poses (see :mod:`annotator.pnp`) are scored by how
many of the instance's markers, in all cameras, they reproject within ``inlier_px``; the best
is refined on its inliers, all markers are re-tested against the refined pose, and refined
again. Markers left out are *rejected* (a misread id, a marker glued elsewhere, a false
detection). An id seen twice in one image keeps the detection consistent with the rest.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from annotator.annotation import FLAGS
from annotator.dataset import Dataset, InstancePose, Scene
from annotator.detection import Detection, MarkerDetector
from annotator.pnp import (
    Observation,
    iter_candidate_poses,
    refine_pose,
    reprojection_errors,
    rms_uncertainty,
)
from annotator.pnp.multiview import lone_marker_poses


@dataclass(frozen=True)
class Settings:
    """Thresholds of the annotation (px, mm, ratios)."""

    inlier_px: float = 4.0
    final_inlier_px: float = 2.5
    high_residual_px: float = 1.0
    ambiguity_ratio: float = 3.0
    high_uncertainty_fraction: float = 0.01
    depth_tolerance_mm: float = 3.0
    depth_min_agreement: float = 0.6
    #: Occlusion and depth agreement from every 2nd pixel of every 2nd row (4x fewer rays;
    #: rates within 0.2% on the sample scenes); ``annotator occlusion`` gives the exact rates.
    visibility_step: int = 2


@dataclass
class InstanceResult:
    object: str
    instance: str
    T: np.ndarray
    extra: dict[str, Any] = field(default_factory=dict)


def detect_scene(ds: Dataset, scene: Scene, detector: MarkerDetector) -> list[list[Detection]]:
    """Detections per rig camera (UserError if an image is missing, corrupt or mis-sized)."""
    return [detector.detect(scene.read_image(cam)) for cam in ds.rig.cameras]


def annotate_scene(
    ds: Dataset,
    scene: Scene,
    detector: MarkerDetector,
    *,
    settings: Settings = Settings(),
) -> tuple[list[InstancePose], dict[str, Any]]:
    """Pose every instance with detected markers; return the poses and top-level fields."""
    cams = ds.rig.cameras
    detections = detect_scene(ds, scene, detector)
    table = ds.marker_table
    unknown: dict[str, list[int]] = {}
    duplicates: dict[str, list[int]] = {}
    per_instance: dict[tuple[str, str], list[Observation]] = defaultdict(list)
    for j, dets in enumerate(detections):
        counts: dict[int, int] = defaultdict(int)
        for d in dets:
            counts[d.id] += 1
        for d in dets:
            ref = table.get(d.id)
            if ref is None:
                unknown.setdefault(cams[j].name, []).append(d.id)
                continue
            if counts[d.id] > 1 and d.id not in duplicates.get(cams[j].name, []):
                duplicates.setdefault(cams[j].name, []).append(d.id)
            X = ds.objects[ref.object].markers.corners[ref.site]
            per_instance[(ref.object, ref.instance)].append(Observation(j, d.id, X, d.corners))
    results: list[InstanceResult] = []
    for (obj, inst), obs in sorted(per_instance.items()):
        r = _pose_instance(ds, obj, inst, obs, settings)
        if r is not None:
            results.append(r)
    _flag_overlaps(ds, results)
    depth = scene.read_depth(ds.rig)
    _add_visibility(ds, results, depth, settings)
    poses = [InstancePose(r.object, r.instance, r.T[:3, :3], r.T[:3, 3], r.extra) for r in results]
    warnings = []
    if not any(detections):
        warnings.append("no marker detected in any camera")
    top = {"unknown_markers": unknown, "duplicates": duplicates, "warnings": warnings}
    return poses, top


def _pose_instance(
    ds: Dataset, obj: str, inst: str, obs: list[Observation], s: Settings
) -> InstanceResult | None:
    cams = ds.rig.cameras
    best, best_key = None, None
    everything = len({(o.camera, o.marker_id) for o in obs})
    for T in iter_candidate_poses(cams, obs):
        err = reprojection_errors(cams, obs, T)
        inl = _dedupe(obs, err, s.inlier_px)
        key = (len(inl), -float(np.sum(np.minimum(err, s.inlier_px))))
        if best_key is None or key > best_key:
            best, best_key = T, key
        if len(inl) == everything:
            break  # explains every marker: no other hypothesis can do better after refinement
    if best is None:
        return None
    inliers = _dedupe(obs, reprojection_errors(cams, obs, best), s.inlier_px)
    if not inliers:
        return None
    est = refine_pose(cams, [obs[k] for k in inliers], best)
    for _ in range(2):
        err = reprojection_errors(cams, obs, est.T)
        thr = max(s.final_inlier_px, 4.0 * est.sigma_px)
        new = _dedupe(obs, err, thr)
        if not new:
            break
        if new == inliers:
            break
        inliers = new
        est = refine_pose(cams, [obs[k] for k in inliers], est.T)
    used = [obs[k] for k in inliers]
    err = reprojection_errors(cams, obs, est.T)
    flags: list[str] = []
    views = sorted({o.camera for o in used})
    if len(views) < 2:
        flags.append("single_view")
    if _ambiguous(cams, used, est.T, s):
        flags.append("ambiguous")
    used_err = err[inliers]
    if float(np.sqrt(np.mean(used_err**2))) > s.high_residual_px:
        flags.append("high_residual")
    rejected = [k for k in range(len(obs)) if k not in inliers]
    if rejected:
        flags.append("rejected_markers")
    model = ds.objects[obj]
    unc = rms_uncertainty(model.mesh.moments, est.T[:3, :3], est.covariance)
    if not unc < s.high_uncertainty_fraction * model.mesh.moments.diameter:
        flags.append("high_uncertainty")
    markers: dict[str, dict[str, list[int]]] = {}
    for k, o in enumerate(obs):
        entry = markers.setdefault(cams[o.camera].name, {"used": [], "rejected": []})
        entry["used" if k in inliers else "rejected"].append(o.marker_id)
    per_cam = {}
    for j in views:
        e = [err[k] for k in inliers if obs[k].camera == j]
        per_cam[cams[j].name] = round(float(np.sqrt(np.mean(np.square(e)))), 4)
    extra: dict[str, Any] = {
        "uncertainty_mm": round(unc, 4) if np.isfinite(unc) else None,
        "reprojection_px": {
            "rms": round(float(np.sqrt(np.mean(used_err**2))), 4),
            "max": round(float(np.max(used_err)), 4),
            "per_camera": per_cam,
        },
        "markers": markers,
        "views": len(views),
        "depth": None,
        "occlusion": None,
        "flags": flags,
    }
    return InstanceResult(obj, inst, est.T, extra)


def _flag_overlaps(ds: Dataset, results: list[InstanceResult]) -> None:
    """Two copies of a part cannot be in the same place: when two instances' poses are within
    10% of the diameter (the paper's match threshold), a marker was glued on or read as the
    wrong copy. Both are flagged ``overlap``."""
    from annotator.symmetry import PoseSpace

    for obj in {r.object for r in results}:
        mine = [r for r in results if r.object == obj]
        if len(mine) < 2:
            continue
        model = ds.objects[obj]
        space = PoseSpace.from_moments(model.mesh.moments, model.symmetry)
        R = np.stack([r.T[:3, :3] for r in mine])
        t = np.stack([r.T[:3, 3] for r in mine])
        D = space.distance_matrix(R, t, R, t)
        np.fill_diagonal(D, np.inf)
        for k in np.flatnonzero(D.min(axis=1) < 0.1 * space.diameter):
            mine[k].extra["flags"].append("overlap")


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


def _ambiguous(cams, used: list[Observation], T: np.ndarray, s: Settings) -> bool:
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


def _add_visibility(
    ds: Dataset, results: list[InstanceResult], depth: np.ndarray | None, s: Settings
) -> None:
    """Depth agreement and occlusion rates of the posed instances (all instances as occluders)."""
    if not results:
        return
    from annotator.occlusion import scene_visibility

    meshes = [ds.objects[r.object].mesh for r in results]
    vis = scene_visibility(
        ds.rig, meshes, [r.T for r in results], depth=depth, step=s.visibility_step
    )
    for r, v in zip(results, vis):
        r.extra["occlusion"] = {
            "rate": round(v.occlusion, 4),
            "per_camera": {c.camera: round(c.occlusion, 4) for c in v.cameras},
        }
    depth_cam = ds.rig.depth.camera if ds.rig.depth is not None else None
    for r, v in zip(results, vis):
        cv = next((c for c in v.cameras if c.camera == depth_cam), None)
        if depth is None or cv is None or cv.depth_agreement is None or cv.depth_pixels < 20:
            continue
        r.extra["depth"] = {
            "agreement": round(cv.depth_agreement, 4),
            "median_abs_mm": round(cv.depth_median_abs_mm, 3),
            "pixels": cv.depth_pixels,
        }
        if cv.depth_agreement < s.depth_min_agreement:
            r.extra["flags"].append("depth_disagreement")
    for r in results:
        r.extra["flags"] = [f for f in FLAGS if f in r.extra["flags"]]
