"""Annotating one scene: detection in every camera, consensus per instance, refinement, trust,
and the scene's completeness.

Robust consensus: every camera's candidate poses (see :mod:`annotator.pnp`) are scored by how
many of the instance's markers, in all cameras, they reproject within ``inlier_px``; the best
is refined on its inliers, all markers are re-tested against the refined pose, and refined
again. Markers left out are *rejected* (a misread id, a marker glued elsewhere, a false
detection). An id seen twice in one image keeps the detection consistent with the rest.

Blurred markers (see :mod:`annotator.detection.deblur`) come in two ways, both held to the
support of others: an id read only through the blur model (*soft*) poses an instance only when
at least two soft observations (two markers, or one marker in two cameras) agree on the pose;
and once an instance is posed, each of its markers that should be visible in a camera where it
was not read is looked for among the unread candidate squares: a square within 2.5 px (or
12% of its side) of the projected marker, whose bits differ from the marker's in at most 2,
is *recovered*. Recovered markers are listed as such in annotation.json.
"""

from __future__ import annotations

import functools
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from annotator.annotation import FLAGS
from annotator.annotation.completeness import (
    CompletenessSettings,
    exposure,
    find_regions,
    mean_silhouette_mm2,
    quality_warnings,
    support_depth,
    unexplained_mask,
)
from annotator.dataset import Dataset, InstancePose, Scene
from annotator.dataset.annotation import InstanceAnnotation, SceneAnnotation, SceneWarning
from annotator.detection import MarkerDetector
from annotator.detection.aruco import ImageReading
from annotator.io.images import to_gray8
from annotator.markers.texture import marker_bits
from annotator.pnp import (
    Observation,
    iter_candidate_poses,
    refine_pose,
    reprojection_errors,
    rms_uncertainty,
)
from annotator.pnp.multiview import lone_marker_poses
from annotator.symmetry.space import MATCH_THRESHOLD_FRACTION


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
    completeness: CompletenessSettings = field(default_factory=CompletenessSettings)


@dataclass
class InstanceResult:
    object: str
    instance: str
    T: np.ndarray
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class SceneResult:
    """What annotating a scene gives: the annotation.json record and the unexplained-depth
    mask (uint8, 255 = unexplained, on the depth camera's grid), or None without depth."""

    annotation: SceneAnnotation
    unexplained: np.ndarray | None


def annotate_scene(
    ds: Dataset,
    scene: Scene,
    detector: MarkerDetector,
    *,
    settings: Settings = Settings(),
) -> SceneResult:
    """Pose every instance with detected markers, and check the scene's completeness."""
    cams = ds.rig.cameras
    grays = [to_gray8(scene.read_image(cam)) for cam in cams]
    readings = [detector.read(g) for g in grays]
    table = ds.marker_table
    unknown: dict[str, list[int]] = {}
    duplicates: dict[str, list[int]] = {}
    per_instance: dict[tuple[str, str], list[Observation]] = defaultdict(list)
    for j, reading in enumerate(readings):
        counts: dict[int, int] = defaultdict(int)
        for d in reading.markers:
            counts[d.id] += 1
        for d in reading.markers:
            ref = table.get(d.id)
            if ref is None:
                if not d.soft:  # a soft reading of an unknown id is most likely a misreading
                    unknown.setdefault(cams[j].name, []).append(d.id)
                continue
            if counts[d.id] > 1 and d.id not in duplicates.get(cams[j].name, []):
                duplicates.setdefault(cams[j].name, []).append(d.id)
            X = ds.objects[ref.object].site_corners(ref.instance)[ref.site]
            per_instance[(ref.object, ref.instance)].append(
                Observation(j, d.id, X, d.corners, soft=d.soft)
            )
    results: list[InstanceResult] = []
    for (obj, inst), obs in sorted(per_instance.items()):
        r = _pose_instance(ds, obj, inst, obs, settings)
        if r is not None and _recover_markers(ds, r, obs, readings, grays, detector):
            r = _pose_instance(ds, obj, inst, obs, settings) or r
        if r is not None:
            results.append(r)
    _flag_overlaps(ds, results)
    depth = scene.read_depth(ds.rig)
    renders: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    _add_visibility(ds, results, depth, settings, renders)
    # A pose resting on blurred readings alone is kept only if the measured depth agrees
    # (or, without depth, two different markers do): blur can misread a marker the same way
    # in both cameras. Its markers are then listed as unconfirmed; a part really there shows
    # as unexplained depth.
    doubtful = [r for r in results if not _supported(r, depth is not None)]
    unconfirmed: dict[str, list[int]] = {}
    if doubtful:
        results = [r for r in results if not any(r is d for d in doubtful)]
        for r in doubtful:
            for cam_name, m in r.extra["markers"].items():
                unconfirmed.setdefault(cam_name, []).extend(m["used"])
        renders = {}
        _add_visibility(ds, results, depth, settings, renders)
    instances = [
        InstanceAnnotation.from_pose(
            InstancePose(r.object, r.instance, r.T[:3, :3], r.T[:3, 3], r.extra)
        )
        for r in results
    ]
    quality = {
        cam.name: {
            "edge_blur_px": None if reading.blur_px is None else round(reading.blur_px, 2),
            **dict(zip(("median", "saturated"), (round(v, 4) for v in exposure(gray)))),
        }
        for cam, reading, gray in zip(cams, readings, grays)
    }
    warnings = [SceneWarning.from_json(w) for w in quality_warnings(quality, settings.completeness)]
    if not any(r.markers for r in readings):
        warnings.insert(0, SceneWarning("no_markers", "no marker detected in any camera"))
    mask = None
    if depth is not None and ds.rig.depth is not None:
        depth_index = [c.name for c in cams].index(ds.rig.depth.camera)
        found, mask = unexplained_depth(
            ds,
            depth,
            renders,
            disagreeing=[k for k, r in enumerate(results) if _owns_its_region(r)],
            unread=readings[depth_index].unread,
            settings=settings,
        )
        if found is not None:
            warnings.append(found)
    annotation = SceneAnnotation(
        instances=instances,
        warnings=warnings,
        image_quality=quality,
        unknown_markers=unknown,
        unconfirmed_markers={c: sorted(set(v)) for c, v in unconfirmed.items()},
        duplicates=duplicates,
        unexplained_mask=UNEXPLAINED_MASK if mask is not None and mask.any() else None,
    )
    return SceneResult(annotation, mask)


