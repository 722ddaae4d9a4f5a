"""From a dataset to measured sites and back: the markers of every annotated scene found again,
gathered per instance, solved (:func:`annotator.sites.solve.solve_sites`), judged, and written
into object.yaml.

What is used of a scene: its annotation.json (the poses, and per camera the markers annotate
used or rejected: a sticker glued a millimetre or two off is rejected by annotate's consensus
and is just what must be measured; the solve leaves out what does not fit the pose at all),
its images (the markers are detected again for their corners) and its depth map (the
instance's visible surface, where the measured depth lies within 3 mm of the pose's rendered
depth).

The prior on the corrections is the dataset's own gluing spread (empirical Bayes): a first
solve with a wide prior (1 mm, 3 degrees) gives every marker's correction and its noise; the
spread of the corrections less that of the noise is how far gluing moved the markers; the
second, final solve uses it. Markers on their sites (a spread near zero) then keep their
layout; stickers glued by hand get what the data say. The report gives the spread.

A marker is *flagged* when its correction moves it more than ``max_move_mm``, or when, read in
two scenes or more, it fits the instance's pose in fewer than half of them: it is probably
glued on another site, or on another copy of the part.
"""

from __future__ import annotations

import functools
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from annotator.annotation.visibility import render_poses
from annotator.dataset import Dataset, Scene, cached_dataset
from annotator.dataset.model import Capture, Frame
from annotator.dataset.records import SceneAnnotation
from annotator.dataset.write import sites_to_yaml
from annotator.detection import MarkerDetector
from annotator.errors import UserError
from annotator.io.documents import parse_yaml, read_text
from annotator.io.images import to_gray8
from annotator.markers.glue import apply_corrections
from annotator.sites.solve import (
    ClosestPoints,
    InstanceData,
    MarkerView,
    SiteSettings,
    SiteSolution,
    solve_sites,
)

#: Measured depth within this of the rendered depth (mm) is the instance's surface.
SURFACE_MM = 3.0
#: Depth points per instance and scene, at most (evenly spread over its visible pixels).
DEPTH_POINTS = 400
#: Pixels of the silhouette's edge left out of the depth points.
EDGE_PIXELS = 6


@dataclass
class InstanceSites:
    """One instance's measured sites and what to tell the user about them.

    Attributes:
        object, instance: Which part.
        marker_ids: Its ids, ``marker_ids[k]`` on site ``k``.
        solution: The solve's outcome (corrections, uncertainties, poses, residuals).
        sites: (S, 4, 3) the measured corners: the layout moved by the corrections.
        flags: Site index -> why the marker is flagged.
        read: Site index -> scenes in which the marker was read.
    """

    object: str
    instance: str
    marker_ids: tuple[int, ...]
    solution: SiteSolution
    sites: np.ndarray
    flags: dict[int, str] = field(default_factory=dict)
    read: dict[int, int] = field(default_factory=dict)

    @property
    def key(self) -> str:
        return f"{self.object}/{self.instance}"

    def to_json(self) -> dict[str, Any]:
        sol = self.solution
        markers = []
        for k, mid in enumerate(self.marker_ids):
            du, dv, dt = sol.corrections[k]
            su, sv, st = sol.std[k]
            markers.append(
                {
                    "site": k,
                    "id": int(mid),
                    "scenes": int(sol.seen[k]),
                    "du_mm": round(float(du), 4),
                    "dv_mm": round(float(dv), 4),
                    "turn_deg": round(float(np.degrees(dt)), 3),
                    "std": None
                    if not np.isfinite(su)
                    else [
                        round(float(su), 4),
                        round(float(sv), 4),
                        round(float(np.degrees(st)), 3),
                    ],
                    "flag": self.flags.get(k),
                }
            )
        return {
            "instance": self.key,
            "scenes": len(sol.poses),
            "markers_used": sol.used,
            "markers_left_out": sol.left_out,
            "corner_rms_px": [round(sol.rms_before, 4), round(sol.rms_after, 4)],
            "unobservable": sol.unobservable,
            "markers": markers,
        }


