"""``export --remove-markers``: one scene's images with their markers filled in, and where
the markers were (:mod:`annotator.export.markers` finds them, :mod:`annotator.export.fill`
fills them). Depth is left as measured.

The exported poses place the instances; their markers are the instance's own (measured) sites
with the ids glued on them. The masks grow by a margin set from the blur ``annotate``
measured in each camera (annotation.json's ``image_quality``), or an assumed one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from annotator.dataset import Dataset, InstancePose, Scene
from annotator.errors import UserError
from annotator.export.fill import fill_markers
from annotator.export.markers import (
    DEFAULT_BLUR_PX,
    ImageMarkers,
    MarkedInstance,
    margin_for_blur,
    scene_markers,
)
from annotator.io.documents import read_json
from annotator.markers.dictionary import dictionary
from annotator.occlusion import InstanceVisibility


@dataclass
class SceneWithoutMarkers:
    """A scene's exported images with the markers filled in, and their markers.

    Attributes:
        images: Per camera, the filled image (only the pixels of its mask differ).
        markers: Per camera, where the markers are (:class:`ImageMarkers`).
        visibility: The instances' masks and occlusion, as :func:`scene_visibility` gives.
    """

    images: dict[str, np.ndarray]
    markers: dict[str, ImageMarkers]
    visibility: list[InstanceVisibility]

    @property
    def filled(self) -> int:
        """Markers filled in, over the cameras (a marker seen by two counts twice)."""
        return sum(len(r.pixels) > 0 for m in self.markers.values() for r in m.regions)


def marked_instances(ds: Dataset, poses: Sequence[InstancePose]) -> list[MarkedInstance]:
    """Each posed instance with its own sites and ids (an instance the dataset does not know
    has no markers)."""
    cells = int(dictionary(ds.dictionary).markerSize) + 2
    out = []
    for p in poses:
        obj = ds.objects[p.object]
        try:
            ids = obj.instance(p.instance).marker_ids
            sites = obj.site_corners(p.instance)[: len(ids)]
        except KeyError:
            ids, sites = (), np.zeros((0, 4, 3))
        out.append(MarkedInstance(p.object, p.instance, obj.mesh, p.T, sites, ids, cells))
    return out


def scene_blur(scene: Scene, frame: str | None = None) -> dict[str, float]:
    """Per camera, the blur (px) ``annotate`` measured on the scene's image, where it did; of
    a sequence, on the images of ``frame`` (each frame has its own: a frame taken while the
    rig moved is blurred more, and its ink spreads further)."""
    if not scene.annotation_path.is_file():
        return {}
    try:
        doc = read_json(scene.annotation_path)
    except UserError:
        return {}
    if isinstance(doc, dict) and frame is not None:
        frames = doc.get("frames")
        doc = frames.get(frame) if isinstance(frames, dict) else None
    quality = doc.get("image_quality") if isinstance(doc, dict) else None
    out: dict[str, float] = {}
    for cam, q in (quality or {}).items() if isinstance(quality, dict) else ():
        blur = q.get("edge_blur_px") if isinstance(q, dict) else None
        if isinstance(blur, (int, float)) and np.isfinite(blur):
            out[str(cam)] = float(blur)
    return out


def fill_blur(measured_px: float | None) -> float:
    """The blur (Gaussian sigma, px) given to the fill: the one ``annotate`` measured (or
    the assumed one) less the pixel's own footprint, which the measure includes and the
    fill's pixels already have (a pixel is a box of variance 1/12)."""
    sigma = DEFAULT_BLUR_PX if measured_px is None else measured_px
    return float(np.sqrt(max(sigma * sigma - 1.0 / 12.0, 0.0)))


def remove_scene_markers(
    ds: Dataset,
    rig: Any,
    scene: Scene,
    poses: Sequence[InstancePose],
    images: dict[str, np.ndarray],
    *,
    cameras: Sequence[str],
    depth: np.ndarray | None,
    fill: str = "surface",
    frame: str | None = None,
) -> SceneWithoutMarkers:
    """Find and fill the markers of a scene's images (already undistorted to ``rig``'s
    pinhole cameras), of its sequence's ``frame`` if it has frames."""
    blur = scene_blur(scene, frame)
    margins = {c: margin_for_blur(blur.get(c)) for c in cameras}
    vis, markers = scene_markers(
        rig, marked_instances(ds, poses), cameras=cameras, depth=depth, margin_px=margins
    )
    filled = {}
    for c in cameras:
        m = markers[c]
        filled[c] = fill_markers(
            images[c],
            m.mask,
            m.labels,
            normals=m.normals,
            rays=rig.camera(c).pixel_rays(),
            blur=fill_blur(blur.get(c)),
            method=fill,
        )
    return SceneWithoutMarkers(filled, markers, vis)