#: Below this depth agreement a pose on one marker id is contradicted by the depth.
CONTRADICTED = 0.3


def _supported(r: InstanceResult, with_depth: bool) -> bool:
    """False for a pose on blurred readings only that the depth does not confirm."""
    markers = r.extra["markers"].values()
    if not all(set(m["used"]) <= set(m.get("recovered", [])) for m in markers):
        return True
    if with_depth and r.extra["depth"] is not None:
        return "depth_disagreement" not in r.extra["flags"]
    return len({i for m in markers for i in m["used"]}) >= 2


def _owns_its_region(r: InstanceResult) -> bool:
    """A pose flagged ``depth_disagreement`` that still explains its part: on several
    markers, or not contradicted outright. (A single marker id whose pose the depth
    contradicts may be a misread or stray marker: the region stays reported.)"""
    if "depth_disagreement" not in r.extra["flags"]:
        return False
    ids = {i for m in r.extra["markers"].values() for i in m["used"]}
    depth = r.extra["depth"]
    return len(ids) > 1 or depth is None or depth["agreement"] >= CONTRADICTED


#: File name of the unexplained-depth mask, beside annotation.json.
UNEXPLAINED_MASK = "unexplained.png"


def _recover_markers(
    ds: Dataset,
    r: InstanceResult,
    obs: list[Observation],
    readings: list[ImageReading],
    grays: list[np.ndarray],
    detector: MarkerDetector,
) -> bool:
    """Add to ``obs`` the markers of a posed instance found among the unread candidate
    squares where the pose puts them (see the module docstring); True if any was."""
    model = ds.objects[r.object]
    inst = model.instance(r.instance)
    seen = {(o.camera, o.marker_id) for o in obs}
    added = False
    n_sites = len(inst.marker_ids)
    X_all = model.site_corners(inst.name)[:n_sites]
    for j, (cam, reading) in enumerate(zip(ds.rig.cameras, readings)):
        if len(reading.unread) == 0:
            continue
        centres = reading.unread.mean(axis=1)
        T = cam.cam_T_rig @ r.T
        C_all = X_all @ T[:3, :3].T + T[:3, 3]  # (S, 4, 3), all sites at once
        normal = np.cross(C_all[:, 3] - C_all[:, 0], C_all[:, 1] - C_all[:, 0])
        centre = C_all.mean(axis=1)
        facing = (C_all[..., 2].min(axis=1) > 0) & (
            -(normal * centre).sum(1)
            >= RECOVER_COS * np.linalg.norm(normal, axis=1) * np.linalg.norm(centre, axis=1)
        )  # in front of the camera, seen within 75 degrees of face-on
        for site in np.flatnonzero(facing):
            mid = inst.marker_ids[site]
            if (j, mid) in seen:
                continue
            X = X_all[site]
            uv = cam.project(C_all[site])
            side = float(np.linalg.norm(uv - np.roll(uv, 1, axis=0), axis=1).mean())
            near = np.flatnonzero(np.linalg.norm(centres - uv.mean(axis=0), axis=1) < 0.35 * side)
            for k in near:
                quads = [np.roll(reading.unread[k], m, axis=0) for m in range(4)]
                m = int(np.argmin([np.abs(q - uv).max() for q in quads]))
                if np.linalg.norm(quads[m] - uv, axis=1).max() > max(2.5, 0.12 * side):
                    continue
                expected = np.rot90(_inner_bits(ds.dictionary, mid), m)
                if int(np.sum(reading.unread_bits[k] != expected)) > RECOVER_MAX_BIT_ERRORS:
                    continue
                corners = detector.refine(grays[j], quads[m][None])[0]
                obs.append(Observation(j, mid, X, corners, soft=True))
                seen.add((j, mid))
                added = True
                break
    return added