def measure_instances(
    ds: Dataset,
    scenes: Sequence[Scene | Frame],
    detections: dict[str, list[tuple[int, int, np.ndarray]]],
    *,
    settings: SiteSettings | None = None,
    annotations: dict[str, SceneAnnotation] | None = None,
    spread: tuple[float, float] | None = None,
) -> tuple[list[InstanceSites], tuple[float, float] | None]:
    """Measure every instance seen in ``scenes`` (which must carry an annotation.json, or be
    a sequence's frames given in ``annotations``), and the gluing spread (mm, degrees; None if
    no marker was seen) used as the prior.

    Args:
        detections: Per scene id, the markers read in it: ``(camera index, id, corners)``
            (see :class:`DetectJob`).
        annotations: Per scene id, the poses and markers to use instead of the scene's
            annotation.json (a scene annotated again with sites measured before).
        spread: The gluing spread to use as the prior, known already (an earlier round's):
            one solve per instance instead of two.
    """
    settings = settings or SiteSettings()
    gathered: dict[tuple[str, str], InstanceData] = {}
    read: dict[tuple[str, str], dict[int, int]] = defaultdict(lambda: defaultdict(int))
    for scene in scenes:
        ann = (annotations or {}).get(scene.id)
        if ann is None:
            ann = (
                SceneAnnotation.read(scene.annotation_path)
                if isinstance(scene, Scene)
                else SceneAnnotation()  # a frame its sequence's solve did not pose
            )
        _gather_scene(ds, scene, ann, detections.get(scene.id, []), gathered, read)
    items = sorted(gathered.items())
    if spread is None:
        solutions = [_solve(ds, key, data, settings) for key, data in items]
        # The prior's width, as gluing spreads the markers of this dataset (empirical
        # Bayes): exact sites then keep their layout, stickers glued by hand get what the
        # data say.
        spread = glue_spread(solutions)
    if spread is not None:
        settings = replace(settings, prior_mm=spread[0], prior_deg=spread[1])
        solutions = [_solve(ds, key, data, settings) for key, data in items]
    out = []
    for ((obj_name, inst_name), data), sol in zip(items, solutions):
        obj = ds.objects[obj_name]
        inst = obj.instance(inst_name)
        sites = apply_corrections(data.layout, sol.corrections)
        result = InstanceSites(obj_name, inst_name, inst.marker_ids, sol, sites)
        for k, views in read[(obj_name, inst_name)].items():
            result.read[k] = views
            if views >= 2 and sol.seen[k] < 0.5 * views:  # once is a misreading, maybe
                how = f"measured from {sol.seen[k]}" if sol.seen[k] else "not measured"
                result.flags[k] = (
                    f"read in {views} scenes, fits the pose in {sol.seen[k]} ({how}): glued "
                    "on another site or another copy?"
                )
        for k in range(len(inst.marker_ids)):
            move = float(np.hypot(*sol.corrections[k, :2]))
            if move > settings.max_move_mm and k not in result.flags:
                result.flags[k] = (
                    f"moved {move:.1f} mm (more than {settings.max_move_mm:g}): glued on "
                    "another site or another copy?"
                )
        out.append(result)
    return out, spread


def _solve(
    ds: Dataset, key: tuple[str, str], data: InstanceData, settings: SiteSettings
) -> SiteSolution:
    obj = ds.objects[key[0]]
    closest = _closest(obj.mesh) if any(len(p) for p in data.depth_points) else None
    return solve_sites(ds.rig.cameras, data, closest, settings=settings)


def glue_spread(solutions: list[SiteSolution]) -> tuple[float, float] | None:
    """How far gluing moved this dataset's markers, per axis (mm) and in turn (degrees):
    the spread of the corrections less that of their measurement noise, over every marker
    seen, at least :data:`MIN_SPREAD`; None when no marker was seen."""
    c = [s.corrections[s.seen > 0] for s in solutions]
    e = [s.std[s.seen > 0] for s in solutions]
    if not any(len(x) for x in c):
        return None
    corr, std = np.concatenate(c), np.nan_to_num(np.concatenate(e))
    mm = np.sqrt(max(float(np.mean(corr[:, :2] ** 2) - np.mean(std[:, :2] ** 2)), 0.0))
    rad = np.sqrt(max(float(np.mean(corr[:, 2] ** 2) - np.mean(std[:, 2] ** 2)), 0.0))
    return max(mm, MIN_SPREAD[0]), max(float(np.degrees(rad)), MIN_SPREAD[1])


#: The narrowest prior (mm, degrees): below it the corrections are noise anyway.
MIN_SPREAD = (0.02, 0.1)


def _gather_scene(
    ds: Dataset,
    scene: Capture,
    ann: SceneAnnotation,
    found: list[tuple[int, int, np.ndarray]],
    gathered: dict[tuple[str, str], InstanceData],
    read: dict[tuple[str, str], dict[int, int]],
) -> None:
    if not ann.instances:
        return
    names = [c.name for c in ds.rig.cameras]
    by_id: dict[tuple[int, int], np.ndarray] = {}
    for j, mid, corners in found:
        by_id.setdefault((j, mid), corners)  # an id seen twice: annotate kept one; so do we
    depth = scene.read_depth(ds.rig)
    surfaces = _surface_points(ds, ann, depth) if depth is not None else {}
    for k, inst in enumerate(ann.instances):
        obj = ds.objects[inst.object]
        if obj.markers is None:
            continue
        ids = obj.instance(inst.instance).marker_ids
        data = gathered.setdefault(
            (inst.object, inst.instance), InstanceData(obj.markers.corners, [], [], [], [])
        )
        view = len(data.poses)
        data.poses.append(inst.T)
        points, rays = surfaces.get(k, (np.zeros((0, 3)), np.zeros((0, 3))))
        data.depth_points.append(points)
        data.depth_rays.append(rays)
        read_here: set[int] = set()
        for camera, uses in inst.markers.items():
            if camera not in names:
                continue
            j = names.index(camera)
            # Those annotate rejected too: a sticker glued a millimetre or two off is
            # rejected by its consensus, and is just what must be measured. The solve leaves
            # out whatever does not fit the pose at all.
            for mid in set(uses.used) | set(uses.rejected):
                seen = by_id.get((j, mid))
                if mid in ids and seen is not None:
                    data.markers.append(MarkerView(view, j, ids.index(mid), seen))
                    read_here.add(ids.index(mid))
        for k in read_here:
            read[(inst.object, inst.instance)][k] += 1


