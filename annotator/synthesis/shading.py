"""Rendering intensity images: diffuse parts with their ArUco markers, lit from the camera.

Every pixel is ray cast through the exact (distorted) OpenCV pixel centre. Pixels on or next
to a marker are then supersampled on an ``n x n`` grid of sub-pixel positions (also exact rays
through the distorted image), which is what keeps the detected marker corners unbiased.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.rendering.raycast import Hits, PlacedMesh, RayScene, Rect, render_scene


@dataclass(frozen=True)
class Surface:
    """A mesh in the world with its appearance.

    Attributes:
        mesh: The mesh, model frame, mm.
        world_T_model: Its pose in the world.
        albedo: Diffuse reflectance of the bare surface, 0..1.
        sites: (S, 4, 3) marker corners (model frame) or None.
        bits: (S, c, c) uint8 marker cell grids (0 or 255) for the sites, or None.
    """

    mesh: Mesh
    world_T_model: np.ndarray
    albedo: float
    sites: np.ndarray | None = None
    bits: np.ndarray | None = None


@dataclass
class View:
    """What a camera sees of the scene at its pixel centres (used for depth simulation too)."""

    hits: Hits
    placed: list[PlacedMesh]
    normals_cam: np.ndarray  # (H, W, 3) unit normals in the camera frame (0 on a miss)
    albedo: np.ndarray  # (H, W) diffuse albedo, markers included
    on_marker: np.ndarray  # (H, W) bool: the pixel centre is on a marker
    #: Per surface after the fixed ones: its pixel rectangle and its own hits there, cast
    #: alone (None when out of view); occlusion rates are computed from these.
    own: list[tuple[Rect, Hits] | None] = field(default_factory=list)


def _albedo(
    surfaces: Sequence[Surface], placed: Sequence[PlacedMesh], hits: Hits
) -> tuple[np.ndarray, np.ndarray]:
    """Albedo at each hit (markers textured) and whether the hit is on a marker.

    Only hits on faces that can hold a point of a marker (see :func:`_face_sites`) are
    looked at: on a part most of the surface carries no marker. A hit's position in a
    site's printed square is an affine function of its barycentric coordinates, so the
    test needs no 3D point.
    """
    base = np.array([s.albedo for s in surfaces] + [0.0], np.float32)
    albedo = base[hits.instance]  # NO_HIT = -1 picks the trailing 0
    on_marker = np.zeros(hits.instance.shape, bool)
    textured = _textured(surfaces)
    if textured is None:
        return albedo, on_marker
    face_offset, grid, cell_offset, count, first, site, affine, bits = textured
    instance = hits.instance.reshape(-1)
    hit = np.flatnonzero(instance >= 0)
    face = face_offset[instance[hit]] + hits.triangle.reshape(-1)[hit]
    keep = grid[face] > 0
    hit, face = hit[keep], face[keep]
    uv = hits.barycentric.reshape(-1, 2)[hit]
    g = grid[face]
    gu = np.minimum((uv[:, 0] * g).astype(np.int32), g - 1)
    gv = np.minimum((uv[:, 1] * g).astype(np.int32), g - 1)
    cell = cell_offset[face] + gu * g + gv
    n = count[cell]
    keep = n > 0
    rows, cell, n = hit[keep], cell[keep], n[keep]
    u, v = uv[keep, 0], uv[keep, 1]
    pair = first[cell]
    # Sites never overlap, so at most one of a cell's candidate sites holds a point: try the
    # first candidate of every point, then the second of the points in cells with two or more.
    todo = np.arange(len(rows))
    found_rows, found_site, found_st = [], [], []
    for k in range(int(n.max(initial=0))):
        A = affine[pair[todo] + k]  # (m, 3, 3): (s, t, d) = A @ (1, u, v)
        uk, vk = u[todo], v[todo]
        s = A[:, 0, 0] + A[:, 0, 1] * uk + A[:, 0, 2] * vk
        t = A[:, 1, 0] + A[:, 1, 1] * uk + A[:, 1, 2] * vk
        d = A[:, 2, 0] + A[:, 2, 1] * uk + A[:, 2, 2] * vk
        inside = (s >= 0) & (s < 1) & (t >= 0) & (t < 1) & (np.abs(d) < MARKER_SLAB)
        found_rows.append(rows[todo[inside]])
        found_site.append(site[pair[todo[inside]] + k])
        found_st.append(np.stack([s[inside], t[inside]], axis=1))
        todo = todo[~inside & (n[todo] > k + 1)]
    target = np.concatenate(found_rows)
    sites = np.concatenate(found_site)
    c = bits.shape[1]
    ij = np.minimum((np.concatenate(found_st) * c).astype(int), c - 1)
    a_flat, m_flat = albedo.reshape(-1), on_marker.reshape(-1)
    a_flat[target] = np.where(bits[sites, ij[:, 1], ij[:, 0]] > 0, 0.92, 0.04)
    m_flat[target] = True
    return albedo, on_marker


#: A point is on a marker if it lies within this distance (mm) of the site's plane (a curved
#: part's surface bends away from the flat printed square).
MARKER_SLAB = 2.0
#: ... and if its face is within about 45 degrees of the site's orientation (cosine).
MARKER_FACING = 0.7


def _textured(
    surfaces: Sequence[Surface],
) -> tuple[np.ndarray, ...] | None:
    """The :class:`FaceSites` of every surface as flat arrays: per face (indexed by
    ``face_offset[surface] + triangle``) its grid and first cell, per cell its candidates, per
    candidate its site and affine map, per site its bits; None when no surface has a marker."""
    face_offset = np.cumsum([0] + [len(s.mesh.faces) for s in surfaces])
    parts: list[list[np.ndarray]] = [[] for _ in range(7)]
    cells = pairs = site_base = 0
    for s in surfaces:
        if s.sites is None or not len(s.sites):
            parts[0].append(np.zeros(len(s.mesh.faces), np.int32))  # grid 0: no candidate
            parts[1].append(np.zeros(len(s.mesh.faces), np.int32))
            continue
        assert s.bits is not None  # a Surface with sites has their bits
        fs = _face_sites(s.mesh, s.sites)
        for k, a in enumerate(
            (fs.grid, fs.cell_offset + cells, fs.count, fs.first + pairs, fs.site + site_base)
        ):
            parts[k].append(a)
        parts[5].append(fs.affine)
        parts[6].append(s.bits)
        cells += len(fs.count)
        pairs += len(fs.site)
        site_base += len(s.bits)
    if not parts[6]:
        return None
    return (face_offset, *(np.concatenate(p) for p in parts))


@dataclass(frozen=True)
class FaceSites:
    """For each face of a mesh, the marker sites a point of the face can lie on.

    A large face can meet many sites; so a face with more than one candidate is cut into a
    ``GRID x GRID`` grid of cells over its barycentric coordinates ``(u, v)``, and each cell
    keeps only the sites that reach it: a point is tested against one or two sites, not a
    dozen.

    Attributes:
        grid: (F,) the face's grid size: 0 (no candidate), 1 (one cell) or ``GRID``.
        cell_offset: (F,) the index of the face's first cell; the point ``(u, v)`` is in cell
            ``cell_offset + min(u * grid, grid - 1) * grid + min(v * grid, grid - 1)``
            (integer parts).
        count: (C,) how many candidate sites the cell has.
        first: (C,) the index of the cell's first candidate; a cell's candidates follow each
            other.
        site: (P,) each candidate's site.
        affine: (P, 3, 3) float32 per candidate: ``(s, t, d) = affine @ (1, u, v)`` takes a
            point's barycentric coordinates ``(u, v)`` on the face (``p = (1-u-v) a + u b +
            v c``) to its position across the printed square (``s`` along TL->TR and ``t``
            along TL->BL, both in [0, 1) on the square) and its distance ``d`` (mm) along the
            site's outward normal.
    """

    grid: np.ndarray
    cell_offset: np.ndarray
    count: np.ndarray
    first: np.ndarray
    site: np.ndarray
    affine: np.ndarray


#: Cells per side of the grid of a face that meets several sites.
GRID = 8

_FACE_SITES: dict[tuple[bytes, bytes], FaceSites] = {}


def _face_sites(mesh: Mesh, sites: np.ndarray) -> FaceSites:
    """The candidate sites of each face (and cell): facing the same way as the site (within
    :data:`MARKER_FACING`) and reaching the site's square and slab. (s, t, d) are affine on a
    face, so their ranges over a triangle or a cell are those over its corners; the ranges are
    widened by a hair, so that float rounding never drops a candidate. Cached per mesh and
    layout."""
    key = (mesh.digest, np.ascontiguousarray(sites).tobytes())
    cached = _FACE_SITES.get(key)
    if cached is not None:
        return cached
    tl = sites[:, 0]
    ex, ey = sites[:, 1] - tl, sites[:, 3] - tl
    normal = np.cross(ey, ex)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    frame = np.stack(
        [ex / (ex * ex).sum(1, keepdims=True), ey / (ey * ey).sum(1, keepdims=True), normal],
        axis=1,
    )  # (S, 3, 3): p - TL -> (s, t, d)
    # (F, S, 3 corners, 3 coordinates)
    corners = np.einsum("sij,fskj->fski", frame, mesh.triangles[:, None] - tl[None, :, None])
    reaches = _reaches(corners.min(axis=2), corners.max(axis=2))
    reaches &= mesh.face_normals @ normal.T > MARKER_FACING
    face, site = np.nonzero(reaches)  # row-major: a face's candidates are consecutive
    a, b, c = (corners[face, site, k] for k in range(3))
    affine = np.stack([a, b - a, c - a], axis=2)  # (P, 3, 3)
    per_face = np.bincount(face, minlength=len(mesh.faces))
    grid = np.where(per_face > 1, GRID, np.minimum(per_face, 1)).astype(np.int32)
    cell_offset = (np.cumsum(grid**2) - grid**2).astype(np.int32)
    cell_of, cand_of = _cell_candidates(face, affine, grid, cell_offset)
    cell_count = np.zeros(int((grid**2).sum()), np.int32)
    np.add.at(cell_count, cell_of, 1)
    first = (np.cumsum(cell_count) - cell_count).astype(np.int32)
    if len(_FACE_SITES) > 256:
        _FACE_SITES.clear()
    cached = _FACE_SITES[key] = FaceSites(
        grid,
        cell_offset,
        cell_count,
        first,
        site[cand_of].astype(np.int32),
        affine[cand_of].astype(np.float32),
    )
    return cached


def _cell_candidates(
    face: np.ndarray, affine: np.ndarray, grid: np.ndarray, cell_offset: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Which candidates (``face``: the face of each, ``affine``: its (s, t, d) over the
    face) reach into which cells of their face's grid (``grid`` cells per side, the face's
    first cell at ``cell_offset``): (cell, candidate) pairs, by cell, then candidate."""
    rows: list[tuple[np.ndarray, np.ndarray]] = []  # (cell, candidate)
    for g in (1, GRID):
        cand = np.flatnonzero(grid[face] == g)
        if not len(cand):
            continue
        edges = np.arange(g + 1) / g
        iu, iv = (i.ravel() for i in np.meshgrid(np.arange(g), np.arange(g), indexing="ij"))
        cu = np.stack([edges[iu], edges[iu + 1], edges[iu], edges[iu + 1]], axis=1)  # (g*g, 4)
        cv = np.stack([edges[iv], edges[iv], edges[iv + 1], edges[iv + 1]], axis=1)
        A = affine[cand]
        vals = (
            A[:, None, None, :, 0]
            + A[:, None, None, :, 1] * cu[None, :, :, None]
            + A[:, None, None, :, 2] * cv[None, :, :, None]
        )  # (candidates, cells, 4 corners, 3)
        meets = _reaches(vals.min(axis=2), vals.max(axis=2))
        which, local = np.nonzero(meets)
        rows.append((cell_offset[face[cand[which]]] + local, cand[which]))
    cell_of = np.concatenate([r[0] for r in rows]) if rows else np.zeros(0, np.int64)
    cand_of = np.concatenate([r[1] for r in rows]) if rows else np.zeros(0, np.int64)
    order = np.lexsort((cand_of, cell_of))  # by cell, then the face's candidate order
    return cell_of[order], cand_of[order]


