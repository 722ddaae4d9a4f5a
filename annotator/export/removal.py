"""``export --remove-markers``: one scene's images with their markers filled in, and where
the markers were (:mod:`annotator.export.markers` finds them, :mod:`annotator.export.fill`
fills them). Depth is left as measured.

The exported poses place the instances; their markers are the instance's own (measured) sites
with the ids glued on them. The masks grow by a margin set from the blur ``annotate``
measured in each camera (annotation.json's ``image_quality``), or an assumed one.

Poses can be wrong (a pose a reviewer has not repaired, an instance flagged and misplaced in
front of the real one): whatever the poses say, every marker a detector finds in the image
is masked too, its square widened by its white border, and the filled image is searched
again, until a search finds nothing more (at most :data:`SEARCHES` rounds; when the poses
cover every marker the first search finds, their fill is not searched again). The detectors
are the project's own and OpenCV's with every setting turned to find more.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
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
        found_beyond: Per camera, markers the detectors found that reach beyond where the
            poses put markers (masked and filled whole).
        found_alone: Of those, the ones whose centre no pose's marker covers (a part
            without a pose, or posed elsewhere).
    """

    images: dict[str, np.ndarray]
    markers: dict[str, ImageMarkers]
    visibility: list[InstanceVisibility]
    found_beyond: dict[str, int] = field(default_factory=dict)
    found_alone: dict[str, int] = field(default_factory=dict)

    @property
    def filled(self) -> int:
        """Markers filled in, over the cameras (a marker seen by two counts twice): those the
        poses place, and those found by the detectors only."""
        placed = sum(len(r.pixels) > 0 for m in self.markers.values() for r in m.regions)
        return placed + sum(self.found_alone.values())


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
    filled, beyond, alone = {}, {}, {}
    for c in cameras:
        fills = partial(
            fill_markers,
            normals=markers[c].normals,
            rays=rig.camera(c).pixel_rays(),
            blur=fill_blur(blur.get(c)),
            method=fill,
        )
        filled[c], beyond[c], alone[c] = _filled_until_clean(
            images[c], markers[c], fills, ds.dictionary
        )
    return SceneWithoutMarkers(filled, markers, vis, beyond, alone)


#: Searches of an image for markers left (the first on the image as it is).
SEARCHES = 3
#: A marker found is at most this share of the image's smaller side wide.
MAX_MARKER_SHARE = 0.25


def _filled_until_clean(
    image: np.ndarray, m: ImageMarkers, fills: Callable[..., np.ndarray], dictionary_name: str
) -> tuple[np.ndarray, int, int]:
    """``image`` with the markers of ``m`` filled, and those a detector finds besides,
    searched again after each fill; how many were found reaching beyond where the poses put
    markers, and how many of those where the poses put none. ``m``'s mask grows by them.
    ``fills(image, mask, labels)`` fills."""
    cells = int(dictionary(dictionary_name).markerSize) + 2
    labels = m.labels.copy()
    out, beyond, alone = image, 0, 0
    for k in range(SEARCHES):
        found = found_markers(out, dictionary_name)
        extra = quads_mask(found, m.mask.shape, cells=cells, margin_px=m.margin_px) & ~m.mask
        if k and not extra.any():
            break
        if not k and not extra.any():  # the poses cover every marker found: no search after
            out = fills(image, m.mask, labels)
            break
        if not k:
            beyond, alone = _beyond(found, m.mask, cells=cells), _outside(found, m.mask)
        # Where only a detector put a marker the poses do not describe the surface (a part
        # without a pose, or posed elsewhere): filled from its surroundings, unlabelled. A
        # marker the poses place in part keeps its part's surface.
        lone = np.array([_outside(q[None], m.mask) == 1 for q in found], bool)
        if lone.any():
            labels[
                quads_mask(found[lone], m.mask.shape, cells=cells, margin_px=m.margin_px) & extra
            ] = -1
        m.mask |= extra
        out = fills(image, m.mask, labels)
    return out, beyond, alone


@functools.cache
def _detectors(dictionary_name: str) -> tuple[MarkerDetector, cv2.aruco.ArucoDetector]:
    # OpenCV's with every knob turned the way that finds more (what a user trying to find
    # markers left would turn): wide thresholding windows, small markers, 8 px a cell, most
    # of the border's bits allowed wrong, rough polygons.
    p = cv2.aruco.DetectorParameters()
    p.adaptiveThreshWinSizeMin, p.adaptiveThreshWinSizeMax, p.adaptiveThreshWinSizeStep = 3, 53, 4
    p.minMarkerPerimeterRate = 0.01
    p.perspectiveRemovePixelPerCell = 8
    p.maxErroneousBitsInBorderRate = 0.6
    p.polygonalApproxAccuracyRate = 0.1
    p.maxMarkerPerimeterRate = 4 * MAX_MARKER_SHARE
    opencv = cv2.aruco.ArucoDetector(dictionary(dictionary_name), p, cv2.aruco.RefineParameters())
    return MarkerDetector(dictionary_name), opencv


def found_markers(image: np.ndarray, dictionary_name: str) -> np.ndarray:
    """(K, 4, 2) the squares of every marker of the dictionary that the project's detector
    or OpenCV's (at its most finding settings) finds in ``image``."""
    ours, opencv = _detectors(dictionary_name)
    quads = [d.corners for d in ours.detect(image)]
    corners, ids, _ = opencv.detectMarkers(to_gray8(image))
    if ids is not None and len(ids):
        quads += list(np.asarray(corners, np.float64).reshape(-1, 4, 2))
    out = np.array(quads, np.float64).reshape(-1, 4, 2)
    # A square wider than a quarter of the image is a bin's outline read as a code, not a
    # marker on a part: masking it would erase the scene.
    sides = np.linalg.norm(out - np.roll(out, 1, axis=1), axis=2).max(axis=1)
    return out[sides <= MAX_MARKER_SHARE * min(image.shape[:2])]


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


def _beyond(quads: np.ndarray, mask: np.ndarray, *, cells: int) -> int:
    """How many of ``quads`` (widened by their white border) reach outside ``mask``: markers
    the poses did not place whole."""
    return sum(
        bool((quads_mask(q[None], mask.shape, cells=cells, margin_px=0) & ~mask).any())
        for q in quads
    )


def _outside(quads: np.ndarray, mask: np.ndarray) -> int:
    """How many of ``quads`` have their centre outside ``mask`` (where no pose put one)."""
    h, w = mask.shape
    n = 0
    for q in quads:
        x, y = np.clip(np.round(q.mean(axis=0)).astype(int), 0, [w - 1, h - 1])
        n += not mask[y, x]
    return n