def _surface_points(
    ds: Dataset, ann: SceneAnnotation, depth: np.ndarray, step: int = 2
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per annotated instance (index), measured points of its visible surface and their
    rays (the motion of a point for 1 mm more depth), both in the rig frame."""
    cam = ds.rig.depth_camera
    assert cam is not None
    poses = [i.pose for i in ann.instances]
    rendered, front = render_poses(ds, poses, step=step).get(cam.name, (None, None))
    if rendered is None:
        return {}
    measured = depth[::step, ::step]
    rays = cam.pixel_rays(step)
    with np.errstate(invalid="ignore"):
        near = np.abs(measured - rendered) < SURFACE_MM
    out = {}
    for k in range(len(poses)):
        # Away from the silhouette's edge, where active stereo smears depth across the
        # boundary: there it would pull the pose, and the sites with it.
        inside = ndimage.binary_erosion(front == k, iterations=EDGE_PIXELS // step)
        rows, cols = np.nonzero(near & inside)
        if len(rows) < 10:
            continue
        pick = np.linspace(0, len(rows) - 1, min(DEPTH_POINTS, len(rows))).astype(int)
        rows, cols = rows[pick], cols[pick]
        ray = rays[rows, cols]
        pts = ray * measured[rows, cols][:, None]
        R = cam.rig_T_cam[:3, :3]
        out[k] = (pts @ R.T + cam.rig_T_cam[:3, 3], ray @ R.T)
    return out


_CLOSEST: dict[bytes, ClosestPoints] = {}


def _closest(mesh: Any) -> ClosestPoints:
    """The mesh's closest-point finder, built once per mesh."""
    if mesh.digest not in _CLOSEST:
        _CLOSEST[mesh.digest] = ClosestPoints(mesh.vertices, mesh.faces)
    return _CLOSEST[mesh.digest]


# ---------------------------------------------------------------------------- detection


@dataclass(frozen=True)
class DetectJob:
    """Read the markers of one scene in every camera (a batch job: picklable)."""

    root: str

    def __call__(self, scene_id: str) -> dict[str, Any]:
        ds = cached_dataset(self.root)
        scene = capture(ds, scene_id)
        detector = _detector(ds.dictionary)
        found = []
        for j, cam in enumerate(ds.rig.cameras):
            for d in detector.read(to_gray8(scene.read_image(cam))).markers:
                if d.id in ds.marker_table:
                    found.append((j, int(d.id), np.asarray(d.corners, float)))
        return {"markers": found}


def capture(ds: Dataset, unit: str) -> Capture:
    """What a unit names: a fixed rig's scene, or (``<scene>/<frame>``) a sequence's frame."""
    return ds.frame(unit) if ds.rig.moving and "/" in unit else ds.scene(unit)


def units(ds: Dataset, scenes: list[Scene]) -> list[Scene | Frame]:
    """What the sites are measured on: the scenes, or every frame of the sequences."""
    if not ds.rig.moving:
        return list[Scene | Frame](scenes)
    return [frame for scene in scenes for frame in scene.frames()]


@functools.cache
def _detector(dictionary: str) -> MarkerDetector:
    return MarkerDetector(dictionary)


# ---------------------------------------------------------------------------- object.yaml


def updated_object_yaml(path: Path, measured: list[InstanceSites]) -> tuple[str, str]:
    """object.yaml's text before and after giving the ``measured`` instances their sites
    (every other field kept as it is)."""
    import yaml

    old = read_text(path)
    doc = parse_yaml(old, path)
    if not isinstance(doc, dict) or not isinstance(doc.get("instances"), list):
        raise UserError("has no instances list", path=path)
    by_name = {m.instance: m for m in measured}
    for entry in doc["instances"]:
        m = by_name.get(str(entry.get("name"))) if isinstance(entry, dict) else None
        if m is not None:
            entry["sites"] = sites_to_yaml(m.sites)
            entry["site_scenes"] = [int(n) for n in m.solution.seen]
    new = yaml.safe_dump(doc, sort_keys=False, width=120, default_flow_style=None)
    return old, new
