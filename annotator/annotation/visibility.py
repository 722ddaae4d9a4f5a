"""What the cameras see of the posed instances: occlusion rates and agreement with the
measured depth (see :mod:`annotator.occlusion`), written into the instances' records."""

from __future__ import annotations

import numpy as np

from annotator.annotation.settings import AnnotateSettings
from annotator.dataset import Dataset, InstancePose
from annotator.dataset.figures import DepthCheck, Occlusion
from annotator.dataset.flags import Flag, sort_flags
from annotator.dataset.records import InstanceAnnotation
from annotator.occlusion import CastMemo, InstanceVisibility, scene_visibility

#: Per camera, the depth (mm) of the nearest posed instance and its index, on a sample grid.
Renders = dict[str, tuple[np.ndarray, np.ndarray]]

#: Fewer visible pixels with a measurement than this give no depth agreement.
MIN_DEPTH_PIXELS = 20


def render_poses(ds: Dataset, poses: list[InstancePose], *, step: int = 2) -> Renders:
    """What each camera sees of ``poses``: per camera, the depth of the nearest instance and
    its index at every ``step``-th pixel (see :func:`annotator.occlusion.scene_visibility`)."""
    renders: Renders = {}
    if poses:
        meshes = [ds.objects[p.object].mesh for p in poses]
        scene_visibility(ds.rig, meshes, [p.T for p in poses], step=step, renders=renders)
    return renders


def add_visibility(
    ds: Dataset,
    instances: list[InstanceAnnotation],
    depth: np.ndarray | None,
    s: AnnotateSettings,
    renders: Renders,
    memo: CastMemo | None = None,
) -> None:
    """Set the occlusion rates and depth agreement of the posed instances (all instances as
    occluders), and their ``depth_disagreement`` flag; ``renders`` receives what each camera
    sees of them. ``memo``: the instances' casts of an earlier call on the same scene, kept
    (see :func:`annotator.occlusion.scene_visibility`)."""
    if not instances:
        return
    vis = scene_visibility(
        ds.rig,
        [ds.objects[r.object].mesh for r in instances],
        [r.T for r in instances],
        depth=depth,
        agreement_tolerance=s.depth_tolerance_mm,
        step=s.visibility_step,
        renders=renders,
        memo=memo,
    )
    depth_cam = ds.rig.depth.camera if ds.rig.depth is not None else None
    for r, v in zip(instances, vis):
        r.occlusion = Occlusion(
            round(v.occlusion, 4), {c.camera: round(c.occlusion, 4) for c in v.cameras}
        )
        flags = [f for f in r.flags if f != Flag.DEPTH_DISAGREEMENT]  # recomputed here
        r.depth = _depth_check(v, depth_cam) if depth is not None else None
        if r.depth_agreement is not None and r.depth_agreement < s.depth_min_agreement:
            flags.append(Flag.DEPTH_DISAGREEMENT)
        r.flags = sort_flags(flags)


def _depth_check(v: InstanceVisibility, depth_cam: str | None) -> DepthCheck | None:
    """The instance's agreement with the measured depth in the depth camera, or None where
    too few of its visible pixels were measured."""
    cv = next((c for c in v.cameras if c.camera == depth_cam), None)
    if cv is None or cv.depth_agreement is None or cv.depth_pixels < MIN_DEPTH_PIXELS:
        return None
    assert cv.depth_median_abs_mm is not None  # set together with depth_agreement
    return DepthCheck(
        round(cv.depth_agreement, 4), round(cv.depth_median_abs_mm, 3), cv.depth_pixels
    )
