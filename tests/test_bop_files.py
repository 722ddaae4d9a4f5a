"""Official BOP files as they are: measured symmetries, rotations orthonormal only to about
1e-2, objects with nothing to find.

The numbers are those of the public LM-O files (eggbox 179.8 degrees, glue 178.5; scene_gt
rotations off by up to 0.0096), rebuilt here from their description.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_evaluation import _bop
from test_formats import _elements

from annotator.cli import main
from annotator.geometry.transforms import axis_angle
from annotator.symmetry.classes import SNAP_DEG, group_of, symmetry_from_bop

Z = np.array([0.0, 0, 1])


@pytest.mark.parametrize(
    "degrees, order",
    [((179.8,), 2), ((178.5,), 2), ((90.3, 180.2, 269.6), 4), ((120.4, 240.9), 3)],
)
def test_measured_symmetries_are_taken_as_the_exact_turn(degrees, order) -> None:
    axis = np.array([0.01, -0.02, 1.0])
    axis /= np.linalg.norm(axis)
    notes: list[str] = []
    sym = symmetry_from_bop(
        {"symmetries_discrete": _elements(*(axis_angle(axis, np.radians(d)) for d in degrees))},
        snapped=notes,
    )
    assert sym.kind == "finite" and len(group_of(sym)) == order
    assert len(notes) == len(degrees)
    assert f"symmetry {degrees[0]:.1f} deg about (0.010, -0.020, 1.000)" in notes[0]
    if order == 2:
        assert notes[0].endswith("taken as the half turn")


def test_a_symmetry_beyond_the_tolerance_is_named(tmp_path, capsys) -> None:
    bad = 180 - SNAP_DEG - 1.7  # 176.3: of no finite order up to 120
    with pytest.raises(ValueError, match=r"symmetries_discrete\[0\]: a turn of 176.30 deg"):
        symmetry_from_bop({"symmetries_discrete": _elements(axis_angle(Z, np.radians(bad)))})
    root = _bop(tmp_path)
    info = root / "models" / "models_info.json"
    doc = json.loads(info.read_text())
    doc["1"] = {"diameter": 45.0, "symmetries_discrete": _elements(axis_angle(Z, np.radians(bad)))}
    info.write_text(json.dumps(doc))
    csv = tmp_path / "r.csv"
    csv.write_text("1,0,1,0.9,1 0 0 0 1 0 0 0 1,0 0 500,-1\n")
    assert main(["evaluate", str(root), "--results", str(csv)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "object 1: symmetries_discrete[0]: a turn of" in err


def test_measured_symmetries_are_said_in_the_header(tmp_path, capsys) -> None:
    root = _bop(tmp_path)
    info = root / "models" / "models_info.json"
    doc = json.loads(info.read_text())
    doc["1"] = {
        "diameter": 45.0,
        "symmetries_discrete": _elements(axis_angle(Z, np.radians(179.8))),
    }
    info.write_text(json.dumps(doc))
    csv = tmp_path / "r.csv"
    csv.write_text("1,0,1,0.9,1 0 0 0 1 0 0 0 1,0 0 500,-1\n")
    assert main(["evaluate", str(root), "--results", str(csv)]) == 0
    out = capsys.readouterr().out
    assert "object 1: symmetry 179.8 deg about (0.000, 0.000, 1.000) taken as the half turn" in out


def _near(R: np.ndarray, off: float) -> np.ndarray:
    """``R`` with its orthonormality spoiled by ``off`` (as BOP's files are)."""
    return R + off * np.array([[0, 1, 0], [0, 0, 0], [0, 0, 1.0]])


def test_near_rotations_are_projected_and_counted(tmp_path, capsys) -> None:
    root = _bop(tmp_path)
    gt_path = root / "test" / "000001" / "scene_gt.json"
    gt = json.loads(gt_path.read_text())
    gt["0"][0]["cam_R_m2c"] = _near(np.eye(3), 0.0096).ravel().tolist()
    gt_path.write_text(json.dumps(gt))
    near = " ".join(str(v) for v in _near(np.eye(3), 0.008).ravel())
    csv = tmp_path / "r.csv"
    csv.write_text(
        "scene_id,im_id,obj_id,score,R,t,time\n"
        f"1,0,1,0.9,{near},0 0 500,-1\n"
        "1,0,1,0.8,1 0 0 0 1 0 0 0 1,100 0 500,-1\n"
    )
    out = tmp_path / "rep.json"
    assert main(["evaluate", str(root), "--results", str(csv), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "note: 1 of 2 rotations in the ground truth were not orthonormal to 1e-3" in text
    assert "note: 1 of 2 rotations in r.csv were not orthonormal to 1e-3" in text
    assert json.loads(out.read_text())["overall"]["TP"] == 1


@pytest.mark.parametrize(
    "R, why",
    [
        ("-1 0 0 0 1 0 0 0 1", "a reflection"),
        ("1 0.2 0 0 1 0 0 0 1", "far from orthonormal"),
    ],
)
def test_what_is_not_close_to_a_rotation_is_refused(tmp_path, capsys, R, why) -> None:
    root = _bop(tmp_path)
    csv = tmp_path / "r.csv"
    csv.write_text(f"1,0,1,0.9,{R},0 0 500,-1\n")
    assert main(["evaluate", str(root), "--results", str(csv)]) == 2
    err = capsys.readouterr().err.strip()
    assert "line 1: R is not a rotation matrix (R R^T differs from I by more than 0.05" in err, why


def test_an_object_with_nothing_to_find_scores_as_its_ap_says(tmp_path) -> None:
    """No scene for an object (not in the ground truth, no result): AP and scene AP follow
    the same rule, nothing to find and nothing found is 1."""
    root = _bop(tmp_path)
    info = root / "models" / "models_info.json"
    doc = json.loads(info.read_text())
    doc["2"] = {"diameter": 45.0}
    info.write_text(json.dumps(doc))
    (root / "models" / "obj_000002.ply").write_bytes(
        (root / "models" / "obj_000001.ply").read_bytes()
    )
    csv = tmp_path / "r.csv"
    csv.write_text("1,0,1,0.9,1 0 0 0 1 0 0 0 1,0 0 500,-1\n")
    out = tmp_path / "rep.json"
    assert main(["evaluate", str(root), "--results", str(csv), "--json", str(out)]) == 0
    empty = json.loads(out.read_text())["per_object"]["obj_000002"]
    assert empty["scenes"] == 0 and empty["AP"] == empty["mean_scene_AP"] == 1.0


@pytest.mark.parametrize("name", ["test_targets_bop19.json", "test_targets_bop24.json"])
def test_targets_files_decide_what_is_scored(tmp_path, capsys, name) -> None:
    root = _bop(tmp_path)
    gt_path = root / "test" / "000001" / "scene_gt.json"
    gt = json.loads(gt_path.read_text())
    gt["1"] = [{"obj_id": 1, "cam_R_m2c": np.eye(3).ravel().tolist(), "cam_t_m2c": [0, 50, 500]}]
    gt_path.write_text(json.dumps(gt))
    csv = tmp_path / "r.csv"
    csv.write_text(
        "1,0,1,0.9,1 0 0 0 1 0 0 0 1,0 0 500,-1\n"
        "1,1,1,0.8,1 0 0 0 1 0 0 0 1,0 300 500,-1\n"  # a false positive in image 1
    )
    out = tmp_path / "rep.json"
    args = ["evaluate", str(root), "--results", str(csv), "--json", str(out), "--overwrite"]
    assert main(args) == 0
    everything = json.loads(out.read_text())["overall"]
    assert (everything["TP"], everything["FP"], everything["FN"]) == (1, 1, 1)
    target = {"scene_id": 1, "im_id": 0}
    if name.endswith("bop19.json"):
        target |= {"obj_id": 1, "inst_count": 1}
    (root / name).write_text(json.dumps([target]))
    capsys.readouterr()
    assert main(args) == 0
    assert f"note: targets from {name}: 1 images, 1 (image, object) pairs to score" in (
        capsys.readouterr().out
    )
    only = json.loads(out.read_text())["overall"]
    assert (only["TP"], only["FP"], only["FN"], only["scenes"]) == (1, 0, 0, 1)
    (root / name).write_text(json.dumps([{"scene_id": 1, "im_id": 0, "obj_id": 9}]))
    assert main(args) == 2
    assert "entry 0: object 9 is not in models_info.json" in capsys.readouterr().err


@pytest.mark.parametrize("offset, said", [([0.0, 0.0, 7.0], False), ([4.0, 0.0, 0.0], True)])
def test_a_continuous_axis_given_by_its_offset(tmp_path, capsys, offset, said) -> None:
    """An offset is any point on the axis: one along the axis through the centroid changes
    nothing; one off it is said (a rigid part's axes pass through its centroid)."""
    root = _bop(tmp_path)
    info = root / "models" / "models_info.json"
    doc = json.loads(info.read_text())
    doc["1"] = {"diameter": 45.0, "symmetries_continuous": [{"axis": [0, 0, 1], "offset": offset}]}
    info.write_text(json.dumps(doc))
    csv = tmp_path / "r.csv"
    # a result turned 1 radian about the axis: the same pose for a part of revolution
    R = axis_angle(Z, 1.0)
    csv.write_text(f"1,0,1,0.9,{' '.join(map(str, R.ravel()))},0 0 500,-1\n")
    assert (
        main(["evaluate", str(root), "--results", str(csv), "--json", str(tmp_path / "r.json")])
        == 0
    )
    out = capsys.readouterr().out
    assert ("passes 4.00 mm from the surface centroid" in out) == said
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["per_object"]["obj_000001"]["TP"] == 1
