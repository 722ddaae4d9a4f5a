"""Per-instance silhouettes, visible parts and occlusion rates, by ray casting.

For every posed instance and camera:

- the *full* silhouette: the instance alone, cast only over its projected bounding box;
- the *visible* part: the pixels of the full silhouette where the instance is the first
  surface hit when all posed instances are cast together (one full-image cast per camera);
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
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from annotator.dataset.model import Rig
from annotator.geometry.mesh import Mesh
from annotator.rendering.raycast import NO_HIT, PlacedMesh, RayScene, projected_bbox

Box = tuple[int, int, int, int]


@dataclass
class CameraVisibility:
    """One instance in one camera. Boxes are ``(x, y, w, h)`` (BOP's convention)."""

    camera: str
    px_all: int
    px_visib: int
    px_visib_depth: int | None
    bbox_all: Box | None
    bbox_visib: Box | None
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


def _cast_union(cam, placed: Sequence[PlacedMesh], boxes: Sequence[Box | None]):
    """Cast all placed meshes together, but only over the union of their bounding boxes (the
    rest of the image cannot show any of them)."""
    from annotator.rendering.raycast import NO_HIT, Hits

    mask = np.zeros((cam.height, cam.width), bool)
    for b in boxes:
        if b is not None:
            mask[b[1] : b[3], b[0] : b[2]] = True
    hits = RayScene(placed).cast(cam.pixel_rays()[mask])
    full = Hits(
        depth=np.full(mask.shape, np.inf, np.float32),
        instance=np.full(mask.shape, NO_HIT, np.int32),
        triangle=np.full(mask.shape, -1, np.int32),
        barycentric=np.zeros((*mask.shape, 2), np.float32),
    )
    full.depth[mask] = hits.depth
    full.instance[mask] = hits.instance
    full.triangle[mask] = hits.triangle
    full.barycentric[mask] = hits.barycentric
    return full


def _bbox(mask: np.ndarray, x0: int = 0, y0: int = 0) -> Box | None:
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return None
    return (
        int(xs.min() + x0),
        int(ys.min() + y0),
        int(xs.max() - xs.min() + 1),
        int(ys.max() - ys.min() + 1),
    )


def scene_visibility(
    rig: Rig,
    meshes: Sequence[Mesh],
    poses: Sequence[np.ndarray],
    *,
    depth: np.ndarray | None = None,
    depth_tolerance: float = 5.0,
    cameras: Sequence[str] | None = None,
    masks: bool = False,
) -> list[InstanceVisibility]:
    """Silhouettes and occlusion of every posed instance (poses: ``rig_T_model`` 4x4)."""
    names = list(cameras) if cameras is not None else [c.name for c in rig.cameras]
    per_instance: list[list[CameraVisibility]] = [[] for _ in meshes]
    depth_cam = rig.depth.camera if rig.depth is not None else None
    for name in names:
        cam = rig.camera(name)
        placed = [PlacedMesh(m, cam.cam_T_rig @ T) for m, T in zip(meshes, poses)]
        boxes = [projected_bbox(cam, pm.mesh, pm.cam_T_model) for pm in placed]
        together = _cast_union(cam, placed, boxes)
        use_depth = depth is not None and name == depth_cam
        for k, pm in enumerate(placed):
            box = boxes[k]
            full = np.zeros((cam.height, cam.width), bool) if masks else None
            if box is None:
                vis = CameraVisibility(
                    name,
                    0,
                    0,
                    0 if use_depth else None,
                    None,
                    None,
                    1.0,
                    1.0 if use_depth else None,
                )
            else:
                x0, y0, x1, y1 = box
                seen = together.instance[y0:y1, x0:x1]
                m_vis = seen == k
                # The full silhouette: where the instance is seen, plus where a ray cast at it
                # alone hits it behind another instance. Rays that hit nothing at all cannot
                # hit it either, so only pixels showing another instance are cast again.
                behind = (seen != k) & (seen != NO_HIT)
                m_all = m_vis.copy()
                if behind.any():
                    m_all[behind] = RayScene([pm]).cast(cam.pixel_rays()[y0:y1, x0:x1][behind]).hit
                px_all, px_vis = int(m_all.sum()), int(m_vis.sum())
                px_dep = occ_dep = None
                m_dep = m_vis
                agreement = median_abs = None
                n_meas = 0
                if use_depth:
                    meas = depth[y0:y1, x0:x1]
                    rend = together.depth[y0:y1, x0:x1]
                    hidden = np.isfinite(meas) & (meas < rend - depth_tolerance)
                    m_dep = m_vis & ~hidden
                    px_dep = int(m_dep.sum())
                    occ_dep = 1.0 - px_dep / px_all if px_all else 1.0
                    measured = m_vis & np.isfinite(meas)
                    n_meas = int(measured.sum())
                    if n_meas:
                        diff = np.abs(meas[measured] - rend[measured])
                        tol = np.maximum(AGREEMENT_TOLERANCE_MM, 0.01 * rend[measured])
                        agreement = float(np.mean(diff < tol))
                        median_abs = float(np.median(diff))
                vis = CameraVisibility(
                    name,
                    px_all,
                    px_vis,
                    px_dep,
                    _bbox(m_all, x0, y0),
                    _bbox(m_vis, x0, y0),
                    1.0 - px_vis / px_all if px_all else 1.0,
                    occ_dep,
                    depth_agreement=agreement,
                    depth_median_abs_mm=median_abs,
                    depth_pixels=n_meas,
                )
                if masks:
                    full[y0:y1, x0:x1] = m_all
                    visible = np.zeros_like(full)
                    visible[y0:y1, x0:x1] = m_dep
                    vis.mask_all, vis.mask_visib = full, visible
            if masks and vis.mask_all is None:
                vis.mask_all = full
                vis.mask_visib = np.zeros_like(full)
            per_instance[k].append(vis)
    out = []
    for cams_vis in per_instance:
        ref = cams_vis[0]
        rate = ref.occlusion_depth if ref.occlusion_depth is not None else ref.occlusion
        out.append(InstanceVisibility(cams_vis, float(rate)))
    return out
