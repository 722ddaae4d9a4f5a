"""What each frame of a sequence sees of the posed instances: occlusion rates and depth
agreement (:func:`frame_visibility`)."""

from __future__ import annotations

import numpy as np

from annotator.annotation.settings import AnnotateSettings
from annotator.annotation.visibility import MIN_DEPTH_PIXELS
from annotator.dataset import Dataset
from annotator.dataset.frames import poses_in_frame
from annotator.dataset.model import Frame
from annotator.dataset.records import (
    InstanceAnnotation,
)
from annotator.occlusion import scene_visibility


def visibility_step(settings: AnnotateSettings) -> int:
    """Every how many pixels (along rows and columns) a frame's visibility is sampled."""
    return max(settings.visibility_step, settings.sequence.visibility_step)


def frame_visibility(
    ds: Dataset,
    frame: Frame,
    instances: list[InstanceAnnotation],
    scene_T_rig: np.ndarray,
    *,
    settings: AnnotateSettings = AnnotateSettings(),
    depth_samples: np.ndarray | None = None,
) -> dict[str, dict]:
    """What ``frame`` sees of the posed instances (scene frame): per instance whose silhouette
    falls in one of its cameras, ``{"occlusion": {camera: rate}, "depth_agreement": a}``.
    ``depth_samples``: the frame's depth map at the samples (:func:`visibility_step`), as
    :func:`~.reading.read_frame_sampled` kept it; None: the depth file is read here."""
    if not instances:
        return {}
    local = poses_in_frame(instances, scene_T_rig)
    step = visibility_step(settings)
    if depth_samples is None:
        depth = frame.read_depth(ds.rig)
    else:
        # Each sample over its step x step pixels: the visibility reads the samples alone.
        assert ds.rig.depth is not None
        cam = ds.rig.camera(ds.rig.depth.camera)
        depth = np.repeat(np.repeat(depth_samples, step, axis=0), step, axis=1)
        depth = depth[: cam.height, : cam.width]
    vis = scene_visibility(
        ds.rig,
        [ds.objects[r.object].mesh for r in local],
        [r.T for r in local],
        depth=depth,
        agreement_tolerance=settings.depth_tolerance_mm,
        step=step,
    )
    out: dict[str, dict] = {}
    depth_cam = None if ds.rig.depth is None else ds.rig.depth.camera
    for r, v in zip(instances, vis):
        if not any(c.px_all > 0 for c in v.cameras):
            continue
        entry: dict = {"occlusion": {c.camera: round(c.occlusion, 4) for c in v.cameras}}
        cv = next((c for c in v.cameras if c.camera == depth_cam), None)
        if (
            depth is not None
            and cv is not None
            and cv.depth_agreement is not None
            and cv.depth_pixels >= MIN_DEPTH_PIXELS
        ):
            entry["depth_agreement"] = round(cv.depth_agreement, 4)
        out[r.key] = entry
    return out
