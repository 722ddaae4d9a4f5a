"""Procedural part meshes, in millimetres, one builder per shape.

Every builder returns a watertight mesh with outward normals whose surface centroid is at
the origin and whose symmetry axes (if any) are the model axes; the symmetry each shape really
has is stated in its docstring and checked in the tests.
"""

from __future__ import annotations

from typing import cast

import numpy as np
import trimesh
from shapely.geometry import Polygon

from annotator.geometry.mesh import Mesh


def _to_mesh(tm: trimesh.Trimesh) -> Mesh:
    tm.merge_vertices()
    tm.fix_normals()
    mesh = Mesh(np.asarray(tm.vertices, dtype=np.float64), np.asarray(tm.faces, dtype=np.int32))
    c = mesh.moments.centroid
    return Mesh(mesh.vertices - c, mesh.faces)


def bracket() -> Mesh:
    """An L-shaped bracket with an off-centre hole-like notch and a rib: no proper symmetry."""
    base = trimesh.creation.box((90.0, 54.0, 18.0))
    wall = trimesh.creation.box((18.0, 54.0, 50.0))
    wall.apply_translation([36.0, 0.0, 34.0])
    rib = trimesh.creation.box((27.0, 9.0, 21.0))
    rib.apply_translation([16.5, -15.0, 19.5])
    boss = trimesh.creation.cylinder(radius=9.0, height=9.0, sections=32)
    boss.apply_translation([-27.0, 12.0, 13.5])
    return _to_mesh(_concat(base, wall, rib, boss))


def brick() -> Mesh:
    """A 96 x 48 x 30 brick with two studs on top at x = +-24 mm: the half turn about z is its
    only non-trivial symmetry (studs on top only break the flips; the rectangle breaks the
    quarter turns)."""
    body = trimesh.creation.box((96.0, 48.0, 30.0))
    parts = [body]
    for x in (-24.0, 24.0):
        stud = trimesh.creation.cylinder(radius=10.0, height=9.0, sections=48)
        stud.apply_translation([x, 0.0, 19.5])
        parts.append(stud)
    return _to_mesh(_concat(*parts))


def gear(teeth: int = 8) -> Mesh:
    """A spur gear with ``teeth`` teeth (70 mm tip diameter, 16 mm thick) and a hub on one
    side: symmetric under turns of 2 pi / teeth about z only (the hub breaks the flips)."""
    r_root, r_tip = 29.0, 35.0
    pts = []
    n = teeth * 4
    for k in range(n):
        a = 2 * np.pi * k / n
        r = r_tip if (k % 4) in (1, 2) else r_root
        pts.append((r * np.cos(a), r * np.sin(a)))
    body = trimesh.creation.extrude_polygon(Polygon(pts), height=16.0)
    hub = trimesh.creation.cylinder(radius=14.0, height=12.0, sections=64)
    hub.apply_translation([0.0, 0.0, 22.0])
    return _to_mesh(_concat(body, hub))


def cup() -> Mesh:
    """A closed cup-like solid of revolution (a frustum with a rim): revolution about z, no flip."""
    profile = np.array(
        [[0.0, 0.0], [21.0, 0.0], [30.0, 54.0], [33.0, 54.0], [33.0, 60.0], [0.0, 60.0]]
    )
    return _to_mesh(trimesh.creation.revolve(profile, sections=64))


def cylinder() -> Mesh:
    """A plain cylinder, 50 mm diameter, 70 mm long: revolution about z with flip."""
    return _to_mesh(trimesh.creation.cylinder(radius=25.0, height=70.0, sections=96))


def ball() -> Mesh:
    """A 60 mm sphere: spherical symmetry."""
    return _to_mesh(trimesh.creation.icosphere(subdivisions=4, radius=30.0))


def _concat(*meshes: trimesh.Trimesh) -> trimesh.Trimesh:
    """Overlapping solids as one mesh: fine for ray casting, physics (convex hulls) and moments
    of what a camera sees; internal faces are removed when a boolean engine is available."""
    if _has_boolean():
        return trimesh.boolean.union(list(meshes))
    # Trimeshes concatenate to a Trimesh; the signature says Geometry.
    return cast(trimesh.Trimesh, trimesh.util.concatenate(list(meshes)))


def _has_boolean() -> bool:
    try:
        import manifold3d  # noqa: F401
    except ImportError:
        return False
    return True
