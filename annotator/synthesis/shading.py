"""Rendering intensity images: diffuse parts with their ArUco markers, lit from the camera.

Every pixel is ray cast through the exact (distorted) OpenCV pixel centre. Pixels on or next
to a marker are then supersampled on an ``n x n`` grid of sub-pixel positions (also exact rays
through the distorted image), which is what keeps the detected marker corners unbiased.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.rendering.raycast import Hits, PlacedMesh, RayScene


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


def _albedo(
    surfaces: Sequence[Surface], placed: Sequence[PlacedMesh], hits: Hits
) -> tuple[np.ndarray, np.ndarray]:
    """Albedo at each hit (markers textured) and whether the hit is on a marker.

    Only hits on triangles that can reach a marker site are looked at (see
    :func:`_site_faces`): on a part most of the surface carries no marker.
    """
    base = np.array([s.albedo for s in surfaces] + [0.0], np.float32)
    albedo = base[hits.instance]  # NO_HIT = -1 picks the trailing 0
    on_marker = np.zeros(hits.instance.shape, bool)
    a_flat = albedo.reshape(-1)
    m_flat = on_marker.reshape(-1)
    instance = hits.instance.reshape(-1)
    triangle = hits.triangle.reshape(-1)
    marked = [
        _site_faces(s.mesh, s.sites) != -1
        if s.sites is not None and len(s.sites)
        else np.zeros(len(s.mesh.faces), bool)
        for s in surfaces
    ]
    offsets = np.cumsum([0] + [len(m) for m in marked])
    hit = np.flatnonzero(instance >= 0)
    near = hit[np.concatenate(marked)[offsets[instance[hit]] + triangle[hit]]]
    if len(near) == 0:
        return albedo, on_marker
    order = near[np.argsort(instance[near], kind="stable")]
    bounds = np.searchsorted(instance[order], np.arange(len(surfaces) + 1))
    for k, surf in enumerate(surfaces):
        rows = order[bounds[k] : bounds[k + 1]]
        if len(rows) == 0:
            continue
        face_site = _site_faces(surf.mesh, surf.sites)
        tri_ids = triangle[rows]
        uv = hits.barycentric.reshape(-1, 2)[rows]
        tri = _triangles32(surf.mesh)[tri_ids]  # model frame
        p = (
            (1.0 - uv[:, :1] - uv[:, 1:]) * tri[:, 0]
            + uv[:, :1] * tri[:, 1]
            + uv[:, 1:] * tri[:, 2]
        )
        # Sites never overlap (their circumscribed circles are disjoint), so the only site that
        # can contain a point is the one with the nearest centre: the face's own site when it
        # meets just one, else the nearest one.
        idx = face_site[tri_ids]
        several = idx == MANY_SITES
        if several.any():
            # argmin |p - c|^2 = argmin (|c|^2 - 2 p.c): one small product, several times
            # faster than a KD-tree query for a part's dozen sites.
            centres = surf.sites.mean(axis=1).astype(np.float32)
            q = p[several]  # (not a matrix product: BLAS would spread it over every core)
            score = (centres * centres).sum(1) - 2.0 * (
                q[:, :1] * centres[:, 0] + q[:, 1:2] * centres[:, 1] + q[:, 2:] * centres[:, 2]
            )
            idx[several] = score.argmin(axis=1)
        # The point in the site's own coordinates: (s, t) across the printed square, d off it.
        frame, origin, normal = (a.astype(np.float32) for a in _site_frames(surf.sites))
        sd = np.einsum("nij,nj->ni", frame[idx], p - origin[idx])
        tri_n = surf.mesh.face_normals[tri_ids]
        inside = (
            (sd[:, 0] >= 0)
            & (sd[:, 0] < 1)
            & (sd[:, 1] >= 0)
            & (sd[:, 1] < 1)
            & (np.abs(sd[:, 2]) < 2.0)
            & ((tri_n * normal[idx]).sum(1) > 0.7)
        )
        c = surf.bits.shape[1]
        ij = np.minimum((sd[inside, :2] * c).astype(int), c - 1)
        target = rows[inside]
        a_flat[target] = np.where(surf.bits[idx[inside], ij[:, 1], ij[:, 0]] > 0, 0.92, 0.04)
        m_flat[target] = True
    return albedo, on_marker


def _site_frames(sites: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per site: the matrix taking ``p - TL`` to ``(s, t, d)`` (fractions along TL->TR and
    TL->BL, distance along the outward normal), the top-left corner, and the normal."""
    tl = sites[:, 0]
    ex, ey = sites[:, 1] - tl, sites[:, 3] - tl
    n = np.cross(ey, ex)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    frame = np.stack(
        [ex / (ex * ex).sum(1, keepdims=True), ey / (ey * ey).sum(1, keepdims=True), n], axis=1
    )
    return frame, tl, n


