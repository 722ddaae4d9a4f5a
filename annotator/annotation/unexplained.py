"""Unexplained depth: measured depth in front of the background that no posed part explains,
often a part without a pose (the rule is in :mod:`annotator.annotation.completeness`)."""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import replace

import cv2
import numpy as np
from scipy import ndimage

from annotator.annotation.completeness import (
    find_regions,
    mean_silhouette_mm2,
    support_depth,
    unexplained_mask,
)
from annotator.annotation.settings import AnnotateSettings
from annotator.annotation.visibility import Renders
from annotator.dataset import Dataset
from annotator.dataset.figures import DepthRegion, SceneWarning
from annotator.dataset.flags import WarningKind
from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh


def unexplained_depth(
    ds: Dataset,
    depth: np.ndarray,
    renders: Renders,
    *,
    disagreeing: Sequence[int] = (),
    unread: np.ndarray | None = None,
    settings: AnnotateSettings = AnnotateSettings(),
) -> tuple[SceneWarning | None, np.ndarray]:
    """The ``unexplained_depth`` warning (or None) and the full-resolution mask (uint8, 255
    where a reported region is), for a depth map (mm) and the posed instances as rendered
    (:func:`annotator.annotation.visibility.render_poses`, on the grid of
    ``settings.visibility_step``).

    Args:
        disagreeing: Indices of instances flagged ``depth_disagreement``: a region lying
            mostly on one's rendered silhouette is that instance's (a part with a doubtful
            pose, already flagged), not a part without a pose.
        unread: Candidate squares (K, 4, 2) of the depth camera that could not be read: those
            on a region are listed with it.
    """
    step = settings.visibility_step
    cam = ds.rig.depth_camera
    assert cam is not None, "unexplained_depth needs a dataset with depth"
    measured = depth[::step, ::step]
    if cam.name in renders:
        rendered, front = renders[cam.name]
    else:
        rendered = np.full(measured.shape, np.inf, np.float32)
        front = np.full(measured.shape, -1, np.int32)
    background, source = _background(ds, cam, measured, step)
    mask = unexplained_mask(measured, background, rendered, settings.completeness)
    regions, kept = find_regions(
        mask,
        measured,
        step=step,
        min_pixels=_min_region_px(ds, cam, measured, settings),
        skip_border_bands=ds.background_depth is None,
        owned=np.isin(front, list(disagreeing)),
    )
    # Each sample's pixel block: a nearest-neighbour enlargement (exact, and several times
    # faster than repeating rows and columns).
    rows, cols = kept.shape
    full_mask = cv2.resize(
        kept.view(np.uint8) * np.uint8(255),
        (cols * step, rows * step),
        interpolation=cv2.INTER_NEAREST_EXACT,
    )[: cam.height, : cam.width]
    if not regions:
        return None, full_mask
    regions = _with_unread(regions, unread, full_mask > 0)
    n_unread = sum(len(r.unread_markers) for r in regions)
    message = (
        f"{len(regions)} region(s) of measured depth in front of {source} that no pose explains "
        f"({sum(r.pixels or 0 for r in regions)} px)"
        + (f", with {n_unread} unread marker square(s)" if n_unread else "")
        + ": a part may have no pose"
    )
    return SceneWarning(WarningKind.UNEXPLAINED_DEPTH, message, tuple(regions)), full_mask


def _background(
    ds: Dataset, cam: Camera, measured: np.ndarray, step: int
) -> tuple[np.ndarray, str]:
    """What lies behind the parts on the sample grid, and where it comes from (for the
    message): the dataset's background depth, or else the support found in the depth."""
    if ds.background_depth is not None:
        return _filled(ds.background_depth, step), "the dataset's background depth"
    return support_depth(measured, cam.pixel_rays(step)), "the support plane found in the depth"


def _min_region_px(
    ds: Dataset, cam: Camera, measured: np.ndarray, settings: AnnotateSettings
) -> float:
    """The smallest region reported: a fraction of the smallest part's mean silhouette, seen
    at the scene's median depth."""
    z = float(np.nanmedian(measured)) if np.isfinite(measured).any() else 1000.0
    f2 = float(cam.K[0, 0] * cam.K[1, 1]) / (z * z)
    areas = [_silhouette_mm2(o.mesh) * f2 for o in ds.objects.values()]
    return settings.completeness.min_region_fraction * min(areas) if areas else np.inf


def _with_unread(
    regions: list[DepthRegion], unread: np.ndarray | None, full: np.ndarray
) -> list[DepthRegion]:
    """The regions with the centres of the unread squares (K, 4, 2) lying on them."""
    found: list[list[tuple[float, float]]] = [[] for _ in regions]
    height, width = full.shape
    for q in unread if unread is not None else ():
        x, y = q.mean(axis=0)
        if not (0 <= x < width and 0 <= y < height and full[int(y), int(x)]):
            continue
        for k, reg in enumerate(regions):
            x0, y0, x1, y1 = reg.box
            if x0 <= x < x1 and y0 <= y < y1:
                found[k].append((round(float(x), 1), round(float(y), 1)))
                break
    return [replace(r, unread_markers=tuple(f)) for r, f in zip(regions, found)]


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


def _silhouette_mm2(mesh: Mesh) -> float:
    return _silhouette_cached(mesh.digest, mesh.vertices.tobytes())
