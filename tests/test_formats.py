"""Symmetries through BOP's models_info.json and the authors' poseutils.json, checked against
the native pose spaces; the format registry."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from annotator.cli import main
from annotator.errors import UserError
from annotator.export.bop import models_info
from annotator.formats import detect_format, get_format
from annotator.formats.sileane import poseutils_from_json, poseutils_to_json
from annotator.geometry.transforms import axis_angle, random_rotations
from annotator.io.ply import write_ply
from annotator.parts import PART_NAMES, build_part
from annotator.symmetry import PoseSpace
from annotator.symmetry.classes import Symmetry, group_of, symmetry_from_bop, symmetry_to_bop

Z = np.array([0.0, 0.0, 1.0])
X = np.array([1.0, 0.0, 0.0])


def _elements(*rotations: np.ndarray) -> list[list[float]]:
    out = []
    for R in rotations:
        M = np.eye(4)
        M[:3, :3] = R
        out.append(M.ravel().tolist())
    return out


@pytest.mark.parametrize("order", [2, 3, 4, 5, 6, 7, 8])
def test_cyclic_groups_of_every_order_read_from_bop(order: int) -> None:
    listed = [axis_angle(Z, 2 * np.pi * k / order) for k in range(1, order)]
    sym = symmetry_from_bop({"symmetries_discrete": _elements(*listed)})
    assert sym.kind == "finite"
    G = group_of(sym)
    assert len(G) == order
    for R in listed:
        assert min(np.abs(R - g).max() for g in G) < 1e-9


def test_dihedral_group_read_from_bop() -> None:
    half = [axis_angle(a, np.pi) for a in (X, np.array([0.0, 1, 0]), Z)]
    sym = symmetry_from_bop({"symmetries_discrete": _elements(*half)})
    assert len(group_of(sym)) == 4


def test_an_incomplete_group_is_refused() -> None:
    # 45 degrees alone generates 8 rotations: listing only one of them is not a group.
    with pytest.raises(ValueError, match="do not form a group"):
        symmetry_from_bop({"symmetries_discrete": _elements(axis_angle(Z, np.pi / 4))})


def test_continuous_classes_read_from_bop() -> None:
    axis = {"axis": [0, 0, 1], "offset": [0, 0, 0]}
    assert symmetry_from_bop({"symmetries_continuous": [axis]}).kind == "revolution"
    flip = symmetry_from_bop(
        {"symmetries_continuous": [axis], "symmetries_discrete": _elements(axis_angle(X, np.pi))}
    )
    assert flip.kind == "revolution_flip" and np.allclose(flip.axis, Z)
    three = [{"axis": a, "offset": [0, 0, 0]} for a in ([1, 0, 0], [0, 1, 0], [0, 0, 1])]
    assert symmetry_from_bop({"symmetries_continuous": three}).kind == "spherical"
    assert symmetry_from_bop({}).kind == "none"


@pytest.mark.parametrize("name", PART_NAMES)
def test_builtin_parts_survive_models_info(name: str) -> None:
    """models_info.json written and read back: same class, same group size, same distances."""
    part = build_part(name)
    info = json.loads(
        json.dumps(models_info(SimpleNamespace(mesh=part.mesh, symmetry=part.symmetry)))
    )
    back = symmetry_from_bop(info)
    assert back.kind == part.symmetry.kind
    if part.symmetry.kind in ("none", "finite"):
        assert len(group_of(back)) == len(group_of(part.symmetry))
    native = PoseSpace.from_moments(part.mesh.moments, part.symmetry)
    read = PoseSpace.from_moments(part.mesh.moments, back)
    rng = np.random.default_rng(PART_NAMES.index(name))
    R1, R2 = random_rotations(50, rng), random_rotations(50, rng)
    t1, t2 = rng.normal(0, 20, (50, 3)), rng.normal(0, 20, (50, 3))
    assert read.distance(R1, t1, R2, t2) == pytest.approx(native.distance(R1, t1, R2, t2))


@pytest.mark.parametrize("name", PART_NAMES)
def test_poseutils_json_gives_the_native_distances(name: str) -> None:
    part = build_part(name)
    native = PoseSpace.from_moments(part.mesh.moments, part.symmetry)
    doc = json.loads(json.dumps(poseutils_to_json(native, threshold_mm=5.0)))
    space, thr = poseutils_from_json(doc, None)
    assert thr == pytest.approx(5.0)
    rng = np.random.default_rng(7)
    R1, R2 = random_rotations(50, rng), random_rotations(50, rng)
    t1, t2 = rng.normal(0, 20, (50, 3)), rng.normal(0, 20, (50, 3))
    # Built-in parts are centred on their surface centroid: their model frame is canonical.
    assert space.distance(R1, t1, R2, t2) == pytest.approx(native.distance(R1, t1, R2, t2))


def _gear_bop(tmp_path, turn: float):
    """A BOP folder with the 8-fold gear, 3 true poses, and results turned by ``turn`` about
    each part's axis."""
    part = build_part("gear")
    root = tmp_path / "bop"
    write_ply(root / "models" / "obj_000001.ply", part.mesh)
    info = {"1": models_info(SimpleNamespace(mesh=part.mesh, symmetry=part.symmetry))}
    (root / "models" / "models_info.json").write_text(json.dumps(info))
    rng = np.random.default_rng(0)
    Rs = random_rotations(3, rng)
    ts = [[-80.0, 0, 600], [0, 0, 600], [80.0, 0, 600]]
    gt = [{"obj_id": 1, "cam_R_m2c": R.ravel().tolist(), "cam_t_m2c": t} for R, t in zip(Rs, ts)]
    (root / "test" / "000000").mkdir(parents=True)
    (root / "test" / "000000" / "scene_gt.json").write_text(json.dumps({"0": gt}))
    lines = ["scene_id,im_id,obj_id,score,R,t,time"]
    for R, t in zip(Rs, ts):
        Rr = R @ axis_angle(Z, turn)
        lines.append(f"0,0,1,1.0,{' '.join(map(str, Rr.ravel()))},{' '.join(map(str, t))},-1")
    (tmp_path / "res.csv").write_text("\n".join(lines) + "\n")
    return root, tmp_path / "res.csv"


