"""Foundation geometry: transforms, the OpenCV camera model, exact surface moments."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh, load_mesh, surface_moments
from annotator.geometry.transforms import (
    invert,
    is_rotation,
    make_transform,
    nearest_rotation,
    random_rotations,
)

K = np.array([[900.0, 0, 319.5], [0, 900.0, 239.5], [0, 0, 1]])
DIST = np.array([-0.12, 0.08, 0.0008, -0.0005, -0.01])


def test_invert_and_rotation_helpers() -> None:
    rng = np.random.default_rng(0)
    R = random_rotations(5, rng)
    assert all(is_rotation(r) for r in R)
    T = np.stack([make_transform(r, rng.normal(size=3) * 100) for r in R])
    assert np.allclose(T @ invert(T), np.eye(4), atol=1e-12)
    assert not is_rotation(np.diag([1.0, 1.0, -1.0]))
    M = R[0] + rng.normal(scale=1e-3, size=(3, 3))
    assert is_rotation(nearest_rotation(M)) and np.abs(nearest_rotation(M) - R[0]).max() < 5e-3


def test_undistort_inverts_projection_to_1e_6_px() -> None:
    cam = Camera("c", 640, 480, K, DIST)
    rng = np.random.default_rng(1)
    pts = np.column_stack(
        [rng.uniform(-0.35, 0.35, 200), rng.uniform(-0.25, 0.25, 200), np.ones(200)]
    )
    uv = cam.project(pts * 700.0)
    xy = cam.undistort_pixels(uv)
    assert np.abs(xy - pts[:, :2]).max() < 1e-8
    rays = cam.pixel_rays()
    assert rays.shape == (480, 640, 3) and np.all(rays[..., 2] == 1)
    # A ray through pixel (u, v) projects back to exactly (u, v): the OpenCV pixel-centre convention.
    back = cam.project(rays[::37, ::41].reshape(-1, 3).astype(np.float64) * 500)
    u, v = np.meshgrid(np.arange(640)[::41], np.arange(480)[::37])
    assert np.abs(back - np.column_stack([u.ravel(), v.ravel()])).max() < 1e-3


def test_undistort_is_exact_for_strong_and_rational_lenses() -> None:
    """OpenCV's quick undistortion is checked point by point and iterated where it falls
    short (a strong barrel lens, and the 8-coefficient rational model)."""
    u, v = np.meshgrid(np.arange(0, 640, 7.0), np.arange(0, 480, 5.0))
    uv = np.stack([u, v], axis=-1).reshape(-1, 2)
    for dist in (
        np.array([-0.45, 0.3, 0.002, -0.001, -0.15]),
        np.array([0.2, -0.1, 0.001, 0.0005, 0.05, 0.1, 0.02, 0.01]),
    ):
        cam = Camera("c", 640, 480, K, dist)
        xy = cam.undistort_pixels(uv)
        pts = np.column_stack([xy, np.ones(len(xy))])
        assert np.abs(cam.project(pts) - uv).max() < 1e-5
        # The lens model used for the check is OpenCV's.
        assert np.abs(cam._distort(xy) - cam.project(pts)).max() < 1e-9


def test_points_behind_camera_project_to_nan() -> None:
    cam = Camera("c", 640, 480, K, DIST)
    uv = cam.project(np.array([[0.0, 0.0, -10.0], [0.0, 0.0, 10.0]]))
    assert np.all(np.isnan(uv[0])) and np.allclose(uv[1], [319.5, 239.5])


def test_surface_moments_are_exact_for_a_box() -> None:
    a, b, c = 40.0, 20.0, 10.0
    box = trimesh.creation.box((a, b, c))
    m = surface_moments(np.asarray(box.vertices), np.asarray(box.faces))
    assert m.area == pytest.approx(2 * (a * b + b * c + a * c))
    assert np.allclose(m.centroid, 0, atol=1e-12)
    # Integral of x^2 over the box surface, by faces: two faces at x = +-a/2 and four faces
    # spanning x in [-a/2, a/2] (mean x^2 = a^2/12).
    ixx = 2 * (b * c) * (a / 2) ** 2 + 2 * (a * b + a * c) * a**2 / 12
    assert m.second[0, 0] == pytest.approx(ixx / m.area)
    assert m.diameter == pytest.approx(np.linalg.norm([a, b, c]))


def test_rms_displacement_matches_dense_sampling() -> None:
    mesh = trimesh.creation.cylinder(radius=15, height=40, sections=64)
    mesh.apply_translation([5.0, -3.0, 2.0])
    m = Mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces, dtype=np.int32)).moments
    pts, _ = trimesh.sample.sample_surface_even(mesh, 60000, seed=3)
    R = random_rotations(1, np.random.default_rng(4))[0]
    t = np.array([1.0, 2.0, -0.5])
    sampled = np.sqrt(np.mean(np.sum((pts @ R.T + t - pts) ** 2, axis=1)))
    assert m.rms_displacement(R, t) == pytest.approx(sampled, rel=0.02)


def test_load_mesh_errors_name_the_file(tmp_path) -> None:
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2")
    with pytest.raises(UserError, match="bad.ply"):
        load_mesh(bad)
    with pytest.raises(UserError, match="missing"):
        load_mesh(tmp_path / "none.ply")
    good = tmp_path / "box.ply"
    trimesh.creation.box((1, 2, 3)).export(good)
    assert load_mesh(good).faces.shape == (12, 3)


def _binary_ply(vertices: np.ndarray, polygons: list[list[int]]) -> bytes:
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(polygons)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    faces = b"".join(np.uint8(len(q)).tobytes() + np.asarray(q, "<i4").tobytes() for q in polygons)
    return header.encode() + np.asarray(vertices, "<f4").tobytes() + faces


def test_load_mesh_reads_a_file_once_until_it_changes(tmp_path) -> None:
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1]], float)
    path = tmp_path / "part.ply"
    path.write_bytes(_binary_ply(square, [[0, 1, 2], [0, 2, 3], [0, 1, 4]]))
    first = load_mesh(path)
    assert first.faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 1, 4]]
    assert load_mesh(path) is first
    # Polygons other than triangles: plyfile's general reader, split into fans.
    path.write_bytes(_binary_ply(square, [[0, 1, 2, 3], [0, 1, 4]]))
    again = load_mesh(path)
    assert again is not first
    assert again.faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 1, 4]]
    np.testing.assert_array_equal(again.vertices, square)
