"""The surface a pile rests on, from measured depth (the empty bin's, or the scene's away
from the parts): the floor's plane, which gives gravity's direction too, and the measured
surface itself (the bin's walls included) as a mesh (see :mod:`annotator.physics` for the
conventions)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.geometry.open3d_lib import o3d
from annotator.rendering.raycast import get_threads, mesh_scene

#: Points within this distance (mm) of a candidate plane count for it.
INLIER_MM = 2.0
#: The measured support this high (mm) above the floor's plane is something else (a wall).
WALL_MM = 4.0
#: How far (mm) a measured wall may be off where it is: depth seen at a grazing angle, mixed
#: with the floor's and the parts' at their edges.
WALL_SLACK_MM = 1.5


@dataclass(frozen=True)
class SupportPlane:
    """``n . x + d = 0`` in the camera frame, ``n`` (3,) the unit normal pointing up."""

    n: np.ndarray
    d: float

    def height(self, points: np.ndarray) -> np.ndarray:
        """(N,) height (mm) of ``points`` (3, N) above the plane."""
        return self.n @ points + self.d

    def to_json(self) -> dict[str, object]:
        return {"normal": [round(float(x), 6) for x in self.n], "offset_mm": round(self.d, 3)}


def fit_support_plane(
    points: np.ndarray, *, seed: int = 0, iterations: int = 300, min_share: float = 0.25
) -> SupportPlane | None:
    """The dominant plane of ``points`` (N, 3, camera frame, mm), its normal turned towards
    the camera (the origin); None with fewer than 100 points or no plane holding
    ``min_share`` of them. RANSAC on three points, then least squares on the inliers.

    >>> rng = np.random.default_rng(1)
    >>> xy = rng.uniform(-100, 100, (500, 2))
    >>> floor = np.c_[xy, 600 + 0.1 * xy[:, 0]]  # a floor seen from 600 mm, tilted
    >>> plane = fit_support_plane(floor)
    >>> round(float(plane.height(np.array([[0.0], [0.0], [0.0]]))[0]), 1)  # the camera
    597.0
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) < 100:
        return None
    rng = np.random.default_rng(seed)
    best, best_count = None, 0
    for _ in range(iterations):
        a, b, c = pts[rng.choice(len(pts), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            continue
        n /= norm
        count = int((np.abs(pts @ n - n @ a) < INLIER_MM).sum())
        if count > best_count:
            best, best_count = (n, float(-n @ a)), count
    if best is None or best_count < len(pts) * min_share:
        return None
    n, d = best
    inliers = pts[np.abs(pts @ n + d) < INLIER_MM]
    centre = inliers.mean(axis=0)
    spread = inliers - centre
    n = np.linalg.eigh(spread.T @ spread)[1][:, 0]  # the direction of least spread
    d = float(-n @ centre)
    if d < 0:  # the camera (origin) is above the support
        n, d = -n, -d
    return SupportPlane(n, d)


def depth_grid(depth: np.ndarray, camera: Camera, *, step: int = 4) -> np.ndarray:
    """(H', W', 3) points of a depth map (z-depth, mm; NaN or 0 where none) of ``camera``,
    in its frame, on a grid of every ``step``-th pixel; NaN where there is no depth."""
    rays = camera.pixel_rays(step)
    z = depth[::step, ::step].astype(np.float64)
    z = np.where(np.isfinite(z) & (z > 0), z, np.nan)
    return rays * z[..., None]


def grid_surface(grid: np.ndarray, *, max_edge_mm: float = 15.0) -> Mesh | None:
    """The surface through a grid of points (H, W, 3; NaN where none): two triangles per
    cell of four neighbours, those with a corner missing or an edge longer than
    ``max_edge_mm`` (a jump in depth, not a surface) left out; None if none is left."""
    h, w = grid.shape[:2]
    idx = np.arange(h * w).reshape(h, w)
    quads = np.stack(
        [idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()],
        axis=1,
    )
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    v = grid.reshape(-1, 3)
    corners = v[tris]  # (T, 3, 3)
    ok = np.all(np.isfinite(corners), axis=(1, 2))
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)
    ok &= np.all(np.nan_to_num(edges, nan=np.inf) < max_edge_mm, axis=1)
    if not ok.any():
        return None
    used, faces = np.unique(tris[ok], return_inverse=True)
    return Mesh(v[used], faces.reshape(-1, 3).astype(np.int32))


@dataclass(frozen=True, eq=False)
class Support:
    """What a pile rests on, in the scene's frame: the floor's plane (gravity is against
    its normal) and, where depth measured it, the support's surface (the bin's floor and
    walls) as a mesh."""

    plane: SupportPlane
    surface: Mesh | None = None
    #: How far (mm) the surface is taken to lie below where its vertices say.
    surface_lowered_by: float = 0.0

    def lowered(self, offset: float) -> Support:
        """The support ``offset`` mm lower (higher if negative), surface and all."""
        n = self.plane.n
        return Support(
            SupportPlane(n, self.plane.d + offset),
            self.surface,
            self.surface_lowered_by + offset,
        )

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(N,) how far (mm) each of ``points`` (3, N) is from the support: its height above
        the floor's plane (0 below it), or less where the measured surface away from the
        floor (a bin's wall, which holds a part leaning on it) is nearer, give or take
        :data:`WALL_SLACK_MM`."""
        d = np.maximum(self.plane.height(points), 0.0)
        if self.surface is None or not points.shape[1]:
            return d
        return self._with_surface(self._raised(points), d)[0]

    def least_distance(self, points: np.ndarray) -> float:
        """``distance(points).min()`` (``points`` (3, N), N > 0), with the measured surface
        asked about fewer points: its closest-point queries are the cost of
        :meth:`distance`, and most of a part's points cannot be the nearest.

        A point's distance to the surface changes no faster than the point moves, so every
        :data:`_PROBE_EVERY`-th point (a probe) is asked first; another point within ``r``
        of a probe at ``D`` from the surface is at least ``D - r`` from it. A point whose
        bound leaves the wall further than its height has its height for distance; one
        whose bound is beyond the least distance found cannot be the least. Only the
        others are asked: the same minimum as :meth:`distance`, to the bit."""
        d = np.maximum(self.plane.height(points), 0.0)
        if self.surface is None:
            return float(d.min())
        raised = self._raised(points)
        probe = np.zeros(len(raised), bool)
        probe[::_PROBE_EVERY] = True
        found, reach = self._with_surface(raised[probe], d[probe])
        least = float(found.min())
        rest, rest_d = raised[~probe], d[~probe]
        if not len(rest):
            return least
        ask = _unsettled(rest, np.minimum(rest_d, least), raised[probe], reach)
        # The others' distance is their height, or no less than ``least``: either way their
        # height stands for it in the minimum.
        if not ask.all():
            least = min(least, float(rest_d[~ask].min()))
        if ask.any():
            least = min(least, float(self._with_surface(rest[ask], rest_d[ask])[0].min()))
        return least

    def _raised(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) ``points`` (3, N) raised by :attr:`surface_lowered_by`: the points are
        moved rather than the surface lowered, so its BVH stays the one built."""
        return points.T + self.surface_lowered_by * self.plane.n

    def _with_surface(self, raised: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The distances ``d`` (the points' height above the floor's plane, 0 below it) of
        the :meth:`_raised` points, lowered where the measured surface off the floor is
        nearer (see :meth:`distance`), and each point's distance to the measured surface."""
        assert self.surface is not None
        query = o3d.core.Tensor(np.ascontiguousarray(raised, dtype=np.float32))
        near = _scene_of(self.surface).compute_closest_points(query, nthreads=get_threads())
        q = near["points"].numpy().astype(np.float64)
        reach = np.linalg.norm(q - raised, axis=1)
        # Near the floor the measured surface is the floor, smeared where it meets a wall:
        # the plane says it better.
        far = np.where(self.plane.height(q.T) - self.surface_lowered_by < WALL_MM, np.inf, reach)
        return np.minimum(d, np.maximum(far - WALL_SLACK_MM, 0.0)), reach


def _unsettled(
    points: np.ndarray, limit: np.ndarray, probes: np.ndarray, reach: np.ndarray
) -> np.ndarray:
    """(N,) which of ``points`` (N, 3) no probe (M, 3; at ``reach`` (M,) from the surface)
    bounds off the surface by ``limit`` (N,) or more, :data:`WALL_SLACK_MM` and
    :data:`_ROUNDING_MM` kept: :meth:`Support.least_distance`'s points to ask about.

    The probes furthest from the surface settle most points: they are tried first, alone,
    and the others only for the points they leave (every probe for every point made most
    of the cost of :meth:`Support.least_distance`'s bounds). A point is settled by one
    probe or by none, whichever probes are tried first: the same points are asked."""
    limit = limit + WALL_SLACK_MM + _ROUNDING_MM
    far = np.argsort(reach)[::-1][:_FAR_PROBES]
    left = np.flatnonzero(_bound(points, probes[far], reach[far]) < limit)
    if len(left):
        left = left[_bound(points[left], probes, reach) < limit[left]]
    ask = np.zeros(len(points), bool)
    ask[left] = True
    return ask


def _bound(points: np.ndarray, probes: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """(N,) the least distance to the surface that the ``probes`` (M, 3, at ``reach``
    (M,) from it) leave each of ``points`` (N, 3): the surface is no nearer to a point
    than to a probe, less the way between them."""
    return np.max(reach[None, :] - _distances(points, probes), axis=1)


def _distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) distances between the points ``a`` (N, 3) and ``b`` (M, 3), from one product
    of the two (the differences of every pair would cost several times more), about their
    mean: the expansion's rounding stays far below :data:`_ROUNDING_MM`."""
    centre = b.mean(axis=0)
    a, b = a - centre, b - centre
    squared = np.sum(a * a, axis=1)[:, None] + np.sum(b * b, axis=1)[None, :] - 2.0 * (a @ b.T)
    return np.sqrt(np.maximum(squared, 0.0))


#: :meth:`Support.least_distance` asks the measured surface about every this-many-th point
#: first.
_PROBE_EVERY = 16
#: :func:`_unsettled` tries this many probes (those furthest from the surface) first.
_FAR_PROBES = 8
#: Its bounds are kept this far (mm) below what they say: the surface's closest points are
#: found in float32.
_ROUNDING_MM = 0.01


# Ray-casting scenes of measured surfaces, by geometry (the empty bin's serves every scene).
_SURFACES: dict[bytes, Any] = {}


def _scene_of(surface: Mesh) -> Any:
    scene = _SURFACES.get(surface.digest)
    if scene is None:
        if len(_SURFACES) >= 4:
            _SURFACES.clear()
        scene = mesh_scene(surface)
        _SURFACES[surface.digest] = scene
    return scene
