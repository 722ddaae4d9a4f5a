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
from annotator.rendering.raycast import Hits, PlacedMesh, RayScene, stacked_triangles


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
    """Albedo at each hit (markers textured) and whether the hit is on a marker."""
    base = np.array([s.albedo for s in surfaces] + [0.0], np.float32)
    albedo = base[hits.instance]  # NO_HIT = -1 picks the trailing 0
    on_marker = np.zeros(hits.instance.shape, bool)
    marked = [k for k, s in enumerate(surfaces) if s.sites is not None and len(s.sites)]
    sel_all = np.isin(hits.instance, marked)
    if not np.any(sel_all):
        return albedo, on_marker
    flat = np.flatnonzero(sel_all)
    inst = hits.instance.reshape(-1)[flat]
    tri_all = hits.triangle.reshape(-1)[flat]
    uv = hits.barycentric.reshape(-1, 2)[flat].astype(np.float64)
    tri = stacked_triangles(placed)[
        np.cumsum([0] + [len(pm.mesh.faces) for pm in placed])[inst] + tri_all
    ]
    pts_all = (
        (1.0 - uv[:, :1] - uv[:, 1:]) * tri[:, 0] + uv[:, :1] * tri[:, 1] + uv[:, 1:] * tri[:, 2]
    )
    order = np.argsort(inst, kind="stable")
    bounds = np.searchsorted(inst[order], np.arange(len(surfaces) + 1))
    a_flat = albedo.reshape(-1)
    m_flat = on_marker.reshape(-1)
    for k in marked:
        rows = order[bounds[k] : bounds[k + 1]]
        if len(rows) == 0:
            continue
        surf = surfaces[k]
        p = pts_all[rows]
        # Sites never overlap (their circumscribed circles are disjoint), so the only site that
        # can contain a point is the one with the nearest centre.
        sites = surf.sites
        _, idx = cKDTree(sites.mean(axis=1)).query(p)
        tl, ex, ey = sites[idx, 0], sites[idx, 1] - sites[idx, 0], sites[idx, 3] - sites[idx, 0]
        n_site = np.cross(ey, ex)
        n_site /= np.linalg.norm(n_site, axis=1, keepdims=True)
        rel = p - tl
        st = np.column_stack(
            [(rel * ex).sum(1) / (ex * ex).sum(1), (rel * ey).sum(1) / (ey * ey).sum(1)]
        )
        tri_n = surf.mesh.face_normals[tri_all[rows]]
        inside = (
            (st >= 0).all(axis=1)
            & (st < 1).all(axis=1)
            & (np.abs((rel * n_site).sum(1)) < 2.0)
            & ((tri_n * n_site).sum(1) > 0.7)
        )
        c = surf.bits.shape[1]
        ij = np.minimum((st[inside] * c).astype(int), c - 1)
        target = flat[rows[inside]]
        a_flat[target] = np.where(surf.bits[idx[inside], ij[:, 1], ij[:, 0]] > 0, 0.92, 0.04)
        m_flat[target] = True
    return albedo, on_marker


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
        # Supersample marker pixels and their neighbours (marker edges against the part).
        near = cv2.dilate(view.on_marker.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
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