#: Recovery: markers seen within 75 degrees of face-on; at most 2 of 16 bits may differ.
RECOVER_COS = float(np.cos(np.radians(75.0)))
RECOVER_MAX_BIT_ERRORS = 2


@functools.lru_cache(maxsize=4096)
def _inner_bits(dictionary: str, marker_id: int) -> np.ndarray:
    """The marker's inner bits (True = white), rows and columns as printed."""
    return marker_bits(dictionary, marker_id)[1:-1, 1:-1] > 127


def render_poses(
    ds: Dataset, poses: list[InstancePose], *, step: int = 2
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """What each camera sees of ``poses``: per camera, the depth of the nearest instance and
    its index at every ``step``-th pixel (see :func:`annotator.occlusion.scene_visibility`)."""
    from annotator.occlusion import scene_visibility

    renders: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    if poses:
        meshes = [ds.objects[p.object].mesh for p in poses]
        scene_visibility(ds.rig, meshes, [p.T for p in poses], step=step, renders=renders)
    return renders


def unexplained_depth(
    ds: Dataset,
    depth: np.ndarray,
    renders: dict[str, tuple[np.ndarray, np.ndarray]],
    *,
    disagreeing: Sequence[int] = (),
    unread: np.ndarray | None = None,
    settings: Settings = Settings(),
) -> tuple[SceneWarning | None, np.ndarray]:
    """The ``unexplained_depth`` warning (or None) and the full-resolution mask (uint8, 255
    where a reported region is), for a depth map (mm) and the posed instances as rendered
    (:func:`render_poses`, on the grid of ``settings.visibility_step``).

    Args:
        disagreeing: Indices of instances flagged ``depth_disagreement``: a region lying
            mostly on one's rendered silhouette is that instance's (a part with a doubtful
            pose, already flagged), not a part without a pose.
        unread: Candidate squares (K, 4, 2) of the depth camera that could not be read: those
            on a region are listed with it.
    """
    cs = settings.completeness
    step = settings.visibility_step
    cam = ds.rig.depth_camera
    assert cam is not None, "unexplained_depth needs a dataset with depth"
    rays = cam.pixel_rays(step)
    measured = depth[::step, ::step]
    if cam.name in renders:
        rendered, front = renders[cam.name]
    else:
        rendered = np.full(measured.shape, np.inf, np.float32)
        front = np.full(measured.shape, -1, np.int32)
    full_bg = ds.background_depth
    if full_bg is not None:
        background = _filled(full_bg, step)
        source = "the dataset's background depth"
    else:
        background = support_depth(measured, rays)
        source = "the support plane found in the depth"
    mask = unexplained_mask(measured, background, rendered, cs)
    z = float(np.nanmedian(measured)) if np.isfinite(measured).any() else 1000.0
    f2 = float(cam.K[0, 0] * cam.K[1, 1]) / (z * z)
    areas = [_silhouette_mm2(o.mesh) * f2 for o in ds.objects.values()]
    min_px = cs.min_region_fraction * min(areas) if areas else np.inf
    regions, kept = find_regions(
        mask,
        measured,
        step=step,
        min_pixels=min_px,
        skip_border_bands=full_bg is None,
        owned=np.isin(front, list(disagreeing)),
    )
    full = np.repeat(np.repeat(kept, step, axis=0), step, axis=1)[: cam.height, : cam.width]
    full_mask = (full * 255).astype(np.uint8)
    if not regions:
        return None, full_mask
    for q in unread if unread is not None else ():
        x, y = q.mean(axis=0)
        if 0 <= x < cam.width and 0 <= y < cam.height and full[int(y), int(x)]:
            for reg in regions:
                x0, y0, x1, y1 = reg.box
                if x0 <= x < x1 and y0 <= y < y1:
                    reg.unread_markers.append((float(x), float(y)))
                    break
    n_unread = sum(len(r.unread_markers) for r in regions)
    message = (
        f"{len(regions)} region(s) of measured depth in front of {source} that no pose explains "
        f"({sum(r.pixels for r in regions)} px)"
        + (f", with {n_unread} unread marker square(s)" if n_unread else "")
        + ": a part may have no pose"
    )
    warning = SceneWarning(
        "unexplained_depth", message, {"regions": [r.to_json() for r in regions]}
    )
    return warning, full_mask


_FILLED: dict[int, tuple[np.ndarray, int, np.ndarray]] = {}


def _filled(depth: np.ndarray, step: int) -> np.ndarray:
    """The background depth on the grid of every ``step``-th pixel, its holes filled from the
    nearest measured sample; computed once per background map (it is the same every scene)."""
    hit = _FILLED.get(id(depth))
    if hit is not None and hit[0] is depth and hit[1] == step:
        return hit[2]
    grid = depth[::step, ::step]
    holes = ~np.isfinite(grid)
    if holes.any() and not holes.all():
        _, (iy, ix) = ndimage.distance_transform_edt(holes, return_indices=True)
        grid = grid[iy, ix]
    _FILLED.clear()
    _FILLED[id(depth)] = (depth, step, grid)
    return grid


@functools.lru_cache(maxsize=64)
def _silhouette_cached(digest: bytes, vertices: bytes) -> float:
    return mean_silhouette_mm2(np.frombuffer(vertices).reshape(-1, 3))


def _silhouette_mm2(mesh) -> float:
    return _silhouette_cached(mesh.digest, mesh.vertices.tobytes())


def _pose_instance(
    ds: Dataset, obj: str, inst: str, obs: list[Observation], s: Settings
) -> InstanceResult | None:
    """Pose one instance from its observations (see the module docstring)."""
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
    if all(o.soft for o in used) and len({(o.camera, o.marker_id) for o in used}) < 2:
        return None  # one blurred reading alone is not evidence enough
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
    # A blurred reading that disagrees is a misreading, not a marker glued elsewhere.
    rejected = [k for k in range(len(obs)) if k not in inliers and not obs[k].soft]
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
        if o.soft and k in inliers:
            entry.setdefault("recovered", []).append(o.marker_id)
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
        for k in np.flatnonzero(D.min(axis=1) < MATCH_THRESHOLD_FRACTION * space.diameter):
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
    ds: Dataset,
    results: list[InstanceResult],
    depth: np.ndarray | None,
    s: Settings,
    renders: dict[str, tuple[np.ndarray, np.ndarray]],
) -> None:
    """Depth agreement and occlusion rates of the posed instances (all instances as
    occluders); ``renders`` receives what each camera sees of the posed instances."""
    if not results:
        return
    from annotator.occlusion import scene_visibility

    for r in results:  # recomputed below, from these poses
        r.extra["flags"] = [f for f in r.extra["flags"] if f != "depth_disagreement"]
    meshes = [ds.objects[r.object].mesh for r in results]
    vis = scene_visibility(
        ds.rig,
        meshes,
        [r.T for r in results],
        depth=depth,
        step=s.visibility_step,
        renders=renders,
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
        assert cv.depth_median_abs_mm is not None  # set together with depth_agreement
        r.extra["depth"] = {
            "agreement": round(cv.depth_agreement, 4),
            "median_abs_mm": round(cv.depth_median_abs_mm, 3),
            "pixels": cv.depth_pixels,
        }
        if cv.depth_agreement < s.depth_min_agreement:
            r.extra["flags"].append("depth_disagreement")
    for r in results:
        r.extra["flags"] = [f for f in FLAGS if f in r.extra["flags"]]
