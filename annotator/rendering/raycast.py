"""Pixel-exact ray casting of posed meshes into an OpenCV camera, with lens distortion.

One :class:`PlacedMesh` per object in the scene (a mesh and its pose in the camera's frame);
:func:`render` casts one ray per pixel centre of the camera (or of a pixel rectangle) and
returns, per pixel, the z-depth, which placed mesh was hit, the triangle and its barycentric
coordinates. Everything that needs to know "what is seen where" (synthetic images, masks and
occlusion, overlays, depth agreement) is built on this.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from annotator.geometry import Rect
from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.geometry.open3d_lib import o3d

#: ``instance`` value of a pixel whose ray hits nothing.
NO_HIT = -1

_threads = 0  # open3d's "automatic": every core


def set_threads(n: int) -> None:
    """Threads of every later BVH build and cast in this process (0: every core). Batch
    workers use one each: the workers are the parallelism."""
    global _threads
    _threads = int(n)


def get_threads() -> int:
    """The setting of :func:`set_threads`."""
    return _threads


def mesh_scene(mesh: Mesh) -> Any:
    """An open3d ray-casting scene of ``mesh`` alone, in its own frame, on this process's
    casting threads (:func:`set_threads`); its search structure is built on the first
    query. Callers that query one mesh often keep it (per ``mesh.digest``)."""
    scene = o3d.t.geometry.RaycastingScene(nthreads=_threads)
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices.astype(np.float32)),
        o3d.core.Tensor(mesh.faces.astype(np.uint32)),
    )
    return scene


@dataclass(frozen=True)
class PlacedMesh:
    """A mesh placed in a camera frame: ``x_cam = cam_T_model @ x_model``."""

    mesh: Mesh
    cam_T_model: np.ndarray


@dataclass(frozen=True)
class Hits:
    """Per-ray results of a cast; arrays share the leading shape of the rays.

    Attributes:
        depth: float32 ray parameter; the z-depth in mm for rays ``(x, y, 1)``; inf on a miss.
        instance: int32 index of the hit :class:`PlacedMesh`, :data:`NO_HIT` on a miss.
        triangle: int32 index of the hit triangle within its mesh (-1 on a miss).
        barycentric: float32 (..., 2) ``(u, v)`` of the hit: ``p = (1-u-v) a + u b + v c``.
    """

    depth: np.ndarray
    instance: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """Boolean mask of rays that hit something."""
        return self.instance != NO_HIT

    def model_points(self, placed: Sequence[PlacedMesh]) -> np.ndarray:
        """Model-frame coordinates of each hit (NaN on a miss), shape (..., 3)."""
        out = np.full((*self.instance.shape, 3), np.nan)
        hit = self.hit
        tri = stacked_triangles(placed)[
            _global_triangle(placed, self.instance[hit], self.triangle[hit])
        ]
        uv = self.barycentric[hit].astype(np.float64)
        out[hit] = (
            (1.0 - uv[:, :1] - uv[:, 1:]) * tri[:, 0]
            + uv[:, :1] * tri[:, 1]
            + uv[:, 1:] * tri[:, 2]
        )
        return out

    def normals(self, placed: Sequence[PlacedMesh]) -> np.ndarray:
        """Unit face normals of each hit in the frame the meshes are placed in (0 on a miss)."""
        normals = np.concatenate(
            [pm.mesh.face_normals @ pm.cam_T_model[:3, :3].T for pm in placed] + [np.zeros((1, 3))]
        ).astype(np.float32)
        offsets = np.cumsum([0] + [len(pm.mesh.faces) for pm in placed])
        # A miss (instance -1) picks the last offset, the row of zeros.
        return normals[offsets[self.instance] + np.maximum(self.triangle, 0)]


def stacked_triangles(placed: Sequence[PlacedMesh]) -> np.ndarray:
    """(sum of M, 3, 3) model-frame triangles of all placed meshes, in order."""
    return np.concatenate([pm.mesh.triangles for pm in placed])


def _global_triangle(
    placed: Sequence[PlacedMesh], instance: np.ndarray, triangle: np.ndarray
) -> np.ndarray:
    offsets = np.cumsum([0] + [len(pm.mesh.faces) for pm in placed])
    return offsets[instance] + triangle


class RayScene:
    """An open3d ray-casting scene of placed meshes, in one camera frame.

    Build it once per (scene, camera) and cast as many ray bundles as needed; building costs
    about as much as one full-image cast (the BVH).
    """

    def __init__(self, placed: Sequence[PlacedMesh]) -> None:
        self.placed = list(placed)
        self._scene = o3d.t.geometry.RaycastingScene(nthreads=_threads)
        self._geometry_to_index: dict[int, int] = {}
        for k, pm in enumerate(self.placed):
            T = np.asarray(pm.cam_T_model, dtype=np.float64)
            verts = (pm.mesh.vertices @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
            gid = self._scene.add_triangles(
                o3d.core.Tensor(verts), o3d.core.Tensor(pm.mesh.faces.astype(np.uint32))
            )
            self._geometry_to_index[int(gid)] = k
        self._lut = np.full(max(self._geometry_to_index, default=0) + 2, NO_HIT, dtype=np.int32)
        for gid, k in self._geometry_to_index.items():
            self._lut[gid] = k
        # open3d numbers a new scene's meshes in order from 0: then an id is its index.
        self._ids_in_order = all(gid == k for gid, k in self._geometry_to_index.items())

    def cast(self, directions: np.ndarray, origin: np.ndarray | None = None) -> Hits:
        """Cast rays from ``origin`` (default: the camera centre) along ``directions`` (..., 3)."""
        shape = directions.shape[:-1]
        # open3d's rays in one array made once (the directions rounded to float32 as
        # astype rounds them): no intermediate copies of a large bundle.
        rays = np.empty((int(np.prod(shape)), 6), np.float32)
        start = np.zeros(3, np.float32) if origin is None else np.asarray(origin, np.float32)
        for k in range(3):  # a column at a time: twice as fast as one strided (N, 3) fill
            rays[:, k] = start[k]
        rays[:, 3:] = np.asarray(directions).reshape(-1, 3)
        if not self.placed:
            return Hits(
                depth=np.full(shape, np.inf, np.float32),
                instance=np.full(shape, NO_HIT, np.int32),
                triangle=np.full(shape, -1, np.int32),
                barycentric=np.zeros((*shape, 2), np.float32),
            )
        res = self._scene.cast_rays(o3d.core.Tensor(rays), nthreads=_threads)
        # open3d's arrays are this call's own: read in place, no copies (large casts spent
        # as long converting them as casting).
        gid = res["geometry_ids"].numpy()
        miss = gid == o3d.t.geometry.RaycastingScene.INVALID_ID
        # A miss's ids are INVALID_ID (2**32 - 1): -1 (NO_HIT) once read as int32, as a
        # miss's triangle is; the LUT's last entry is NO_HIT, which a miss's index picks.
        if self._ids_in_order:
            instance = gid.view(np.int32)
        else:
            instance = self._lut[np.minimum(gid, len(self._lut) - 1)]
        tri = res["primitive_ids"].numpy().view(np.int32)
        depth = res["t_hit"].numpy()
        depth[miss] = np.inf
        return Hits(
            depth=depth.reshape(shape),
            instance=instance.reshape(shape),
            triangle=tri.reshape(shape),
            barycentric=res["primitive_uvs"].numpy().reshape(*shape, 2),
        )


_MODEL_SCENES: dict[bytes, RayScene] = {}


def cast_alone(
    mesh: Mesh, cam_T_model: np.ndarray, rays: np.ndarray, *, origin: np.ndarray | None = None
) -> Hits:
    """Cast camera rays (..., 3) at one placed mesh, alone.

    The rays are brought into the model frame, where the mesh's ray-casting scene lives,
    built once per process and kept by content (a mesh loaded again reuses it), so one BVH
    serves every copy of a part in every scene and camera. Depths are unchanged (a rigid
    motion keeps ray parameters); ``Hits.instance`` is 0 on a hit. ``origin``: the rays'
    common start in the camera frame (default its centre).
    """
    scene = _MODEL_SCENES.get(mesh.digest)
    if scene is None:
        if len(_MODEL_SCENES) >= 64:
            _MODEL_SCENES.clear()
        scene = _MODEL_SCENES[mesh.digest] = RayScene([PlacedMesh(mesh, np.eye(4))])
    R, t = cam_T_model[:3, :3], cam_T_model[:3, 3]
    start = -R.T @ t if origin is None else R.T @ (np.asarray(origin, float) - t)
    return scene.cast(rays @ R, origin=start)


def cast_separately(
    rays: np.ndarray,
    placed: Sequence[PlacedMesh],
    boxes: Sequence[Rect | None],
    *,
    behind: Hits | None = None,
    first: int = 0,
    surface: bool = True,
) -> tuple[Hits, list[Hits | None]]:
    """Cast a grid of rays (H, W, 3) at each placed mesh alone, over its box of the grid
    (:func:`cast_alone`), and keep the nearest hit of each ray: what one cast at a scene of
    all the meshes gives, up to float rounding (on exactly equal depths the earlier mesh wins).

    It is also several times faster: a ray costs little more in a part's own small BVH than
    the bare overhead of a cast, and a part's box is a small share of the image.

    Args:
        rays: The grid of ray directions, e.g. :meth:`Camera.pixel_rays`.
        placed: The meshes in the rays' frame.
        boxes: Per mesh, the rectangle of the grid it can be seen in (e.g.
            :func:`projected_bbox`), None for a mesh out of view.
        behind: Hits of other geometry on the whole grid (what the meshes stand in front of,
            e.g. :func:`render_once` of a scene's fixed surroundings); by default nothing.
        first: ``Hits.instance`` of ``placed[0]`` in the result (the rest follow).
        surface: False when only which mesh is nearest, and how far, is needed (see
            :func:`nearest`).

    Returns:
        The nearest hits on the grid, and per mesh its own hits over its box (None where its
        box is None).
    """
    own = [
        None if r is None else cast_alone(pm.mesh, pm.cam_T_model, rays[r[1] : r[3], r[0] : r[2]])
        for pm, r in zip(placed, boxes)
    ]
    together = nearest(rays.shape[:2], boxes, own, behind=behind, first=first, surface=surface)
    return together, own


def nearest(
    shape: tuple[int, int],
    boxes: Sequence[Rect | None],
    own: Sequence[Hits | None],
    *,
    behind: Hits | None = None,
    first: int = 0,
    surface: bool = True,
) -> Hits:
    """The nearest of several meshes' own hits (each over its box of a grid of ``shape``), in
    front of ``behind``; see :func:`cast_separately`. ``surface=False``: which mesh and how
    far only (``triangle`` -1 and ``barycentric`` 0 everywhere), at half the cost."""
    if behind is None:
        depth = np.full(shape, np.inf, np.float32)
        instance = np.full(shape, NO_HIT, np.int32)
    else:
        depth, instance = behind.depth.copy(), behind.instance.copy()
    if not surface:
        triangle = np.broadcast_to(np.int32(-1), shape)
        bary = np.broadcast_to(np.float32(0.0), (*shape, 2))
    elif behind is None:
        triangle = np.full(shape, -1, np.int32)
        bary = np.zeros((*shape, 2), np.float32)
    else:
        triangle, bary = behind.triangle.copy(), behind.barycentric.copy()
    for k, (box, h) in enumerate(zip(boxes, own)):
        if box is None or h is None:
            continue
        x0, y0, x1, y1 = box
        closer = h.depth < depth[y0:y1, x0:x1]
        np.copyto(depth[y0:y1, x0:x1], h.depth, where=closer)
        np.copyto(instance[y0:y1, x0:x1], first + k, where=closer)
        if surface:
            np.copyto(triangle[y0:y1, x0:x1], h.triangle, where=closer)
            np.copyto(bary[y0:y1, x0:x1], h.barycentric, where=closer[..., None])
    return Hits(depth, instance, triangle, bary)


_ONCE: dict[tuple, Hits] = {}


def render_once(camera: Camera, placed: Sequence[PlacedMesh]) -> Hits:
    """:func:`render` of geometry that stays where it is from one scene to the next (a bin,
    a table), kept by content and made again only when the camera or the geometry changes.
    The arrays are read-only."""
    key = (
        camera.grid_key,
        tuple((pm.mesh.digest, np.asarray(pm.cam_T_model, float).tobytes()) for pm in placed),
    )
    hits = _ONCE.get(key)
    if hits is None:
        hits = render(camera, placed)
        for a in (hits.depth, hits.instance, hits.triangle, hits.barycentric):
            a.setflags(write=False)
        if len(_ONCE) >= 4:  # a rig's cameras and projector; each is 20 bytes a pixel
            _ONCE.clear()
        _ONCE[key] = hits
    return hits


def render_scene(
    camera: Camera, placed: Sequence[PlacedMesh], *, fixed: int = 0
) -> tuple[Hits, list[tuple[Rect, Hits] | None]]:
    """:func:`render` of a scene whose first ``fixed`` meshes are its unchanging surroundings
    (a table, a bin: :func:`render_once`), the others cast each alone over the rectangle of
    the rays that can hit it (:func:`hit_bbox`, :func:`cast_separately`). Returns the hits,
    and per mesh after the fixed ones its rectangle and its own hits there (None when out of
    view)."""
    behind = render_once(camera, placed[:fixed]) if fixed else None
    rects = [hit_bbox(camera, pm.mesh, pm.cam_T_model) for pm in placed[fixed:]]
    hits, own = cast_separately(
        camera.pixel_rays(), placed[fixed:], rects, behind=behind, first=fixed
    )
    return hits, [None if r is None or h is None else (r, h) for r, h in zip(rects, own)]


def render(
    camera: Camera,
    placed: Sequence[PlacedMesh],
    *,
    region: tuple[int, int, int, int] | None = None,
    scene: RayScene | None = None,
) -> Hits:
    """Render placed meshes into ``camera``, one ray per pixel centre, distortion included.

    Args:
        camera: The camera; ``placed`` poses are in its frame.
        placed: The meshes and their poses; ``Hits.instance`` indexes this sequence.
        region: Optional pixel rectangle ``(x0, y0, x1, y1)`` (end exclusive, clipped to the
            image); the result then has shape (y1 - y0, x1 - x0).
        scene: A :class:`RayScene` already built from ``placed``, to reuse its BVH.

    Returns:
        Per-pixel :class:`Hits` of shape (height, width) or the region's shape.
    """
    rays = camera.pixel_rays()
    if region is not None:
        x0, y0, x1, y1 = clip_region(region, camera.width, camera.height)
        rays = rays[y0:y1, x0:x1]
    return (scene or RayScene(placed)).cast(rays)


def clip_region(
    region: tuple[int, int, int, int], width: int, height: int
) -> tuple[int, int, int, int]:
    """Clip a pixel rectangle ``(x0, y0, x1, y1)`` (end exclusive) to the image."""
    x0, y0, x1, y1 = (int(v) for v in region)
    x0, x1 = max(0, min(x0, width)), max(0, min(x1, width))
    y0, y1 = max(0, min(y0, height)), max(0, min(y1, height))
    return x0, y0, max(x0, x1), max(y0, y1)


def projected_bbox(
    camera: Camera, mesh: Mesh, cam_T_model: np.ndarray, *, margin: int = 2
) -> tuple[int, int, int, int] | None:
    """Pixel rectangle ``(x0, y0, x1, y1)`` covering the projection of a placed mesh's bounding
    box (distortion included), clipped to the image; None if entirely behind or outside."""
    lo, hi = mesh.bounds
    # Distortion bends straight edges: project a grid through the box, not just its corners.
    s = np.linspace(0.0, 1.0, 7)
    grid = np.stack(np.meshgrid(s, s, s, indexing="ij"), axis=-1).reshape(-1, 3)
    pts = lo + grid * (hi - lo)
    cam = pts @ cam_T_model[:3, :3].T + cam_T_model[:3, 3]
    if np.all(cam[:, 2] <= 0):
        return None
    if np.any(cam[:, 2] <= 0):
        return (0, 0, camera.width, camera.height)
    uv = camera.project(cam)
    x0, y0 = np.floor(uv.min(axis=0)).astype(int) - margin
    x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + margin + 1
    box = clip_region((x0, y0, x1, y1), camera.width, camera.height)
    return None if box[0] >= box[2] or box[1] >= box[3] else box


#: How far (normalised image coordinates) a ray may pass outside its mesh's projected
#: vertices and still hit it: float32 rounding of rays and vertices, by far less (1e-4 is
#: about a tenth of a pixel).
_HIT_SLACK = 1e-4

# Per camera grid: each row's range of ray y and each column's range of ray x.
_RANGES: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}


def _ray_ranges(camera: Camera, step: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Of the camera's grid of rays (:meth:`Camera.pixel_rays`): per row the least and
    greatest y of its rays, per column the least and greatest x (lens distortion bends
    rows and columns)."""
    key = (camera.grid_key, step)
    found = _RANGES.get(key)
    if found is None:
        rays = camera.pixel_rays(step)
        y, x = rays[..., 1], rays[..., 0]
        found = (y.min(axis=1), y.max(axis=1), x.min(axis=0), x.max(axis=0))
        if len(_RANGES) > 16:
            _RANGES.clear()
        _RANGES[key] = found
    return found


def hit_bbox(
    camera: Camera, mesh: Mesh, cam_T_model: np.ndarray, *, step: int = 1, margin: int = 0
) -> tuple[int, int, int, int] | None:
    """A rectangle ``(x0, y0, x1, y1)`` of the camera's grid of every ``step``-th pixel
    (:meth:`Camera.pixel_rays`; sample indices, end exclusive) outside which none of its rays
    can hit the placed mesh, grown by ``margin`` samples; None when none can.

    A ray meets a triangle in front of the camera only through the triangle's projection,
    which lies within its vertices' projections: so the rays that can hit the mesh have
    undistorted image coordinates within the range of its vertices'. The rectangle holds the
    rows and columns with such rays, which is tighter than :func:`projected_bbox` (the box of
    the mesh's bounding box, turned with it) for a turned part: the same hits from fewer
    rays, found from a few numbers per row and column.
    """
    width, height = -(-camera.width // step), -(-camera.height // step)
    cam = mesh.vertices @ cam_T_model[:3, :3].T + cam_T_model[:3, 3]
    if np.any(cam[:, 2] <= 0):  # a vertex behind the camera: no such range
        loose = projected_bbox(camera, mesh, cam_T_model)
        if loose is None:
            return None
        x0, y0, x1, y1 = (-(-v // step) for v in loose)
    else:
        x, y = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
        row_lo, row_hi, col_lo, col_hi = _ray_ranges(camera, step)
        rows = np.flatnonzero((row_hi >= y.min() - _HIT_SLACK) & (row_lo <= y.max() + _HIT_SLACK))
        cols = np.flatnonzero((col_hi >= x.min() - _HIT_SLACK) & (col_lo <= x.max() + _HIT_SLACK))
        if len(rows) == 0 or len(cols) == 0:
            return None
        x0, y0, x1, y1 = int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1
    return clip_region((x0 - margin, y0 - margin, x1 + margin, y1 + margin), width, height)


def reachable(
    camera: Camera, mesh: Mesh, cam_T_model: np.ndarray, box: Rect, *, step: int = 1
) -> np.ndarray | None:
    """Of the rays of ``box`` (a rectangle ``(x0, y0, x1, y1)`` of the camera's grid of every
    ``step``-th pixel, sample indices, as :func:`hit_bbox` gives it), those that can hit the
    placed mesh: a boolean mask of the box's shape; None when any may (a vertex behind the
    camera).

    As in :func:`hit_bbox`, a ray that hits has undistorted image coordinates within the
    range of the mesh's projected vertices, and so along every direction of the image: each
    row of rays keeps those whose x lies within the bounds that a few directions' ranges
    set across the row's range of y. The rays left out (beside a turned or slanted part, the
    corners of its rectangle) would each cost a cast to miss.
    """
    cam = mesh.vertices @ cam_T_model[:3, :3].T + cam_T_model[:3, 3]
    if np.any(cam[:, 2] <= 0):
        return None
    along = (cam[:, :2] / cam[:, 2:]) @ _DIRECTIONS.T  # (V, K)
    low, high = along.min(axis=0) - _HIT_SLACK, along.max(axis=0) + _HIT_SLACK
    x0, y0, x1, y1 = box
    row_lo, row_hi = _ray_ranges(camera, step)[:2]
    # A ray at (x, y) of a row with y in [lo, hi]: c x + s y within [low, high] for every
    # direction (c, s), c > 0, bounds x whatever its y.
    c, s = _DIRECTIONS[:, 0], _DIRECTIONS[:, 1]
    sy_lo, sy_hi = s * row_lo[y0:y1, None], s * row_hi[y0:y1, None]  # (R, K)
    left = ((low - np.maximum(sy_lo, sy_hi)) / c).max(axis=1) - _HIT_SLACK
    right = ((high - np.minimum(sy_lo, sy_hi)) / c).min(axis=1) + _HIT_SLACK
    x = camera.pixel_rays(step)[y0:y1, x0:x1, 0]
    return (x >= left[:, None]) & (x <= right[:, None])


#: :func:`reachable`'s directions (c, s) of the image plane, c > 0 (x's own among them; y's
#: range is :func:`hit_bbox`'s rows).
_DIRECTIONS = np.array(
    [[np.cos(a), np.sin(a)] for a in np.radians([-67.5, -45.0, -22.5, 0.0, 22.5, 45.0, 67.5])]
)


def _vertices_bbox(
    camera: Camera, mesh: Mesh, cam_T_model: np.ndarray, *, margin: int = 1
) -> tuple[int, int, int, int] | None:
    """:func:`projected_bbox` for a camera without distortion, from the vertices themselves:
    a pixel centre that sees a triangle lies within its vertices' projections, so the box of
    every vertex's projection holds every pixel a cast can hit, and is much tighter than the
    bounding box's for a turned part (fewer rays, the same hits)."""
    cam = mesh.vertices @ cam_T_model[:3, :3].T + cam_T_model[:3, 3]
    if np.any(cam[:, 2] <= 0):
        return projected_bbox(camera, mesh, cam_T_model)
    x, y = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
    K = camera.K
    u, v = K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]
    x0, y0 = int(np.floor(u.min())) - margin, int(np.floor(v.min())) - margin
    x1, y1 = int(np.ceil(u.max())) + margin + 1, int(np.ceil(v.max())) + margin + 1
    box = clip_region((x0, y0, x1, y1), camera.width, camera.height)
    return None if box[0] >= box[2] or box[1] >= box[3] else box


def render_depth(
    mesh: Mesh, cam_T_model: np.ndarray, K: np.ndarray, width: int, height: int
) -> tuple[Rect, np.ndarray] | None:
    """One mesh's z-depth (mm, float32, 0 where it is not seen) in a pinhole camera without
    distortion, over the rectangle it projects into: ``(rect, depth)``, or None when it is out
    of view. BOP's evaluation renders models this way (its depth images have no distortion)."""
    camera = Camera("pinhole", int(width), int(height), np.asarray(K, float), np.zeros(5))
    box = _vertices_bbox(camera, mesh, cam_T_model)
    if box is None:
        return None
    x0, y0, x1, y1 = box
    # The pose is applied as written: a rotation that is not quite orthonormal (BOP's files
    # have them) deforms the mesh slightly, as a renderer given the matrix would.
    A = np.linalg.inv(cam_T_model)
    hits = cast_alone(
        mesh, np.eye(4), camera.pixel_rays()[y0:y1, x0:x1] @ A[:3, :3].T, origin=A[:3, 3]
    )
    depth = np.where(np.isfinite(hits.depth), hits.depth, np.float32(0.0)).astype(np.float32)
    return box, depth
