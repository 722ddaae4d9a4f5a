"""Posed bodies and the exact distances between them: how deep one reaches into another
(signed distances to the triangle mesh as it is) and how far one is from another's convex
hull (see :mod:`annotator.physics` for the conventions)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull

from annotator.errors import UserError
from annotator.geometry.mesh import Mesh, surface_samples
from annotator.geometry.open3d_lib import o3d
from annotator.geometry.transforms import invert
from annotator.rendering.raycast import get_threads, mesh_scene

#: Surface points drawn per body (every vertex is added to them).
SAMPLES = 3000
#: Rays that vote whether a point is inside a mesh (odd).
INSIDE_VOTES = 5
#: How far (mm) a point must lie beyond a plane of a hull to be taken as outside it without
#: asking the ray-casting scene, whose queries are float32's (errors of 1e-5 mm at most).
PLANE_SLACK_MM = 0.01
#: :func:`least_hull_distance` and :func:`depth_inside` ask about this many points first.
FIRST_ASKED = 8

# Ray-casting scenes of meshes (and of their hulls), by geometry: built once per process.
_SCENES: dict[tuple[bytes, bool], object] = {}
_HULLS: dict[bytes, Mesh] = {}
_HULL_PLANES: dict[bytes, np.ndarray] = {}
_HULL_CORNERS: dict[bytes, np.ndarray] = {}
# Surface samples of meshes (and with their vertices), by geometry: drawn once per process.
_DRAWN: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}
_MODEL_POINTS: dict[bytes, np.ndarray] = {}


@dataclass(frozen=True, eq=False)
class Body:
    """A part posed in the camera frame: ``key`` (``object/instance``), its mesh (mm, model
    frame) and ``T`` = ``cam_T_model`` (4x4)."""

    key: str
    mesh: Mesh
    T: np.ndarray

    @cached_property
    def points(self) -> np.ndarray:
        """(N, 3) surface points in the camera frame: every vertex and :data:`SAMPLES` drawn
        over the surface in proportion to area (the same for every copy of a mesh)."""
        return self.T[:3, :3] @ _model_points(self.mesh).T + self.T[:3, 3:4]

    @cached_property
    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        """(3, M) points drawn over the surface and their (3, M) outward normals, in the
        camera frame (those of :attr:`points` but the vertices)."""
        drawn, normals = _drawn(self.mesh)
        R = self.T[:3, :3]
        return R @ drawn.T + self.T[:3, 3:4], R @ normals.T

    @cached_property
    def box(self) -> tuple[np.ndarray, np.ndarray]:
        """The axis-aligned bounds (min, max) of the body in the camera frame."""
        pts = self.points.T
        return pts.min(axis=0), pts.max(axis=0)

    @cached_property
    def centroid(self) -> np.ndarray:
        """The surface centroid in the camera frame."""
        return self.T[:3, :3] @ self.mesh.moments.centroid + self.T[:3, 3]

    @cached_property
    def corners(self) -> np.ndarray:
        """(3, K) the corners of the body's convex hull in the camera frame."""
        return self.T[:3, :3] @ hull_corners(self.mesh).T + self.T[:3, 3:4]

    @cached_property
    def model_T_cam(self) -> np.ndarray:
        """The inverse of :attr:`T`: every pair and gap of a pile asks for it again."""
        return invert(self.T)

    def to_model(self, points: np.ndarray) -> np.ndarray:
        """``points`` (3, N) of the camera frame in this body's model frame, (N, 3)."""
        M = self.model_T_cam
        return (M[:3, :3] @ points + M[:3, 3:4]).T


