"""Placing square marker sites on a part's surface.

Conventions (FORMAT.md): a site is four corners ``TL, TR, BR, BL`` in the model frame, in
ArUco order as seen from outside the part. With ``r = (TR - TL) / size`` (marker right) and
``d = (BL - TL) / size`` (marker down), the outward normal is ``n = d x r``.

On curved patches (cylinders, cups) the corners are then moved to the nearest surface points,
so that they lie exactly on the part where the printed marker's corners are.

Algorithm: candidate centres are sampled evenly over the surface (seeded). A candidate is kept
if the square of side ``size`` in its tangent plane lies on the surface within
``flatness_tol`` mm (checked at a 5x5 grid of points over the square, and the surface normal
at those points must agree with the square's within ``max_normal_deg`` (15), so that a square never bridges
an edge), and if its circumscribed circle does not meet an accepted one (plus ``gap``). Flat
facets are tried first, centred, then the rest of the surface in a seeded random order.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from annotator.geometry.mesh import Mesh
from annotator.geometry.open3d_lib import o3d
from annotator.markers.sites import MarkerSites


@dataclass(frozen=True)
class MarkerLayout:
    """Marker sites on a part.

    Attributes:
        size: Side of the printed square, mm.
        corners: (S, 4, 3) corners, model frame, ArUco order.
        normals: (S, 3) outward unit normals.
        min_facing: Worst case, over 500 view directions spread over the sphere, of the number
            of markers facing the viewer (normal within 60 degrees of the direction to it).
    """

    size: float
    corners: np.ndarray
    normals: np.ndarray
    min_facing: int

    @property
    def sites(self) -> MarkerSites:
        return MarkerSites(size=self.size, corners=self.corners)


def fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` unit vectors spread evenly over the sphere."""
    k = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * k / n)
    theta = np.pi * (1 + 5**0.5) * k
    return np.column_stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)])


def facing_counts(
    normals: np.ndarray, directions: np.ndarray, *, max_angle_deg: float = 60.0
) -> np.ndarray:
    """For each view direction (towards the viewer), how many site normals face it."""
    if len(normals) == 0:
        return np.zeros(len(directions), dtype=int)
    return (directions @ normals.T > np.cos(np.radians(max_angle_deg))).sum(axis=1)


def square_corners(
    centre: np.ndarray, normal: np.ndarray, right: np.ndarray, size: float
) -> np.ndarray:
    """The (4, 3) ArUco-ordered corners of a square centred at ``centre`` with outward
    ``normal`` and ``right`` (TL -> TR) direction (made orthogonal to the normal here)."""
    n = normal / np.linalg.norm(normal)
    r = right - (right @ n) * n
    r /= np.linalg.norm(r)
    d = np.cross(r, n)  # so that d x r = n: seen from outside, rows go down
    h = size / 2
    return np.array(
        [
            centre - r * h - d * h,
            centre + r * h - d * h,
            centre + r * h + d * h,
            centre - r * h + d * h,
        ]
    )


def place_markers(
    mesh: Mesh,
    *,
    size: float,
    max_sites: int | None = None,
    flatness_tol: float = 0.35,
    gap: float | None = None,
    max_normal_deg: float = 15.0,
    seed: int = 0,
) -> MarkerLayout:
    """Place non-overlapping square sites of side ``size`` mm on flat-enough patches.

    Args:
        mesh: The part, mm.
        size: Printed marker side, mm.
        max_sites: Keep at most this many sites (default: as many as fit), chosen to cover every
            view direction as evenly as possible.
        flatness_tol: Largest distance, mm, between the square and the surface.
        gap: Extra clearance between sites' circumscribed circles (default ``size / 10``).
        max_normal_deg: Largest angle between the square and the surface normals under it.
        seed: Seed of the candidate order.
    """
    gap = size / 10 if gap is None else gap
    rng = np.random.default_rng(seed)
    fit = _SiteFit(mesh, _raycasting_scene(mesh), size, flatness_tol, max_normal_deg)
    radius = size / np.sqrt(2)
    kept_c: list[np.ndarray] = []
    kept: list[np.ndarray] = []
    kept_n: list[np.ndarray] = []
    for c, n in zip(*_candidates(mesh, size, rng)):
        if kept_c and np.min(np.linalg.norm(np.asarray(kept_c) - c, axis=1)) < 2 * radius + gap:
            continue
        corners = fit.corners(c, n)
        if corners is None:
            continue
        kept_c.append(c)
        kept.append(corners)
        kept_n.append(n)
    corners = np.asarray(kept).reshape(-1, 4, 3)
    nrm = np.asarray(kept_n).reshape(-1, 3)
    dirs = fibonacci_sphere(500)
    if max_sites is not None and len(corners) > max_sites:
        keep = _spread(nrm, dirs, max_sites)
        corners, nrm = corners[keep], nrm[keep]
    min_facing = int(facing_counts(nrm, dirs).min())
    return MarkerLayout(size=size, corners=corners, normals=nrm, min_facing=min_facing)