@pytest.mark.parametrize("turn, tp", [(np.pi / 8, 0), (np.pi / 4, 3), (3 * np.pi / 4, 3)])
def test_gear_symmetry_from_bop_is_8_fold(tmp_path, turn, tp) -> None:
    root, res = _gear_bop(tmp_path, turn)
    out = tmp_path / "r.json"
    assert main(["evaluate", str(root), "--results", str(res), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["overall"]["TP"] == tp


def test_registry_and_detection(tmp_path, sample) -> None:
    assert get_format("bop").NAME == "bop"
    with pytest.raises(UserError, match="unknown format 'coco'"):
        get_format("coco")
    assert detect_format(sample).NAME == "ours"
    (tmp_path / "gt").mkdir()
    assert detect_format(tmp_path).NAME == "sileane"
    with pytest.raises(UserError, match="not a dataset"):
        detect_format(tmp_path / "gt")


def test_symmetry_to_bop_lists_every_non_identity_element() -> None:
    sym = Symmetry("finite", ((Z, 8),))
    assert len(symmetry_to_bop(sym, np.zeros(3))["symmetries_discrete"]) == 7


def test_symmetry_to_bop_takes_z_for_a_revolution_without_axis() -> None:
    # As symmetry_to_yaml does (and a reloaded object.yaml has): no axis means z.
    bare = symmetry_to_bop(Symmetry("revolution_flip"), np.zeros(3))
    assert bare == symmetry_to_bop(Symmetry("revolution_flip", axis=Z), np.zeros(3))
