"""Per-instance silhouettes, visible parts and occlusion rates, by ray casting.

For every posed instance and camera:

- the *full* silhouette: the instance alone, cast only over its projected bounding box;
- the *visible* part: the pixels of the full silhouette where no other instance's silhouette
  is closer (a depth buffer of all the full silhouettes);
- in the depth camera, the visible part *with the depth test*: a visible pixel whose measured
  depth is closer than the rendered one by more than ``depth_tolerance`` mm (default 5 mm,
  several times the sensor noise) is hidden by something nobody annotated (bin walls, clutter);
  a pixel without measurement counts as visible.

``occlusion = 1 - visible / full`` (1.0 when the full silhouette is empty). In the depth camera
the *depth agreement* is also measured: the fraction of visible pixels with a measurement where
measured and rendered depth agree within ``max(3 mm, 1% of the depth)``. The rate reported
for an instance is the reference camera's, with the depth test when the depth camera is the
reference camera and a depth map exists. Pixels follow OpenCV's convention, lens distortion
included, exactly as the overlays and the synthetic images.

Each instance is cast alone, in its model frame (the rays are moved, not the mesh), so that a
part's bounding volume hierarchy is built once per process and serves every copy of it in
every scene and camera.

``step`` trades exactness for speed: with ``step=s`` only every ``s``-th pixel of every
``s``-th row is cast (``s**2`` times fewer rays), pixel counts are these samples times ``s**2``
and boxes are those of the samples. The rates are then estimates (within 0.2% for parts
of more than a few hundred pixels); annotation uses ``step=2``, exports and ``annotator
occlusion`` use the exact ``step=1``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from annotator.dataset.model import Rig
from annotator.geometry import XYWH, Rect
from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.rendering.raycast import (
    Hits,
    PlacedMesh,
    cast_alone,
    hit_bbox,
    nearest,
)

#: Instances cast alone, by (camera, step, mesh digest, pose bytes): their rectangle on the
#: sample grid and their hits there (see ``scene_visibility``'s ``memo``).
CastMemo = dict[tuple[str, int, bytes, bytes], tuple[Rect | None, Hits | None]]

#: How much closer (mm) a measurement must be than the rendered part to hide a pixel of it:
#: several times the sensor noise.
DEPTH_TOLERANCE_MM = 5.0


@dataclass
class CameraVisibility:
    """One instance in one camera; boxes are :data:`XYWH`."""

    camera: str
    px_all: int
    px_visib: int
    px_visib_depth: int | None
    bbox_all: XYWH | None
    bbox_visib: XYWH | None
    occlusion: float
    occlusion_depth: float | None
    mask_all: np.ndarray | None = None
    mask_visib: np.ndarray | None = None
    depth_agreement: float | None = (
        None  # visible pixels with |measured - rendered| within tolerance
    )
    depth_median_abs_mm: float | None = None
    depth_pixels: int = 0  # visible pixels with a measurement


@dataclass
class InstanceVisibility:
    """One instance in every camera, and the occlusion rate reported for it."""

    cameras: list[CameraVisibility]
    occlusion: float


#: Depth agreement: measured and rendered depth agree within max(3 mm, 1% of the depth).
AGREEMENT_TOLERANCE_MM = 3.0


def _bbox(mask: np.ndarray, x0: int = 0, y0: int = 0, step: int = 1) -> XYWH | None:
    """``(x, y, w, h)`` of the true samples of a grid mask whose sample (0, 0) is grid point
    ``(x0, y0)``, in pixels. (From the rows and columns holding one: the positions of
    every true sample cost several times more.)"""
    ys, xs = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(xs) == 0:
        return None
    return (
        int(xs[0] + x0) * step,
        int(ys[0] + y0) * step,
        int(xs[-1] - xs[0]) * step + 1,
        int(ys[-1] - ys[0]) * step + 1,
    )


def scene_visibility(
    rig: Rig,
    meshes: Sequence[Mesh],
    poses: Sequence[np.ndarray],
    *,
    depth: np.ndarray | None = None,
    depth_tolerance: float = DEPTH_TOLERANCE_MM,
    agreement_tolerance: float = AGREEMENT_TOLERANCE_MM,
    cameras: Sequence[str] | None = None,
    masks: bool = False,
    step: int = 1,
    renders: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
    casts: Mapping[str, Sequence[tuple[Rect, Hits] | None]] | None = None,
    memo: CastMemo | None = None,
) -> list[InstanceVisibility]:
    """Silhouettes and occlusion of every posed instance (poses: ``rig_T_model`` 4x4).

    Args:
        depth: The depth camera's measured depth map (mm, NaN where nothing was measured).
        depth_tolerance: How much closer (mm) a measurement must be to hide a pixel.
        agreement_tolerance: Measured and rendered depth agree within
            ``max(agreement_tolerance, 1% of the depth)`` (mm).
        cameras: Names of the cameras to process (default: all, the reference camera first).
        masks: Also return full-image masks (requires ``step=1``).
        step: Cast every ``step``-th pixel only (see the module's docstring).
        renders: If given, receives per camera the scene as the poses render it: at each
            sample, the depth (mm) of the nearest instance (inf where none) and its index
            (``NO_HIT`` where none).
        casts: Per camera, each instance cast alone over its rectangle (what
            :func:`cast_separately` returns, with the rectangle), when it has already been
            done at ``step=1`` (by the synthetic renderer); missing cameras are cast here.
        memo: Each instance's own cast, kept by camera, step, mesh and pose: given again
            (for the same rig), an instance that has not moved is not cast again.
    """
    if masks and step != 1:
        raise ValueError("masks need step=1")
    names = list(cameras) if cameras is not None else [c.name for c in rig.cameras]
    per_instance: list[list[CameraVisibility]] = [[] for _ in meshes]
    depth_cam = rig.depth.camera if rig.depth is not None else None
    tolerances = (depth_tolerance, agreement_tolerance)
    for name in names:
        cam = rig.camera(name)
        done = casts.get(name) if casts is not None and step == 1 else None
        boxes, alone, front, zbuf = _cast_camera(cam, meshes, poses, step, done, memo)
        if renders is not None:
            renders[name] = (zbuf, front)
        measured = depth[::step, ::step] if depth is not None and name == depth_cam else None
        size = cam.size if masks else None
        for k, box in enumerate(boxes):
            cast = _InstanceCast(name, box, alone[k], front, k)
            per_instance[k].append(_visibility(cast, measured, tolerances, step, size))
    out = []
    for cams_vis in per_instance:
        ref = cams_vis[0]
        rate = ref.occlusion_depth if ref.occlusion_depth is not None else ref.occlusion
        out.append(InstanceVisibility(cams_vis, float(rate)))
    return out


def _cast_camera(
    cam: Camera,
    meshes: Sequence[Mesh],
    poses: Sequence[np.ndarray],
    step: int,
    done: Sequence[tuple[Rect, Hits] | None] | None,
    memo: CastMemo | None,
) -> tuple[list[Rect | None], list[tuple[np.ndarray, np.ndarray] | None], np.ndarray, np.ndarray]:
    """Every instance cast alone over its rectangle (as :func:`cast_separately` does; or from
    ``done`` or ``memo``), then a depth buffer of all of them (on equal depths the first
    instance wins, so that visible parts never overlap): the rectangles (on the sample grid),
    per instance its (hit mask, depth) there, and the nearest instance and its depth at every
    sample."""
    rays = cam.pixel_rays(step)
    if done is not None:
        boxes = [None if c is None else c[0] for c in done]
        own = [None if c is None else c[1] for c in done]
    else:
        boxes, own = [], []
        for m, T in zip(meshes, poses):
            key = (cam.name, step, m.digest, np.asarray(T, float).tobytes())
            found = memo.get(key) if memo is not None else None
            if found is None:
                pm = PlacedMesh(m, cam.cam_T_rig @ T)
                box = hit_bbox(cam, pm.mesh, pm.cam_T_model, step=step)
                window = rays if box is None else rays[box[1] : box[3], box[0] : box[2]]
                found = (box, None if box is None else cast_alone(pm.mesh, pm.cam_T_model, window))
                if memo is not None:
                    memo[key] = found
            boxes.append(found[0])
            own.append(found[1])
    together = nearest(rays.shape[:2], boxes, own, surface=False)
    alone = [None if h is None else (h.hit, h.depth) for h in own]
    return boxes, alone, together.instance, together.depth


@dataclass(frozen=True)
class _InstanceCast:
    """Instance ``index`` in one camera: its rectangle on the sample grid, its own (hit
    mask, depth) there, and the index of the nearest instance at every sample."""

    camera: str
    box: Rect | None
    alone: tuple[np.ndarray, np.ndarray] | None
    front: np.ndarray
    index: int


def _visibility(
    cast: _InstanceCast,
    measured: np.ndarray | None,
    tolerances: tuple[float, float],
    step: int,
    size: tuple[int, int] | None,
) -> CameraVisibility:
    """The instance's counts, boxes, occlusion and depth agreement in one camera (pixel
    counts are samples times ``step**2``), and with ``size`` (width, height) its full-image
    masks: the silhouette and its visible part, with the depth test in the depth camera.
    ``tolerances``: how much closer a measurement hides a pixel, and within how much it
    agrees (mm)."""
    use_depth = measured is not None
    empty = None if size is None else np.zeros((size[1], size[0]), bool)
    if cast.box is None or cast.alone is None:
        vis = CameraVisibility(
            cast.camera, 0, 0, 0 if use_depth else None, None, None, 1.0, 1.0 if use_depth else None
        )
        if empty is not None:
            vis.mask_all, vis.mask_visib = empty, empty.copy()
        return vis
    area = step * step
    x0, y0, x1, y1 = cast.box
    m_all, rend = cast.alone
    m_vis = cast.front[y0:y1, x0:x1] == cast.index
    px_all, px_vis = area * int(np.count_nonzero(m_all)), area * int(np.count_nonzero(m_vis))
    vis = CameraVisibility(
        cast.camera,
        px_all,
        px_vis,
        None,
        _bbox(m_all, x0, y0, step),
        _bbox(m_vis, x0, y0, step),
        1.0 - px_vis / px_all if px_all else 1.0,
        None,
    )
    m_dep = m_vis
    if measured is not None:
        meas = measured[y0:y1, x0:x1]
        hide, agree = tolerances
        measured_here = np.isfinite(meas)
        m_dep = m_vis & ~(measured_here & (meas < rend - hide))
        vis.px_visib_depth = area * int(np.count_nonzero(m_dep))
        vis.occlusion_depth = 1.0 - vis.px_visib_depth / px_all if px_all else 1.0
        seen = m_vis & measured_here
        vis.depth_pixels = area * int(np.count_nonzero(seen))
        if vis.depth_pixels:
            r = rend[seen]
            diff = np.abs(meas[seen] - r)
            vis.depth_agreement = int(np.count_nonzero(diff < np.maximum(agree, 0.01 * r))) / len(r)
            vis.depth_median_abs_mm = float(np.median(diff))
    if empty is not None:
        vis.mask_all, vis.mask_visib = empty, empty.copy()
        vis.mask_all[y0:y1, x0:x1] = m_all
        vis.mask_visib[y0:y1, x0:x1] = m_dep
    return vis