def _raycasting_scene(mesh: Mesh) -> Any:
    """open3d's scene of the part, for closest points on its surface."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices.astype(np.float32)),
        o3d.core.Tensor(mesh.faces.astype(np.uint32)),
    )
    return scene


class _SiteFit:
    """Whether a square site fits the surface at a candidate centre and normal."""

    def __init__(
        self, mesh: Mesh, scene: Any, size: float, flatness_tol: float, max_normal_deg: float
    ) -> None:
        self.mesh = mesh
        self.scene = scene
        self.size = size
        self.flatness_tol = flatness_tol
        self.cos_tol = np.cos(np.radians(max_normal_deg))
        u = np.linspace(-0.5, 0.5, 5) * size
        # Sampled across the square, not only at its corners: a bump in its middle shows.
        self.grid = np.stack(np.meshgrid(u, u), axis=-1).reshape(-1, 2)

    def corners(self, c: np.ndarray, n: np.ndarray) -> np.ndarray | None:
        """The (4, 3) corners of the site at ``c`` facing ``n``, glued to the surface; None if
        the surface under it is not flat enough, turns away, or ends under a corner."""
        size, scene = self.size, self.scene
        ref = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        corners = square_corners(c, n, np.cross(ref, n), size)
        r = (corners[1] - corners[0]) / size
        d = (corners[3] - corners[0]) / size
        pts = c + self.grid[:, :1] * r + self.grid[:, 1:] * d
        q = scene.compute_closest_points(o3d.core.Tensor(pts.astype(np.float32)))
        closest = q["points"].numpy()
        if np.max(np.linalg.norm(closest - pts, axis=1)) > self.flatness_tol:
            return None
        face_n = self.mesh.face_normals[q["primitive_ids"].numpy()]
        if np.min(face_n @ n) < self.cos_tol:
            return None
        # On a curved patch, glue the corners to the surface (the printed square bends onto it).
        on_surface = scene.compute_closest_points(o3d.core.Tensor(corners.astype(np.float32)))[
            "points"
        ].numpy()
        moved = on_surface - corners
        sideways = moved - np.outer(moved @ n, n)
        if np.linalg.norm(sideways, axis=1).max() > 0.1:  # a corner slid off the patch (an edge)
            return None
        return on_surface.astype(np.float64)


def _spread(normals: np.ndarray, dirs: np.ndarray, k: int, *, target: int = 4) -> np.ndarray:
    """Greedy choice of ``k`` sites that best cover every view direction: each step adds the site
    that most raises ``sum over directions of min(facing count, target)``, so the worst-covered
    directions are served first. Returns sorted indices."""
    faces = dirs @ normals.T > np.cos(np.radians(60.0))  # (D, S)
    counts = np.zeros(len(dirs), int)
    chosen: list[int] = []
    free = np.ones(len(normals), bool)
    for _ in range(k):
        need = counts < target
        gain = (faces & need[:, None]).sum(axis=0) + 1e-3 * faces.sum(axis=0)
        gain[~free] = -1
        j = int(np.argmax(gain))
        chosen.append(j)
        free[j] = False
        counts += faces[:, j]
    return np.array(sorted(chosen))


def _candidates(mesh: Mesh, size: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Candidate centres and normals: centres of large flat facets first, then surface samples."""
    tm = mesh.to_trimesh()
    first_c, first_n = [], []
    for facet, normal in zip(tm.facets, tm.facets_normal):
        area = mesh.face_areas[facet].sum()
        if area < size * size:
            continue
        tri = mesh.triangles[facet]
        w = mesh.face_areas[facet]
        first_c.append((tri.mean(axis=1) * w[:, None]).sum(axis=0) / w.sum())
        first_n.append(normal)
    n_samples = int(np.clip(mesh.moments.area / (size * size) * 8, 200, 4000))
    pts, face_idx = _sample_surface(mesh, n_samples, rng)
    order = rng.permutation(len(pts))
    centres = np.concatenate([np.asarray(first_c).reshape(-1, 3), pts[order]])
    normals = np.concatenate(
        [np.asarray(first_n).reshape(-1, 3), mesh.face_normals[face_idx[order]]]
    )
    return centres, normals


def _sample_surface(mesh: Mesh, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points drawn uniformly over the surface, and their faces."""
    p = mesh.face_areas / mesh.face_areas.sum()
    faces = rng.choice(len(p), size=n, p=p)
    a, b = rng.random(n), rng.random(n)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    tri = mesh.triangles[faces]
    pts = tri[:, 0] + a[:, None] * (tri[:, 1] - tri[:, 0]) + b[:, None] * (tri[:, 2] - tri[:, 0])
    return pts, faces


def assign_ids(n_sites: int, n_instances: int, *, start: int = 0) -> list[list[int]]:
    """Disjoint consecutive marker ids for ``n_instances`` copies of a part with ``n_sites`` sites."""
    return [list(range(start + k * n_sites, start + (k + 1) * n_sites)) for k in range(n_instances)]
