"""The paper's pose distance: group invariance and agreement with brute force (within 1%)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from annotator.dataset.model import Symmetry
from annotator.geometry.mesh import Mesh
from annotator.geometry.transforms import axis_angle, random_rotations
from annotator.parts import build_part
from annotator.symmetry import PoseSpace, filter_duplicates, finite_group

Z = np.array([0.0, 0.0, 1.0])


def _tilted(mesh: Mesh, rng: np.random.Generator) -> tuple[Mesh, np.ndarray, np.ndarray]:
    """The mesh moved off its centroid and turned, so that the model frame is not canonical."""
    Q = random_rotations(1, rng)[0]
    off = np.array([12.0, -7.0, 5.0])
    return Mesh(mesh.vertices @ Q.T + off, mesh.faces), Q, off


CASES = ["bracket", "brick", "gear", "cup", "cylinder", "ball"]


def _space_and_group(name: str, rng: np.random.Generator):
    part = build_part(name)
    mesh, Q, off = _tilted(part.mesh, rng)
    sym = part.symmetry
    if sym.kind == "finite":
        sym = Symmetry("finite", tuple((Q @ a, o) for a, o in sym.generators))
    elif sym.axis is not None:
        sym = Symmetry(sym.kind, axis=Q @ sym.axis)
    space = PoseSpace.from_moments(mesh.moments, sym)
    # Dense samples of the group, as rotations about the centroid in the model frame.
    if sym.kind == "none":
        G = np.eye(3)[None]
    elif sym.kind == "finite":
        G = finite_group(sym.generators)
    elif sym.kind == "spherical":
        G = random_rotations(4000, np.random.default_rng(5))
    else:
        G = np.stack(
            [axis_angle(sym.axis, a) for a in np.linspace(0, 2 * np.pi, 720, endpoint=False)]
        )
        if sym.kind == "revolution_flip":
            perp = np.cross(sym.axis, [1.0, 0, 0])
            G = np.concatenate([G, G @ axis_angle(perp, np.pi)])
    return mesh, space, G, off


@pytest.mark.parametrize("name", CASES)
def test_distance_equals_brute_force_rms_over_the_group(name: str) -> None:
    rng = np.random.default_rng(CASES.index(name))
    mesh, space, G, _ = _space_and_group(name, rng)
    m = mesh.moments
    for _ in range(5):
        R1, R2 = random_rotations(2, rng)
        t1, t2 = rng.normal(size=(2, 3)) * 20
        # Pose 2 composed with a group element g about the centroid: x -> R2 (c + g (x - c)) + t2.
        best = np.inf
        # For SO(3) random samples are too sparse near the optimum: add the exact aligning turn.
        samples = np.concatenate([G, (R2.T @ R1)[None]]) if space.kind == "spherical" else G
        for g in samples:
            Rg = R2 @ g
            tg = t2 + R2 @ (m.centroid - g @ m.centroid)
            # RMS over the surface of (R1 x + t1) - (Rg x + tg), exactly from the moments.
            best = min(best, m.rms_displacement(Rg.T @ R1, Rg.T @ (t1 - tg)))
        d = float(space.distance(R1[None], t1[None], R2[None], t2[None])[0])
        assert d == pytest.approx(best, rel=0.01), name


@pytest.mark.parametrize("name", CASES)
def test_distance_is_invariant_under_the_group(name: str) -> None:
    rng = np.random.default_rng(10 + CASES.index(name))
    mesh, space, G, _ = _space_and_group(name, rng)
    c = mesh.moments.centroid
    R1, R2 = random_rotations(2, rng)
    t1, t2 = rng.normal(size=(2, 3)) * 30
    d0 = space.distance(R1[None], t1[None], R2[None], t2[None])[0]
    for g in G[:: max(1, len(G) // 12)]:
        Rg, tg = R2 @ g, t2 + R2 @ (c - g @ c)
        assert space.distance(R1[None], t1[None], Rg[None], tg[None])[0] == pytest.approx(
            d0, abs=1e-4
        )
        assert space.distance(Rg[None], tg[None], R2[None], t2[None])[0] == pytest.approx(
            0.0, abs=1e-4
        )


def test_nearest_duplicates_and_average() -> None:
    part = build_part("brick")
    space = PoseSpace.from_moments(part.mesh.moments, part.symmetry)
    rng = np.random.default_rng(3)
    R = random_rotations(6, rng)
    t = rng.normal(size=(6, 3)) * 100
    idx, d = space.nearest(R, t + 0.1, R, t)
    assert np.array_equal(idx, np.arange(6)) and np.all(d < 0.2)
    # A duplicate: pose 0 turned by the brick's half turn, plus noise -> removed.
    half = axis_angle(Z, np.pi)
    Rd = np.concatenate([R, (R[0] @ half)[None]])
    td = np.concatenate([t, (t[0] + [0.2, 0, 0])[None]])
    poses = np.tile(np.eye(4), (7, 1, 1))
    poses[:, :3, :3], poses[:, :3, 3] = Rd, td
    kept = filter_duplicates(poses, np.array([6, 5, 4, 3, 2, 1, 7.0]), space, radius=5.0)
    assert sorted(kept.tolist()) == [1, 2, 3, 4, 5, 6]
    Ra, ta = space.average(np.stack([R[0], R[0] @ half]), np.stack([t[0] + 1, t[0] - 1]))
    assert space.distance(Ra[None], ta[None], R[0][None], t[0][None])[0] < 1e-6


def test_non_finite_generators_are_refused() -> None:
    with pytest.raises(ValueError):
        finite_group([(np.array([0, 0, 1.0]), 7), (np.array([0, 1.0, 1.0]), 5)])
    box = trimesh.creation.box((4, 2, 1))
    assert len(finite_group([(Z, 2), (np.array([1.0, 0, 0]), 2)])) == 4 and box.area > 0
