"""The physics check's shortcuts give the figures of asking every point: a hull's planes and
corners, the mesh's own bounds and the probes of the measured surface only decide which
points the ray-casting scenes are asked about, never a figure."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from annotator.geometry.mesh import Mesh
from annotator.geometry.transforms import make_transform
from annotator.physics import Body, Support, SupportPlane
from annotator.physics.contact import (
    hull_distance,
    hulls_apart,
    least_hull_distance,
    penetration,
    signed_distance,
)
from annotator.physics.support import grid_surface


def _ring() -> Mesh:
    """A concave part: a ring 30 mm across with a 16 mm hole, 8 mm high."""
    ring = trimesh.creation.annulus(r_min=8.0, r_max=15.0, height=8.0, sections=24)
    return Mesh(np.asarray(ring.vertices), np.asarray(ring.faces, np.int32))


def _posed(key: str, mesh: Mesh, rng: np.random.Generator, spread: float) -> Body:
    R = Rotation.random(random_state=rng).as_matrix()
    return Body(key, mesh, make_transform(R, rng.uniform(-spread, spread, 3)))


def _depth(a: Body, b: Body) -> float:
    """How deep ``a`` reaches into ``b``, every point of ``a`` asked."""
    return max(0.0, -float(signed_distance(b.mesh, b.to_model(a.points)).min()))


@pytest.mark.parametrize("seed", range(12))
def test_penetrations_are_those_of_every_point(seed: int) -> None:
    rng = np.random.default_rng(seed)
    a, b = (_posed(k, _ring(), rng, 14.0) for k in ("ring/a", "ring/b"))
    expected = max(_depth(a, b), _depth(b, a))
    assert penetration(a, b) == expected
    if hulls_apart(a, b):
        assert expected == 0.0


@pytest.mark.parametrize("seed", range(12))
def test_the_least_hull_distance_is_that_of_every_point(seed: int) -> None:
    rng = np.random.default_rng(seed)
    b = _posed("ring/b", _ring(), rng, 0.0)
    points = rng.uniform(-25.0, 25.0, (3, 400))
    least = float(hull_distance(points, b).min())
    for below in (np.inf, least + 0.5, least, max(0.0, least - 0.5)):
        found = least_hull_distance(points, b, below)
        if least < below:
            assert found == least
        else:
            assert found >= below


def _bin() -> Support:
    """A floor at z = 0 (up: +z) measured on a 2 mm grid, with a wall 20 mm high along
    x = 20 mm."""
    x, y = np.meshgrid(np.arange(-40.0, 40.0, 2.0), np.arange(-40.0, 40.0, 2.0))
    z = np.where(x >= 20.0, 20.0, 0.0) + 0.01 * np.sin(x + y)
    wall = grid_surface(np.stack([x, y, z], axis=-1), max_edge_mm=30.0)
    return Support(SupportPlane(np.array([0.0, 0.0, 1.0]), 0.0), wall).lowered(0.3)


@pytest.mark.parametrize("seed", range(8))
def test_the_least_distance_to_the_support_is_that_of_every_point(seed: int) -> None:
    rng = np.random.default_rng(seed)
    support = _bin()
    part = _posed("ring/a", _ring(), rng, 10.0)
    points = part.points + np.array([[8.0], [0.0], [18.0]])  # near the wall, above the floor
    assert support.least_distance(points) == float(support.distance(points).min())
