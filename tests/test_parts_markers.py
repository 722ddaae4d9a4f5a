"""Built-in parts (every symmetry class) and marker layouts."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from annotator.cli import main
from annotator.errors import UserError
from annotator.geometry.transforms import axis_angle
from annotator.markers.layout import place_markers
from annotator.parts import PART_NAMES, build_part
from annotator.symmetry import finite_group


def _surface_distance(mesh, pts: np.ndarray) -> np.ndarray:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices.astype(np.float32)),
        o3d.core.Tensor(mesh.faces.astype(np.uint32)),
    )
    return np.abs(scene.compute_signed_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy())


def _group(part) -> np.ndarray:
    s = part.symmetry
    if s.kind == "finite":
        return finite_group(s.generators)
    if s.kind in ("revolution", "revolution_flip"):
        G = [axis_angle(s.axis, a) for a in np.linspace(0.3, 6.0, 5)]
        if s.kind == "revolution_flip":
            G.append(axis_angle(np.cross(s.axis, [1.0, 0, 0]), np.pi))
        return np.stack(G)
    if s.kind == "spherical":
        return np.stack([axis_angle(np.array([1.0, 2, 3]), a) for a in (0.4, 2.0)])
    return np.eye(3)[None]


@pytest.mark.parametrize("name", PART_NAMES)
def test_part_is_closed_centred_and_has_exactly_its_symmetry(name: str) -> None:
    part = build_part(name)
    tm = part.mesh.to_trimesh()
    assert tm.is_watertight and tm.volume > 0
    assert np.abs(part.mesh.moments.centroid).max() < 1e-6
    samples = np.asarray(tm.sample(3000, seed=0))
    for g in _group(part):
        # 0.1 mm: open3d's float32 closest point is off by up to 0.06 mm on the brick's long
        # sliver triangles, even for the identity (an undeclared symmetry moves points > 1 mm).
        assert _surface_distance(part.mesh, samples @ g.T).max() < 0.1, f"{name} not invariant"
    if part.symmetry.kind in ("none", "finite"):
        # A symmetry it does not declare: the quarter turn about z (the brick, the bracket) or
        # the flip (the gear, whose hub is on one side) moves its surface.
        for extra in (
            axis_angle(np.array([0, 0, 1.0]), np.pi / 2),
            axis_angle(np.array([1.0, 0, 0]), np.pi),
        ):
            if not any(np.abs(extra - g).max() < 1e-6 for g in _group(part)):
                assert _surface_distance(part.mesh, samples @ extra.T).max() > 1.0, (
                    f"{name} has an undeclared symmetry"
                )
    if part.symmetry.kind == "revolution":
        flip = axis_angle(np.array([1.0, 0, 0]), np.pi)
        assert _surface_distance(part.mesh, samples @ flip.T).max() > 1.0


def test_unknown_part_is_a_one_line_error() -> None:
    with pytest.raises(UserError, match="unknown part 'sprocket'.*bracket"):
        build_part("sprocket")


@pytest.mark.parametrize("name", ["bracket", "cylinder", "cup"])
def test_layout_sites_lie_on_the_surface_and_do_not_overlap(name: str) -> None:
    part = build_part(name)
    layout = place_markers(part.mesh, size=part.marker_size, flatness_tol=0.35)
    c = layout.corners
    assert len(c) >= 10
    # Corners and interior points on the surface, within the tolerance.
    u = np.linspace(0, 1, 4)
    s, t = np.meshgrid(u, u)
    interior = (
        c[:, None, None, 0]
        + s[None, ..., None] * (c[:, 1] - c[:, 0])[:, None, None]
        + t[None, ..., None] * (c[:, 3] - c[:, 0])[:, None, None]
    )
    assert _surface_distance(part.mesh, c.reshape(-1, 3)).max() < 1e-3
    assert _surface_distance(part.mesh, interior.reshape(-1, 3)).max() < 0.35 + 1e-3
    # Squares of the stated size, in ArUco order with the normal pointing out of the part.
    sides = np.linalg.norm(np.roll(c, -1, axis=1) - c, axis=2)
    assert np.abs(sides - part.marker_size).max() < 0.02 * part.marker_size
    outward = (c.mean(axis=1) + 0.5 * layout.normals).astype(np.float32)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(part.mesh.vertices.astype(np.float32)),
        o3d.core.Tensor(part.mesh.faces.astype(np.uint32)),
    )
    assert np.all(
        scene.compute_signed_distance(o3d.core.Tensor(outward)).numpy() > 0
    )  # outside the part
    # No overlap: circumscribed circles are disjoint.
    centres = c.mean(axis=1)
    d = np.linalg.norm(centres[:, None] - centres[None], axis=2) + np.eye(len(c)) * 1e9
    assert d.min() >= 2 * part.marker_size / np.sqrt(2)
    assert layout.min_facing >= 2


@pytest.mark.slow
def test_markers_command_writes_object_sheets_and_textured_mesh(tmp_path, capsys) -> None:
    out = tmp_path / "brick"
    assert main(["markers", "brick", str(out), "--instances", "2", "--dpi", "300", "--json"]) == 0
    import json

    import cv2
    import yaml

    info = json.loads(capsys.readouterr().out)
    doc = yaml.safe_load((out / "object.yaml").read_text())
    assert len(doc["instances"]) == 2 and doc["symmetry"]["class"] == "finite"
    ids = [i for inst in doc["instances"] for i in inst["marker_ids"]]
    assert len(ids) == len(set(ids)) == 2 * info["sites"]
    sheet = cv2.imread(str(out / "sheets" / "sheet_01.png"), cv2.IMREAD_GRAYSCALE)
    # A4 at 300 dpi, true scale.
    assert sheet.shape == (round(297 / 25.4 * 300), round(210 / 25.4 * 300))
    assert (out / "sheets" / "markers.pdf").stat().st_size > 1000
    assert (out / "textured" / "brick.obj").exists() and (
        out / "textured" / "brick_texture.png"
    ).exists()
    # Refuses an existing folder, changes nothing.
    before = sorted(p.name for p in out.iterdir())
    assert main(["markers", "brick", str(out)]) == 2
    assert "exists and is not empty" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == before
    assert main(["markers", "brick", str(tmp_path / "x"), "--size", "-1"]) == 2
    assert main(["markers", str(tmp_path / "nope.ply"), str(tmp_path / "y")]) == 2
    err = capsys.readouterr().err
    assert "--size" in err and "nope.ply" in err and not (tmp_path / "x").exists()
