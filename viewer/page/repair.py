"""The page's repair actions on a scene's poses, over :mod:`annotator.repair`: what R (refine),
A (alternatives), the nudge keys and adding a missing part compute, from a scene's markers as
detected and its depth (:class:`RepairInputs`, made once per scene).

The pose of an instance here is the one the page shows (:attr:`annotator.review.scenes.SceneInfo.poses`,
edits applied); the other posed parts are its neighbours for the refinement.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from annotator.dataset import Dataset, Scene
from annotator.detection import MarkerDetector
from annotator.detection.aruco import ImageReading
from annotator.geometry.transforms import invert
from annotator.io.images import to_gray8
from annotator.rendering.raycast import PlacedMesh
from annotator.repair import (
    Candidate,
    Nudge,
    NudgeKind,
    Refinement,
    alternatives,
    instance_observations,
    nudged,
    refine_instance,
    start_pose,
    used_observations,
)
from annotator.repair.candidates import SAME_FRACTION, pose_distance
from annotator.review import SceneInfo

#: Nudge steps: small and large (the large ones for a part far off).
SMALL_MM, SMALL_DEG = 1.0, 1.0
LARGE_MM, LARGE_DEG = 10.0, 10.0


@functools.cache
def _detector(dictionary: str) -> MarkerDetector:
    return MarkerDetector(dictionary)


@dataclass(frozen=True)
class RepairInputs:
    """A scene's markers as read in every camera, and its depth (mm; None without)."""

    readings: tuple[ImageReading, ...]
    depth: np.ndarray | None

    @classmethod
    def read(cls, ds: Dataset, scene: Scene) -> RepairInputs:
        detector = _detector(ds.dictionary)
        readings = tuple(detector.read(to_gray8(scene.read_image(c))) for c in ds.rig.cameras)
        return cls(readings, scene.read_depth(ds.rig))


def _neighbours(ds: Dataset, info: SceneInfo, key: str) -> list[PlacedMesh]:
    return [
        PlacedMesh(ds.objects[p.object].mesh, p.T)
        for p in info.poses
        if p.key != key and p.object in ds.objects
    ]


def refine(ds: Dataset, info: SceneInfo, key: str, inputs: RepairInputs) -> Refinement:
    """R: the shown pose of ``key`` refined against the depth and its markers."""
    pose = info.pose(key)
    assert pose is not None
    mesh = ds.objects[pose.object].mesh
    obs = instance_observations(ds, inputs.readings, pose.object, pose.instance)
    auto = info.auto_pose(key)
    used = used_observations(ds.rig.cameras, mesh, obs, auto.markers if auto else None)
    return refine_instance(
        mesh,
        pose.T,
        depth_camera=ds.rig.depth_camera,
        depth=inputs.depth,
        others=_neighbours(ds, info, key),
        cameras=ds.rig.cameras,
        observations=used,
    )


def candidates(ds: Dataset, info: SceneInfo, key: str, inputs: RepairInputs) -> list[Candidate]:
    """A: the poses to cycle through, the auto pose first (if there is one), then the other
    candidates from the markers, the best supported first."""
    pose = info.pose(key)
    assert pose is not None
    mesh = ds.objects[pose.object].mesh
    obs = instance_observations(ds, inputs.readings, pose.object, pose.instance)
    found = alternatives(ds.rig.cameras, mesh, obs)
    auto = info.auto_pose(key)
    if auto is None:
        return found
    same = SAME_FRACTION * mesh.moments.diameter
    first = Candidate(auto.T, auto.count("used"), auto.reprojection_rms, "the auto-annotation")
    return [first] + [c for c in found if pose_distance(mesh, c.T, auto.T) >= same]


def nudge(ds: Dataset, info: SceneInfo, key: str, step: Nudge) -> np.ndarray:
    """The shown pose of ``key`` moved by ``step`` along the reference camera's axes: for a
    sequence's frames view (``ds`` the view, :meth:`annotator.review.state.ReviewState.dataset_of`)
    those of the first shown frame's reference camera, the top-left picture, not the scene
    frame's (the first frame's, perhaps not shown and seen from elsewhere)."""
    pose = info.pose(key)
    assert pose is not None
    centroid = ds.objects[pose.object].mesh.moments.centroid
    if not info.shown:
        return nudged(pose.T, step, centroid)
    scene_T_cam = ds.rig.cameras[0].rig_T_cam  # the view's rig frame is the scene frame
    return scene_T_cam @ nudged(invert(scene_T_cam) @ pose.T, step, centroid)


def step_of(kind: NudgeKind, axis: int, sign: int, large: bool) -> Nudge:
    """The nudge of a key: ``kind`` move or turn, small or large."""
    if kind == NudgeKind.MOVE:
        amount = LARGE_MM if large else SMALL_MM
    else:
        amount = LARGE_DEG if large else SMALL_DEG
    return Nudge(kind, axis, sign * amount)


def unposed(ds: Dataset, info: SceneInfo) -> list[str]:
    """The physical instances (object.yaml) with no pose in this scene."""
    posed = {p.key for p in info.poses}
    return [
        f"{name}/{inst.name}"
        for name, obj in ds.objects.items()
        for inst in obj.instances
        if f"{name}/{inst.name}" not in posed
    ]


def start(
    ds: Dataset,
    info: SceneInfo,
    key: str,
    camera: str,
    pixel: tuple[float, float],
    inputs: RepairInputs,
) -> Candidate | None:
    """M + click: where instance ``key`` (which has no pose) starts, at ``pixel`` of
    ``camera``."""
    obj, _, inst = key.partition("/")
    return start_pose(
        ds,
        obj,
        inst,
        camera=ds.rig.camera(camera),
        pixel=pixel,
        readings=inputs.readings,
        depth=inputs.depth,
        others=_neighbours(ds, info, key),
    )
