"""A model's depth for BOP's VSD: one mesh in a pinhole camera, a ray through each pixel
centre of a rectangle it cannot be seen outside.

The depths of :func:`annotator.rendering.raycast.render_depth`, pixel for pixel, for less
work around the same casts. That one projects every vertex to find its rectangle (half a
millisecond for a mesh of LM's size) and reads every output of the cast; this one

- projects the centres of small clusters of the vertices
  (:func:`annotator.evaluation.largest_gap.clusters_of`, 16 points each) and grows each by
  how far its points can project from it: a rectangle a pixel or two wider (a pixel centre
  that sees a triangle lies within its vertices' projections, so within it), whose extra
  rays miss at a third of a hit's cost;
- casts at the same triangles (float32, as ``RayScene`` places them) the same rays
  (float32 directions ``pixel_rays @ R^T`` from the pose's inverse) and reads the hit
  distance alone.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from annotator.evaluation.largest_gap import clusters_of
from annotator.geometry import Rect
from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.geometry.open3d_lib import o3d
from annotator.rendering.raycast import clip_region, get_threads, mesh_scene, render_depth

#: Pixels added around the rectangle, as ``render_depth``'s own.
_MARGIN_PX = 1
#: Vertices per cluster the rectangle is bounded with (fewer: a tighter rectangle, more
#: centres to project).
_BOX_CLUSTER_POINTS = 16


def model_depth(
    mesh: Mesh, cam_T_model: np.ndarray, K: np.ndarray, width: int, height: int
) -> tuple[Rect, np.ndarray] | None:
    """The mesh's z-depth (mm, float32, 0 where it is not seen) over a rectangle it cannot
    be seen outside: ``(rect, depth)``, or None when it is out of view (an
    :data:`annotator.evaluation.bop19.DepthRenderer`)."""
    box = _box(mesh, cam_T_model, K, int(width), int(height))
    if box is None:
        # a point may be at or behind the camera's plane: the projection bounds do not hold
        return render_depth(mesh, cam_T_model, K, width, height)
    x0, y0, x1, y1 = box
    if x0 >= x1 or y0 >= y1:
        return None
    camera = Camera("pinhole", int(width), int(height), np.asarray(K, float), np.zeros(5))
    # The pose is applied as written, as render_depth applies it: rays brought into the
    # model's frame by the pose's inverse.
    A = np.linalg.inv(cam_T_model)
    grid = camera.pixel_rays()[y0:y1, x0:x1]
    rays = np.empty((grid.shape[0] * grid.shape[1], 6), np.float32)
    for k in range(3):
        rays[:, k] = np.float32(A[k, 3])
    rays[:, 3:] = (grid @ A[:3, :3].T).reshape(-1, 3)
    got = _scene(mesh).cast_rays(o3d.core.Tensor(rays), nthreads=get_threads())
    t = got["t_hit"].numpy()
    depth = np.where(np.isfinite(t), t, np.float32(0.0)).astype(np.float32)
    return box, depth.reshape(grid.shape[:2])


def prepare(meshes: Iterable[Mesh]) -> None:
    """Builds what :func:`model_depth` needs of each mesh (its ray-casting scene, whose
    search structure is made on the first cast, and its clusters) ahead, once for the
    processes forked next."""
    ray = o3d.core.Tensor(np.array([[0, 0, -1e6, 0, 0, 1]], np.float32))
    for mesh in meshes:
        _scene(mesh).cast_rays(ray, nthreads=get_threads())
        clusters_of(mesh.vertices, _BOX_CLUSTER_POINTS)


def _scene(mesh: Mesh) -> Any:
    """The mesh's open3d ray-casting scene in its own frame, built once per process and
    mesh (by content), its triangles placed as ``RayScene`` places them."""
    scene = _SCENES.get(mesh.digest)
    if scene is None:
        if len(_SCENES) >= 64:
            _SCENES.clear()
        scene = mesh_scene(mesh)
        _SCENES[mesh.digest] = scene
    return scene


_SCENES: dict[bytes, Any] = {}


def _box(
    mesh: Mesh, cam_T_model: np.ndarray, K: np.ndarray, width: int, height: int
) -> Rect | None:
    """A rectangle holding every vertex's projection, and a pixel more, clipped to the
    image (empty when out of view); None when a cluster may reach the camera's plane.

    A cluster's points lie within ``rho = |R|_2 r`` of its centre ``q`` once placed; their
    normalised image coordinates within ``rho |q| / ((q_z - rho) q_z)`` of the centre's
    (the difference is ``(d_xy q_z - q_xy d_z) / (z q_z)``), and their pixels within
    ``|K_2x2|_2`` times that."""
    clusters = clusters_of(mesh.vertices, _BOX_CLUSTER_POINTS)
    R, t = cam_T_model[:3, :3], cam_T_model[:3, 3]
    q = clusters.centres @ R.T + t
    rho = _norm_bound(R) * clusters.radii * (1.0 + 1e-9) + 1e-9
    qz = q[:, 2]
    if not np.all(qz - rho > 0):
        return None
    spread = _norm_bound(K[:2, :2]) * rho * np.linalg.norm(q, axis=1) / ((qz - rho) * qz)
    x, y = q[:, 0] / qz, q[:, 1] / qz
    u, v = K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]
    x0 = int(np.floor((u - spread).min())) - _MARGIN_PX
    y0 = int(np.floor((v - spread).min())) - _MARGIN_PX
    x1 = int(np.ceil((u + spread).max())) + _MARGIN_PX + 1
    y1 = int(np.ceil((v + spread).max())) + _MARGIN_PX + 1
    return clip_region((x0, y0, x1, y1), width, height)


def _norm_bound(M: np.ndarray) -> float:
    """An upper bound of the spectral norm of ``M``: the square root of the largest absolute
    row sum of ``M^T M`` (Gershgorin), 1 for a rotation; an SVD costs ten times as much."""
    return float(np.sqrt(np.abs(M.T @ M).sum(axis=1).max()))
