"""``export --remove-markers``: one scene's images with their markers filled in, and where
the markers were (:mod:`annotator.export.markers` finds them, :mod:`annotator.export.fill`
fills them). Depth is left as measured.

The exported poses place the instances; their markers are the instance's own (measured) sites
with the ids glued on them. The masks grow by a margin set from the blur ``annotate``
measured in each camera (annotation.json's ``image_quality``), or an assumed one.

Poses can be wrong (a pose a reviewer has not repaired, an instance flagged and misplaced in
front of the real one): whatever the poses say, every marker a detector finds in the image
is masked too, its square widened by its white border, and the filled image is searched
again, until a search finds nothing more (at most :data:`SEARCHES` rounds). The detectors
are the project's own and OpenCV's at its defaults.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from annotator.dataset import Dataset, InstancePose, Scene
from annotator.detection.aruco import MarkerDetector
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
from annotator.io.images import to_gray8
from annotator.markers.dictionary import dictionary
from annotator.occlusion import InstanceVisibility


@dataclass
class SceneWithoutMarkers:
    """A scene's exported images with the markers filled in, and their markers.

    Attributes:
        images: Per camera, the filled image (only the pixels of its mask differ).
        markers: Per camera, where the markers are (:class:`ImageMarkers`).
        visibility: The instances' masks and occlusion, as :func:`scene_visibility` gives.
        found_elsewhere: Per camera, markers the detectors found where the poses put none
            (masked and filled too).
    """

    images: dict[str, np.ndarray]
    markers: dict[str, ImageMarkers]
    visibility: list[InstanceVisibility]
    found_elsewhere: dict[str, int] = field(default_factory=dict)

    @property
    def filled(self) -> int:
        """Markers filled in, over the cameras (a marker seen by two counts twice): those the
        poses place, and those found where they place none."""
        placed = sum(len(r.pixels) > 0 for m in self.markers.values() for r in m.regions)
        return placed + sum(self.found_elsewhere.values())


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
    filled, elsewhere = {}, {}
    cells = int(dictionary(ds.dictionary).markerSize) + 2
    for c in cameras:
        m = markers[c]

        def filled_with(mask: np.ndarray, c: str = c, m: ImageMarkers = m) -> np.ndarray:
            return fill_markers(
                images[c],
                mask,
                m.labels,
                normals=m.normals,
                rays=rig.camera(c).pixel_rays(),
                blur=fill_blur(blur.get(c)),
                method=fill,
            )

        out = images[c]
        elsewhere[c] = 0
        for _ in range(SEARCHES):
            found = found_markers(out, ds.dictionary)
            extra = quads_mask(found, m.mask.shape, cells=cells, margin_px=m.margin_px) & ~m.mask
            if out is not images[c] and not extra.any():
                break
            if out is images[c]:
                elsewhere[c] = _outside(found, m.mask)
            m.mask |= extra
            out = filled_with(m.mask)
        filled[c] = out
    return SceneWithoutMarkers(filled, markers, vis, elsewhere)


#: Searches of an image for markers left (the first on the image as it is).
SEARCHES = 3


@functools.cache
def _detectors(dictionary_name: str) -> tuple[MarkerDetector, cv2.aruco.ArucoDetector]:
    full = dictionary(dictionary_name)
    opencv = cv2.aruco.ArucoDetector(
        full, cv2.aruco.DetectorParameters(), cv2.aruco.RefineParameters()
    )
    return MarkerDetector(dictionary_name), opencv


def found_markers(image: np.ndarray, dictionary_name: str) -> np.ndarray:
    """(K, 4, 2) the squares of every marker of the dictionary that the project's detector
    or OpenCV's (at its defaults) finds in ``image``."""
    ours, opencv = _detectors(dictionary_name)
    quads = [d.corners for d in ours.detect(image)]
    corners, ids, _ = opencv.detectMarkers(to_gray8(image))
    if ids is not None and len(ids):
        quads += list(np.asarray(corners, np.float64).reshape(-1, 4, 2))
    return np.array(quads, np.float64).reshape(-1, 4, 2)


def quads_mask(
    quads: np.ndarray, shape: tuple[int, ...], *, cells: int, margin_px: int
) -> np.ndarray:
    """(H, W) bool: each marker square of ``quads`` widened by its one cell of white border
    (a square of ``cells`` cells, its black border included), grown by ``margin_px``.

    >>> q = np.array([[[10, 10], [20, 10], [20, 20], [10, 20]]], float)
    >>> m = quads_mask(q, (40, 40), cells=6, margin_px=0)
    >>> bool(m[15, 15]), bool(m[9, 15]), bool(m[5, 15])
    (True, True, False)
    """
    h, w = shape[:2]
    mask: np.ndarray = np.zeros((h, w), np.uint8)
    grow = (cells + 2.0) / cells
    for q in quads:
        centre = q.mean(axis=0)
        wide = centre + (q - centre) * grow
        cv2.fillConvexPoly(mask, np.round(wide * 16).astype(np.int32), 1, cv2.LINE_8, 4)
    if margin_px > 0 and mask.any():
        d = 2 * margin_px + 1
        mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d, d)))
    return mask > 0


def _outside(quads: np.ndarray, mask: np.ndarray) -> int:
    """How many of ``quads`` have their centre outside ``mask`` (where no pose put one)."""
    h, w = mask.shape
    n = 0
    for q in quads:
        x, y = np.clip(np.round(q.mean(axis=0)).astype(int), 0, [w - 1, h - 1])
        n += not mask[y, x]
    return n