def _drawn(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """About :data:`SAMPLES` points over the surface (model frame) and their normals; drawn
    once per mesh (by content) and process: every body of a scene asks for them."""
    hit = _DRAWN.get(mesh.digest)
    if hit is None:
        area = float(mesh.face_areas.sum())
        spacing = np.sqrt(12.0 * area / SAMPLES)  # surface_samples' density: 12 per spacing^2
        if len(_DRAWN) >= 64:
            _DRAWN.clear()
        hit = _DRAWN[mesh.digest] = surface_samples(mesh, spacing)
        for a in hit:
            a.setflags(write=False)
    return hit


def _model_points(mesh: Mesh) -> np.ndarray:
    hit = _MODEL_POINTS.get(mesh.digest)
    if hit is None:
        if len(_MODEL_POINTS) >= 64:
            _MODEL_POINTS.clear()
        hit = _MODEL_POINTS[mesh.digest] = np.concatenate([mesh.vertices, _drawn(mesh)[0]])
        hit.setflags(write=False)
    return hit


def check_solid(mesh: Mesh, path: Path) -> None:
    """Refuse, in one line naming the file, a mesh with no volume (:attr:`Mesh.is_flat`):
    contacts and penetrations are measured between solids."""
    if mesh.is_flat:
        raise UserError(
            "the mesh has no volume (its vertices lie on a plane or a line): the physics "
            "check needs a solid part",
            path=path,
        )


def hull_of(mesh: Mesh) -> Mesh:
    """The convex hull of ``mesh`` (faces as scipy gives them; the signed distance needs
    no winding)."""
    hit = _HULLS.get(mesh.digest)
    if hit is None:
        hull = ConvexHull(mesh.vertices)
        hit = _HULLS[mesh.digest] = Mesh(mesh.vertices, hull.simplices.astype(np.int32))
    return hit


def hull_planes(mesh: Mesh) -> np.ndarray:
    """(F, 4) the planes of :func:`hull_of`'s faces, ``n . x + d`` with ``n`` the outward
    unit normal: negative inside the hull (model frame). Each plane once: a face of the
    hull is several triangles."""
    hit = _HULL_PLANES.get(mesh.digest)
    if hit is None:
        planes = ConvexHull(mesh.vertices).equations
        first = np.unique(np.round(planes, 9), axis=0, return_index=True)[1]
        hit = _HULL_PLANES[mesh.digest] = np.ascontiguousarray(planes[np.sort(first)])
        hit.setflags(write=False)
    return hit


def hull_corners(mesh: Mesh) -> np.ndarray:
    """(K, 3) the vertices of ``mesh`` on its convex hull (model frame)."""
    hit = _HULL_CORNERS.get(mesh.digest)
    if hit is None:
        hit = _HULL_CORNERS[mesh.digest] = mesh.vertices[np.unique(hull_of(mesh).faces)]
        hit.setflags(write=False)
    return hit


def hulls_apart(a: Body, b: Body) -> bool:
    """Whether a plane of one body's hull leaves the other's hull wholly beyond it (by
    more than :data:`PLANE_SLACK_MM`): then neither reaches into the other, and no point
    need be cast. Most pairs whose bounds overlap are parts lying side by side."""
    for near, far in ((a, b), (b, a)):
        planes = hull_planes(far.mesh)
        corners = far.to_model(near.corners)
        if np.any(np.min(planes[:, :3] @ corners.T + planes[:, 3:], axis=1) > PLANE_SLACK_MM):
            return True
    return False


def outside_hull(mesh: Mesh, local: np.ndarray) -> np.ndarray:
    """(N,) how far ``local`` (N, 3, model frame) lies beyond the furthest plane of
    ``mesh``'s hull: no more than its distance to the hull (<= 0 inside). A few products,
    where the ray-casting scene's queries cost a microsecond or more a point."""
    planes = hull_planes(mesh)
    if not len(local):
        return np.zeros(0)
    return np.max(planes[:, :3] @ local.T + planes[:, 3:], axis=0)


def _scene(mesh: Mesh, *, hull: bool) -> Any:
    """The ray-casting scene of ``mesh`` or of its hull (its BVH built once per process)."""
    key = (mesh.digest, hull)
    scene = _SCENES.get(key)
    if scene is None:
        geometry = hull_of(mesh) if hull else mesh
        scene = mesh_scene(geometry)
        _SCENES[key] = scene
    return scene


def signed_distance(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    """(N,) signed distance (mm) of ``points`` (N, 3, model frame) to ``mesh``: negative
    inside the solid."""
    scene = _scene(mesh, hull=False)
    query = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
    # Inside or out is voted by several rays: one ray grazing an edge counts it twice.
    found = scene.compute_signed_distance(query, nthreads=get_threads(), nsamples=INSIDE_VOTES)
    return found.numpy().astype(np.float64)


def depth_inside(a: Body, b: Body) -> float:
    """How deep (mm, >= 0) ``a``'s surface reaches inside ``b``'s solid."""
    local = b.to_model(a.points[:, _near(a, b)])
    # Outside the mesh's own bounds (b's bounds in its model frame, tighter than those in
    # the camera's) is outside the solid: those points' signed distances, all positive,
    # could not be the deepest.
    lo, hi = b.mesh.bounds
    local = local[np.all((local >= lo - PLANE_SLACK_MM) & (local <= hi + PLANE_SLACK_MM), axis=1)]
    if len(local):  # outside the hull is outside the solid: only the others are asked
        hull = _scene(b.mesh, hull=True)
        query = o3d.core.Tensor(np.ascontiguousarray(local, dtype=np.float32))
        local = local[hull.compute_occupancy(query, nthreads=get_threads()).numpy() > 0.5]
    if len(local) == 0:
        return 0.0
    return _deepest(b.mesh, local)


def _deepest(mesh: Mesh, local: np.ndarray) -> float:
    """How deep (mm, >= 0) the deepest of ``local`` (N, 3, model frame; inside ``mesh``'s
    hull) lies inside the solid, the signed distance asked about few of them.

    A point inside the solid is no deeper in it than in its hull (the hull's boundary is
    outside the solid or on it), and its depth in the hull is a few products
    (:func:`outside_hull`). The points deepest in the hull are asked first; the others only
    if the hull leaves them room to be deeper than the deepest found (less
    :data:`PLANE_SLACK_MM`: the signed distances are float32's): the same depth as asking
    every point, to the bit."""
    room = -outside_hull(mesh, local)
    order = np.argsort(room, kind="stable")[::-1]
    first = order[:FIRST_ASKED]
    deepest = max(0.0, -float(signed_distance(mesh, local[first]).min()))
    rest = order[FIRST_ASKED:]
    rest = rest[room[rest] > deepest - PLANE_SLACK_MM]
    if len(rest):
        deepest = max(deepest, -float(signed_distance(mesh, local[rest]).min()))
    return deepest


def penetration(a: Body, b: Body) -> float:
    """How deep (mm, >= 0) the two solids overlap: the deepest surface point of either
    inside the other."""
    if hulls_apart(a, b):  # each is outside the other's hull, and so outside its solid
        return 0.0
    return max(depth_inside(a, b), depth_inside(b, a))


def hull_distance(points: np.ndarray, b: Body) -> np.ndarray:
    """(N,) distance (mm, 0 inside) of ``points`` (3, N, camera frame) to ``b``'s convex
    hull."""
    if points.shape[1] == 0:
        return np.zeros(0)
    return _hull_distance(b.mesh, b.to_model(points))


def least_hull_distance(points: np.ndarray, b: Body, below: float) -> float:
    """``hull_distance(points, b).min()`` where that is below ``below``, else no less than
    ``below`` (inf when no point can be nearer): the ray-casting scene is asked only about
    the points whose :func:`outside_hull` bound could be the least.

    The few points with the least bound are asked first; the least distance they find
    leaves out most of the others. The bound is kept :data:`PLANE_SLACK_MM` low (the
    casts are float32's) and each point's distance is the scene's own: the same minimum
    as :func:`hull_distance`'s, to the bit."""
    local = b.to_model(points)
    bound = outside_hull(b.mesh, local)
    ask = np.flatnonzero(bound < below + PLANE_SLACK_MM)
    if not len(ask):
        return np.inf
    order = ask[np.argsort(bound[ask], kind="stable")]
    least = float(_hull_distance(b.mesh, local[order[:FIRST_ASKED]]).min())
    rest = order[FIRST_ASKED:]
    rest = rest[bound[rest] < min(least, below) + PLANE_SLACK_MM]
    if len(rest):
        least = min(least, float(_hull_distance(b.mesh, local[rest]).min()))
    return least


def _hull_distance(mesh: Mesh, local: np.ndarray) -> np.ndarray:
    """(N,) distance (mm, 0 inside) of ``local`` (N, 3, model frame) to ``mesh``'s hull."""
    hull = _scene(mesh, hull=True)  # convex: one ray tells inside from outside
    query = o3d.core.Tensor(np.ascontiguousarray(local, dtype=np.float32))
    inside = hull.compute_occupancy(query, nthreads=get_threads()).numpy() > 0.5
    far = hull.compute_distance(query, nthreads=get_threads()).numpy().astype(np.float64)
    return np.where(inside, 0.0, far)


def _near(a: Body, b: Body, margin: float = 0.0) -> np.ndarray:
    """Which of ``a``'s points lie in ``b``'s bounds grown by ``margin`` (the others
    cannot be inside it)."""
    lo, hi = b.box
    pts = a.points
    return np.all((pts >= lo[:, None] - margin) & (pts <= hi[:, None] + margin), axis=0)


def overlapping_boxes(bodies: Sequence[Body]) -> list[tuple[int, int]]:
    """The pairs ``(i, j)``, ``i < j`` in order, of ``bodies`` whose bounds overlap (those
    :func:`boxes_overlap` tells apart), all at once: a pile has hundreds of pairs."""
    if not bodies:
        return []
    lo = np.array([b.box[0] for b in bodies])
    hi = np.array([b.box[1] for b in bodies])
    meets = np.all(lo[:, None, :] <= hi[None, :, :], axis=2)
    meets &= meets.T
    i, j = np.nonzero(np.triu(meets, 1))
    return list(zip(i.tolist(), j.tolist()))


def boxes_overlap(a: Body, b: Body, margin: float = 0.0) -> bool:
    """Whether the two bodies' bounds, grown by ``margin``, overlap."""
    (alo, ahi), (blo, bhi) = a.box, b.box
    return bool(np.all(alo <= bhi + margin) and np.all(blo <= ahi + margin))