_TRIANGLES32: dict[bytes, np.ndarray] = {}


def _triangles32(mesh: Mesh) -> np.ndarray:
    """The mesh's triangles in float32 (half the memory traffic per textured point)."""
    tri = _TRIANGLES32.get(mesh.digest)
    if tri is None:
        if len(_TRIANGLES32) > 64:
            _TRIANGLES32.clear()
        tri = _TRIANGLES32[mesh.digest] = mesh.triangles.astype(np.float32)
    return tri


MANY_SITES = -2
_SITE_FACES: dict[tuple[bytes, bytes], np.ndarray] = {}


def _site_faces(mesh: Mesh, sites: np.ndarray) -> np.ndarray:
    """For each face of ``mesh``: the one marker site whose circumscribed sphere it meets, -1
    if none, ``MANY_SITES`` if several. Cached."""
    key = (mesh.digest, np.ascontiguousarray(sites).tobytes())
    hit = _SITE_FACES.get(key)
    if hit is None:
        centres = sites.mean(axis=1)
        radius = np.linalg.norm(sites - centres[:, None], axis=2).max(axis=1)
        tri = mesh.triangles
        tc = tri.mean(axis=1)
        tr = np.linalg.norm(tri - tc[:, None], axis=2).max(axis=1)
        tree = cKDTree(centres)
        face_site = np.full(len(tri), -1)
        for f, js in enumerate(tree.query_ball_point(tc, r=tr + radius.max() + 2.0)):
            meets = [j for j in js if np.linalg.norm(tc[f] - centres[j]) <= tr[f] + radius[j] + 2.0]
            if meets:
                face_site[f] = meets[0] if len(meets) == 1 else MANY_SITES
        if len(_SITE_FACES) > 256:
            _SITE_FACES.clear()
        hit = _SITE_FACES[key] = face_site
    return hit


def _shade(
    albedo: np.ndarray, normals: np.ndarray, rays: np.ndarray, hit: np.ndarray, ambient: float
) -> np.ndarray:
    """Lambert shading with a light at the camera centre (direction towards the camera = -ray)."""
    d = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    lambert = np.clip(-(normals * d).sum(axis=-1), 0.0, 1.0)
    img = albedo * (ambient + (1.0 - ambient) * lambert)
    img[~hit] = 0.0
    return img


def render_view(
    camera: Camera,
    cam_T_world: np.ndarray,
    surfaces: Sequence[Surface],
    scene: RayScene | None = None,
) -> View:
    """Cast one ray per pixel centre; albedo (markers included) and normals per pixel."""
    placed = [PlacedMesh(s.mesh, cam_T_world @ s.world_T_model) for s in surfaces]
    scene = scene or RayScene(placed)
    hits = scene.cast(camera.pixel_rays())
    albedo, on_marker = _albedo(surfaces, placed, hits)
    return View(hits, placed, hits.normals(placed), albedo, on_marker)


def render_intensity(
    camera: Camera,
    cam_T_world: np.ndarray,
    surfaces: Sequence[Surface],
    *,
    supersample: int = 4,
    ambient: float = 0.25,
) -> tuple[np.ndarray, View]:
    """Render a float32 intensity image in [0, 1] (no blur, no noise) and the centre-ray view."""
    placed = [PlacedMesh(s.mesh, cam_T_world @ s.world_T_model) for s in surfaces]
    scene = RayScene(placed)
    view = render_view(camera, cam_T_world, surfaces, scene)
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
        for dy in offs:
            for dx in offs:
                sub_rays = _interpolate_rays(rays, us + dx, vs + dy)
                h = scene.cast(sub_rays)
                a, _ = _albedo(surfaces, placed, h)
                acc += _shade(a, h.normals(placed), sub_rays, h.hit, ambient)
        img[vs, us] = acc / supersample**2
    return img, view


def _interpolate_rays(rays: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
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
    out = img.astype(np.float32) * 255.0
    if blur > 0:
        out = cv2.GaussianBlur(out, (0, 0), blur)
    if noise > 0:
        out = out + rng.normal(0.0, noise, out.shape).astype(np.float32)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)