def _reaches(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Whether the (s, t, d) box ``lo..hi`` (..., 3) meets the printed square and its slab,
    widened by a hair (1e-4 of the square, 1e-3 mm)."""
    e = 1e-4
    return (
        (hi[..., 0] >= -e)
        & (lo[..., 0] < 1 + e)
        & (hi[..., 1] >= -e)
        & (lo[..., 1] < 1 + e)
        & (hi[..., 2] > -MARKER_SLAB - 1e-3)
        & (lo[..., 2] < MARKER_SLAB + 1e-3)
    )


def _shade(
    albedo: np.ndarray, normals: np.ndarray, rays: np.ndarray, hit: np.ndarray, ambient: float
) -> np.ndarray:
    """Lambert shading with a light at the camera centre (direction towards the camera = -ray)."""
    x, y, z = (rays[..., i] for i in range(3))
    towards = normals[..., 0] * x + normals[..., 1] * y + normals[..., 2] * z
    lambert = np.clip(-towards / np.sqrt(x * x + y * y + z * z), 0.0, 1.0)
    img = albedo * (np.float32(ambient) + np.float32(1.0 - ambient) * lambert)
    img[~hit] = 0.0
    return img


def render_view(
    camera: Camera,
    cam_T_world: np.ndarray,
    surfaces: Sequence[Surface],
    *,
    fixed: int = 0,
) -> View:
    """Cast one ray per pixel centre; albedo (markers included) and normals per pixel.

    The first ``fixed`` surfaces are the scene's surroundings, the same in every scene (a
    table, a bin): they are rendered once per camera and kept; each other surface is cast
    alone over the rectangle of the rays that can hit it (:func:`render_scene`).
    """
    placed = [PlacedMesh(s.mesh, cam_T_world @ s.world_T_model) for s in surfaces]
    hits, own = render_scene(camera, placed, fixed=fixed)
    albedo, on_marker = _albedo(surfaces, placed, hits)
    return View(hits, placed, hits.normals(placed), albedo, on_marker, own)


def render_intensity(
    camera: Camera,
    cam_T_world: np.ndarray,
    surfaces: Sequence[Surface],
    *,
    supersample: int = 4,
    ambient: float = 0.25,
    fixed: int = 0,
) -> tuple[np.ndarray, View]:
    """Render a float32 intensity image in [0, 1] (no blur, no noise) and the centre-ray view
    (``fixed``: see :func:`render_view`)."""
    view = render_view(camera, cam_T_world, surfaces, fixed=fixed)
    placed = view.placed
    rays = camera.pixel_rays()
    img = _shade(view.albedo, view.normals_cam, rays, view.hits.hit, ambient)
    if supersample > 1 and np.any(view.on_marker):
        # Supersample the pixels of markers and around them where an edge passes: where the
        # albedo or the surface differs within the pixel's 3x3 neighbourhood (a straight edge
        # through a pixel always separates its centre from a neighbour's).
        near = cv2.dilate(view.on_marker.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        kernel = np.ones((3, 3), np.uint8)
        code = view.albedo * 1000.0 + view.hits.instance.astype(np.float32)
        near &= cv2.dilate(code, kernel) != cv2.erode(code, kernel)
        vs, us = np.nonzero(near)
        offs = (np.arange(supersample) + 0.5) / supersample - 0.5
        acc = np.zeros(len(us), np.float64)
        scene = RayScene(placed)
        for dy in offs:
            for dx in offs:
                if dx == 0 and dy == 0:  # the pixel centre (odd n): already cast
                    acc += _shade(
                        view.albedo[vs, us],
                        view.normals_cam[vs, us],
                        rays[vs, us],
                        view.hits.hit[vs, us],
                        ambient,
                    )
                    continue
                sub_rays = interpolate_rays(rays, us + dx, vs + dy)
                h = scene.cast(sub_rays)
                a, _ = _albedo(surfaces, placed, h)
                acc += _shade(a, h.normals(placed), sub_rays, h.hit, ambient)
        img[vs, us] = acc / supersample**2
    return img, view


def interpolate_rays(rays: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rays through sub-pixel positions, interpolated bilinearly between pixel-centre rays.

    Rays vary smoothly with the pixel position, so for offsets under a pixel the error of the
    interpolation is far below a thousandth of a pixel with the mild distortion of real lenses.
    """
    h, w = rays.shape[:2]
    u0 = np.clip(np.floor(u).astype(int), 0, w - 2)
    v0 = np.clip(np.floor(v).astype(int), 0, h - 2)
    fu = (u - u0)[:, None].astype(np.float32)
    fv = (v - v0)[:, None].astype(np.float32)
    top = rays[v0, u0] * (1 - fu) + rays[v0, u0 + 1] * fu
    bottom = rays[v0 + 1, u0] * (1 - fu) + rays[v0 + 1, u0 + 1] * fu
    return top * (1 - fv) + bottom * fv


def finish_image(
    img: np.ndarray, *, blur: float, noise: float, rng: np.random.Generator
) -> np.ndarray:
    """Blur (Gaussian sigma, px), add Gaussian noise (sigma, grey levels), quantise to uint8."""
    out: np.ndarray = img.astype(np.float32) * 255.0
    if blur > 0:
        out = cv2.GaussianBlur(out, (0, 0), blur)
    if noise > 0:
        out = out + rng.normal(0.0, noise, out.shape).astype(np.float32)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)
