"""A model's depth for BOP's VSD: one mesh in a pinhole camera, a ray through each pixel
centre of the rectangle it can cover.

The same casts as :func:`annotator.rendering.raycast.render_depth`; only the rectangle is
found with less work. That one projects every vertex (half a millisecond for a mesh of LM's
size, a sixth of the cast); this one projects the centres of the vertices' clusters
(:func:`annotator.evaluation.largest_gap.clusters_of`, a few hundred), bounds how far each
cluster's points can project from its centre, and projects point by point only the clusters
that can reach the rectangle's edges: the same rectangle, the same rays, the same depths.
"""

from __future__ import annotations

import numpy as np

from annotator.evaluation.largest_gap import clusters_of
from annotator.geometry import Rect
from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.rendering.raycast import cast_alone, clip_region, render_depth

#: Pixels added around the rectangle, as ``render_depth``'s own.
_MARGIN_PX = 1


def model_depth(
    mesh: Mesh, cam_T_model: np.ndarray, K: np.ndarray, width: int, height: int
) -> tuple[Rect, np.ndarray] | None:
    """The mesh's z-depth (mm, float32, 0 where it is not seen) over the rectangle it can
    cover: ``(rect, depth)``, or None when it is out of view (an
    :data:`annotator.evaluation.bop19.DepthRenderer`)."""
    box = _box(mesh, cam_T_model, K, int(width), int(height))
    if box is None:
        # a point may be at or behind the camera's plane: the projection bounds do not hold
        return render_depth(mesh, cam_T_model, K, width, height)
    x0, y0, x1, y1 = box
    if x0 >= x1 or y0 >= y1:
        return None
    camera = Camera("pinhole", int(width), int(height), np.asarray(K, float), np.zeros(5))
    # The pose is applied as written, as render_depth applies it.
    A = np.linalg.inv(cam_T_model)
    hits = cast_alone(
        mesh, np.eye(4), camera.pixel_rays()[y0:y1, x0:x1] @ A[:3, :3].T, origin=A[:3, 3]
    )
    depth = np.where(np.isfinite(hits.depth), hits.depth, np.float32(0.0)).astype(np.float32)
    return box, depth


def _box(
    mesh: Mesh, cam_T_model: np.ndarray, K: np.ndarray, width: int, height: int
) -> Rect | None:
    """``render_depth``'s rectangle (every vertex's projection, and a pixel more, clipped to
    the image: empty when out of view); None when a cluster may reach the camera's plane.

    A cluster's points lie within ``rho = |R|_2 r`` of its centre ``q`` once placed; their
    normalised image coordinates within ``rho |q| / ((q_z - rho) q_z)`` of the centre's
    (the difference is ``(d_xy q_z - q_xy d_z) / (z q_z)``), and their pixels within
    ``|K_2x2|_2`` times that. Only the clusters that can reach past the extremes of one
    point per cluster are projected point by point."""
    clusters = clusters_of(mesh.vertices)
    R, t = cam_T_model[:3, :3], cam_T_model[:3, 3]
    q = clusters.centres @ R.T + t
    rho = _norm_bound(R) * clusters.radii * (1.0 + 1e-9) + 1e-9
    qz = q[:, 2]
    if not np.all(qz - rho > 0):
        return None
    spread = _norm_bound(K[:2, :2]) * rho * np.linalg.norm(q, axis=1) / ((qz - rho) * qz)
    u, v = _pixels(q, K)
    u_some, v_some = _pixels(clusters.firsts @ R.T + t, K)
    lo_u, hi_u, lo_v, hi_v = u_some.min(), u_some.max(), v_some.min(), v_some.max()
    reach = (
        (u - spread <= lo_u) | (u + spread >= hi_u) | (v - spread <= lo_v) | (v + spread >= hi_v)
    )
    u_far, v_far = _pixels(clusters.members(np.flatnonzero(reach)) @ R.T + t, K)
    lo_u, hi_u = min(lo_u, u_far.min(initial=lo_u)), max(hi_u, u_far.max(initial=hi_u))
    lo_v, hi_v = min(lo_v, v_far.min(initial=lo_v)), max(hi_v, v_far.max(initial=hi_v))
    x0, y0 = int(np.floor(lo_u)) - _MARGIN_PX, int(np.floor(lo_v)) - _MARGIN_PX
    x1, y1 = int(np.ceil(hi_u)) + _MARGIN_PX + 1, int(np.ceil(hi_v)) + _MARGIN_PX + 1
    return clip_region((x0, y0, x1, y1), width, height)


def _norm_bound(M: np.ndarray) -> float:
    """An upper bound of the spectral norm of ``M``: the square root of the largest absolute
    row sum of ``M^T M`` (Gershgorin), 1 for a rotation; an SVD costs ten times as much."""
    return float(np.sqrt(np.abs(M.T @ M).sum(axis=1).max()))


def _pixels(cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (u, v) of points in the camera's frame, as ``render_depth``'s."""
    x, y = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
    return K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]
