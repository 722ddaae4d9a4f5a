"""BOP's pose errors computed the quick way against the brute force they replace: MSSD and
MSPD over the points that can hold the maximum (:mod:`annotator.evaluation.largest_gap`),
VSD's renders over a rectangle found from the clusters (:mod:`annotator.evaluation.vsd_render`)
and the images shared between processes (:mod:`annotator.evaluation.forked`)."""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh

from annotator.evaluation import bop19
from annotator.evaluation.bop19 import bop19_scores, mspd, mssd
from annotator.evaluation.forked import in_processes
from annotator.evaluation.largest_gap import clusters_of
from annotator.evaluation.vsd_render import model_depth
from annotator.formats.bop_images import BopEstimates, BopImage, BopObject, symmetry_transformations
from annotator.geometry.mesh import Mesh
from annotator.rendering.raycast import render_depth

K = np.array([[572.4, 0.0, 325.3], [0.0, 573.6, 242.0], [0.0, 0.0, 1.0]])
HALF_TURN = [[-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]


def _mesh(seed: int = 0) -> Mesh:
    """A bumpy ellipsoid of 2562 vertices, 60-160 mm across (not convex)."""
    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(subdivisions=4)
    v = np.asarray(sphere.vertices, float)
    bump = 1 + 0.15 * np.sin(5 * v[:, 0] + rng.uniform(0, 6)) * np.cos(4 * v[:, 2])
    v = v * bump[:, None] * np.array([80.0, 50.0, 30.0])
    return Mesh(vertices=v, faces=np.asarray(sphere.faces, np.int32))


def _object(info: dict, mesh: Mesh) -> BopObject:
    R, t = symmetry_transformations(info)
    v = mesh.vertices
    diameter = float(np.sqrt(((v[:, None] - v[None]) ** 2).sum(-1)).max())
    return BopObject(v, diameter, R, t, mesh)


def _rotation(rng: np.random.Generator, deg: float) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(rng.normal(scale=np.radians(deg), size=3))[0]


def _brute(R_e, t_e, R_g, t_g, obj: BopObject, K_: np.ndarray | None = None) -> float:
    """bop_toolkit's pose_error.mssd / mspd, literally."""
    pts = obj.points
    es = []
    for S, ts in zip(obj.sym_R, obj.sym_t):
        R_s, t_s = R_g @ S, R_g @ ts + t_g
        a, b = pts @ R_e.T + t_e, pts @ R_s.T + t_s
        if K_ is not None:
            a, b = a @ K_.T, b @ K_.T
            a, b = a[:, :2] / a[:, 2:], b[:, :2] / b[:, 2:]
        es.append(np.linalg.norm(a - b, axis=1).max())
    return float(min(es))


@pytest.mark.parametrize("info", [{}, {"symmetries_discrete": HALF_TURN},
                                  {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}])  # fmt: skip
def test_mssd_and_mspd_equal_the_brute_force(info: dict) -> None:
    obj = _object(info, _mesh())
    rng = np.random.default_rng(1)
    for k in range(10 if "symmetries_continuous" in info else 40):  # 315 copies: slow brute
        R_g = _rotation(rng, 180)
        t_g = np.r_[rng.uniform(-150, 150, 2), rng.uniform(400, 1200)]
        # from a near-perfect estimate to a wild one; some turned about a symmetry's axis
        deg, mm = [(0.01, 0.05), (1, 2), (5, 10), (30, 60), (120, 200)][k % 5]
        R_e = R_g @ _rotation(rng, deg)
        if k % 7 == 0:
            R_e = R_g @ np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
        if k % 11 == 0:  # not quite a rotation, as BOP's files have
            R_e = R_e + rng.normal(scale=3e-3, size=(3, 3))
        t_e = t_g + rng.normal(scale=mm, size=3)
        want = _brute(R_e, t_e, R_g, t_g, obj)
        assert mssd(R_e, t_e, R_g, t_g, obj) == pytest.approx(want, rel=1e-12, abs=1e-12)
        want = _brute(R_e, t_e, R_g, t_g, obj, K)
        assert mspd(R_e, t_e, R_g, t_g, K, obj) == pytest.approx(want, rel=1e-12, abs=1e-12)


def test_cutoff_gives_infinity_only_past_it() -> None:
    obj = _object({}, _mesh())
    rng = np.random.default_rng(2)
    t_g = np.array([0.0, 0.0, 700.0])
    for _ in range(20):
        R_e, t_e = _rotation(rng, 20), t_g + rng.normal(scale=20, size=3)
        exact = mssd(R_e, t_e, np.eye(3), t_g, obj)
        for cut in (0.5 * exact, exact * (1 + 1e-9), 2 * exact):
            got = mssd(R_e, t_e, np.eye(3), t_g, obj, cutoff=cut)
            assert got == (np.inf if exact >= cut else pytest.approx(exact, rel=1e-12))


def test_points_at_the_camera_plane_are_computed_not_bounded() -> None:
    """An estimate reaching behind the camera: the projection bounds do not hold there, so
    every such cluster is computed point by point."""
    obj = _object({}, _mesh())
    t_g = np.array([0.0, 0.0, 120.0])
    R_e, t_e = _rotation(np.random.default_rng(3), 10), np.array([5.0, -3.0, 60.0])
    want = _brute(R_e, t_e, np.eye(3), t_g, obj, K)
    assert mspd(R_e, t_e, np.eye(3), t_g, K, obj) == pytest.approx(want, rel=1e-12)


def test_clusters_hold_every_point_once() -> None:
    pts = _mesh().vertices
    c = clusters_of(pts)
    assert clusters_of(pts) is c  # computed once per array
    every = c.members(np.arange(len(c.radii)))
    assert np.array_equal(
        np.sort(every.view("f8,f8,f8"), axis=0), np.sort(pts.view("f8,f8,f8"), axis=0)
    )
    for k in range(0, len(c.radii), 7):
        inside = c.points[c.starts[k] : c.starts[k + 1]]
        assert np.linalg.norm(inside - c.centres[k], axis=1).max() <= c.radii[k] + 1e-12


def test_model_depth_is_render_depth() -> None:
    mesh = _mesh()
    rng = np.random.default_rng(4)
    poses = [(_rotation(rng, 180), np.r_[rng.uniform(-300, 300, 2), rng.uniform(300, 900)])
             for _ in range(12)]  # fmt: skip
    poses += [
        (np.eye(3), np.array([0.0, 0.0, 60.0])),  # reaching behind the camera
        (np.eye(3), np.array([5000.0, 0.0, 500.0])),
    ]  # out of view
    for R, t in poses:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        want, got = render_depth(mesh, T, K, 640, 480), model_depth(mesh, T, K, 640, 480)
        assert (want is None) == (got is None)
        if want is not None and got is not None:
            assert np.array_equal(_image(want), _image(got))  # the same depths
            (a, b, c, d), (A, B, C, D) = want[0], got[0]
            assert A <= a and B <= b and C >= c and D >= d  # in a rectangle as large or larger


def _image(rendered: tuple) -> np.ndarray:
    (x0, y0, x1, y1), depth = rendered
    out = np.zeros((480, 640), np.float32)
    out[y0:y1, x0:x1] = depth
    return out


def _case(seed: int = 5) -> tuple[list[BopImage], dict, dict]:
    mesh = _mesh(seed)
    objects = {
        1: _object({"symmetries_discrete": HALF_TURN}, mesh),
        2: _object({}, _mesh(seed + 1)),
    }
    rng = np.random.default_rng(seed)
    images, estimates = [], {}
    for im in range(6):
        ids = np.array([1, 2, 1])
        R = np.stack([_rotation(rng, 180) for _ in ids])
        t = np.stack([np.r_[rng.uniform(-120, 120, 2), rng.uniform(500, 900)] for _ in ids])
        depth = np.zeros((480, 640), np.float32)
        for oid, R_k, t_k in zip(ids, R, t):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R_k, t_k
            got = render_depth(objects[int(oid)].mesh, T, K, 640, 480)
            if got is not None:
                (x0, y0, x1, y1), d = got
                win = depth[y0:y1, x0:x1]
                win[:] = np.where((d > 0) & ((win == 0) | (d < win)), d, win)
        images.append(BopImage(0, im, K, 640, 480, ids, R, t, rng.uniform(0.2, 1, 3), {1: 2, 2: 1},
                               depth=lambda d=depth: d))  # fmt: skip
        n = 5
        pick = rng.integers(0, 3, n)
        R_e = np.stack([R[p] @ _rotation(rng, 8) for p in pick])
        t_e = t[pick] + rng.normal(scale=8, size=(n, 3))
        estimates[(0, im)] = BopEstimates(ids[pick], rng.uniform(0, 1, n), R_e, t_e)
    return images, estimates, objects


def test_processes_give_the_same_numbers(monkeypatch: pytest.MonkeyPatch) -> None:
    images, estimates, objects = _case()
    one = bop19_scores(images, estimates, objects, render=model_depth)
    bop19._PAIRS.clear()
    monkeypatch.setattr(bop19, "PARALLEL_MIN_ESTIMATES", 1)
    here = []
    groups = bop19._image_groups
    monkeypatch.setattr(
        bop19, "_image_groups", lambda im, *a, **k: here.append(im) or groups(im, *a, **k)
    )
    two = bop19_scores(images, estimates, objects, render=model_depth, processes=2)
    assert len(here) == 3  # the other half in the child
    assert one.metrics["vsd"] is not None
    assert two.recalls == one.recalls and two.per_object == one.per_object
    # the child's pairs came back: BOP 2024's scores next find them all
    assert sum(len(m) for m in bop19.pair_errors().values()) >= one.estimates


def test_a_failed_child_share_is_computed_here() -> None:
    parent = os.getpid()

    def work(share, progress):
        if os.getpid() != parent:
            raise RuntimeError("a child that fails")
        return [x * 2 for x in share]

    assert in_processes(work, list(range(7)), 3) == [[0, 6, 12], [2, 8], [4, 10]]
    assert in_processes(work, [], 2) == [[]]
