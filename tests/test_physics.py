"""Ground truth that obeys physics (issue 47): on piles ``synth`` dropped with MuJoCo, the
truth raises no flag; a part pushed 3 mm into the part it rests on, one lifted 5 mm, and a
symmetric part turned on end into the bin's floor are each flagged, naming the right
partner, by ``annotator check --physics``; annotate records the same figures."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from annotator.cli import main
from annotator.dataset import load_dataset, read_poses
from annotator.dataset.figures import SUPPORT, PhysicsCheck
from annotator.dataset.flags import Flag
from annotator.dataset.records import InstanceAnnotation
from annotator.dataset.review import Review
from annotator.geometry.mesh import Mesh
from annotator.physics import Body, PhysicsSettings, Support, SupportPlane, check_bodies
from annotator.physics.contact import hull_distance, penetration
from annotator.physics.dataset import physics_of_dataset
from annotator.physics.labels import pick_labels
from annotator.physics.scene import bodies_of, floor_of_pile
from annotator.physics.support import fit_support_plane
from annotator.review import SceneInfo
from viewer.page.panel_text import instance_table

pytestmark = pytest.mark.slow  # a pile rendered

SCENE = "000000"


@pytest.fixture(scope="module")
def pile(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("pile") / "ds"
    args = ["synth", str(root), "--scenes", "1", "--size", "640x512", "--supersample", "1"]
    assert main([*args, "--instances", "14-16", "--seed", "11", "--quiet"]) == 0
    return root


@pytest.fixture()
def copy(pile: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "ds"
    shutil.copytree(pile, dst)
    return dst


def _truth(root: Path):
    ds = load_dataset(root)
    summary = physics_of_dataset(ds, poses="gt")
    return ds, {r.key: r for r in summary.scenes[0].instances}, summary.scenes[0].support


def _move(root: Path, key: str, T: np.ndarray) -> None:
    """Put ``key`` at ``T @`` its true pose in gt.json (camera frame)."""
    path = root / "scenes" / SCENE / "gt.json"
    doc = json.loads(path.read_text())
    for rec in doc["instances"]:
        if f"{rec['object']}/{rec['instance']}" == key:
            R = T[:3, :3] @ np.array(rec["cam_R_m2c"]).reshape(3, 3)
            t = T[:3, :3] @ np.array(rec["cam_t_m2c"]) + T[:3, 3]
            rec["cam_R_m2c"], rec["cam_t_m2c"] = R.ravel().tolist(), t.tolist()
    path.write_text(json.dumps(doc))


def _check(root: Path, capsys) -> dict:
    assert main(["check", str(root), "--physics", "--poses", "gt", "--json"]) == 0
    return json.loads(capsys.readouterr().out)["physics"]["scenes"][SCENE]["instances"]


def _shift(v: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = v
    return T


def test_the_truth_of_a_dropped_pile_raises_no_flag(pile: Path, capsys) -> None:
    found = _check(pile, capsys)
    assert len(found) >= 12
    assert all(not rec["flags"] for rec in found.values()), found
    assert all(rec["penetration_mm"] < 1.0 for rec in found.values())


def test_a_part_pushed_into_its_neighbour_is_flagged_with_it(copy: Path, capsys) -> None:
    ds, truth, support = _truth(copy)
    bodies = {b.key: b for b in _bodies(ds, copy)}

    def pushed(k: str, j: str) -> np.ndarray | None:
        """``k`` moved 3 mm towards ``j``, if that makes ``j`` the part it reaches deepest."""
        d = bodies[j].centroid - bodies[k].centroid
        T = _shift(3.0 * d / np.linalg.norm(d))
        moved = Body(k, bodies[k].mesh, T @ bodies[k].T)
        depth = {o: penetration(moved, b) for o, b in bodies.items() if o != k}
        return T if max(depth, key=depth.get) == j and depth[j] > 2.0 else None

    # A part resting on another, pushed 3 mm into it.
    key, partner, T = next(
        (k, r.check.rests_on, T)
        for k, r in truth.items()
        if r.check.rests_on not in (None, SUPPORT)
        and (T := pushed(k, r.check.rests_on)) is not None
    )
    _move(copy, key, T)
    found = _check(copy, capsys)
    assert "penetrates" in found[key]["flags"]
    assert found[key]["partners"]["penetrates"] == partner
    assert found[key]["penetration_mm"] > 1.5
    assert "penetrates" in found[partner]["flags"]
    assert found[partner]["partners"]["penetrates"] == key
    # Any other flag is a consequence of the move: it names the part moved.
    others = [r for k, r in found.items() if r["flags"] and k not in (key, partner)]
    assert all(key in r["partners"].values() for r in others), others


def test_a_part_lifted_5_mm_floats_above_what_held_it(copy: Path, capsys) -> None:
    ds, truth, support = _truth(copy)
    up = np.array(support["normal"])
    bodies = {b.key: b for b in _bodies(ds, copy)}
    plane = SupportPlane(up, support["offset_mm"])

    def clear_after_lift(k: str) -> bool:
        """Whether ``k``, lifted 5 mm, has nothing within 4 mm under its lower half."""
        lifted = Body(k, bodies[k].mesh, _shift(5.0 * up) @ bodies[k].T)
        h = plane.height(lifted.points)
        low = lifted.points[:, h < float(plane.height(lifted.centroid[:, None])[0])]
        near = [hull_distance(low, b).min() for o, b in bodies.items() if o != k]
        return min(near) > 4.0

    # A part on the floor that nothing else would hold once lifted.
    key = next(k for k, r in truth.items() if r.check.rests_on == SUPPORT and clear_after_lift(k))
    _move(copy, key, _shift(5.0 * up))
    found = _check(copy, capsys)
    assert found[key]["flags"] == ["floats"]
    assert found[key]["partners"]["floats"] == SUPPORT
    # 5 mm above the floor, as far as the measured floor (its noise, its bias) can tell.
    assert 3.0 < found[key]["gap_mm"] < 5.5
    assert sum(bool(r["flags"]) for r in found.values()) == 1


def test_a_symmetric_part_turned_on_end_penetrates_the_floor(copy: Path, capsys) -> None:
    ds, truth, support = _truth(copy)
    up = np.array(support["normal"])
    bodies = {b.key: b for b in _bodies(ds, copy)}
    key = next(
        k
        for k, r in truth.items()
        if k.startswith("cylinder/")
        and r.check.rests_on == SUPPORT
        and abs(float(bodies[k].T[:3, 2] @ up)) < 0.3  # lying: its axis across gravity
    )
    body = bodies[key]
    c = body.centroid
    axis = np.cross(body.T[:3, 2], up)  # across both: turns the axis upright
    R = Rotation.from_rotvec(np.pi / 2 * axis / np.linalg.norm(axis)).as_matrix()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, c - R @ c
    _move(copy, key, T)
    found = _check(copy, capsys)
    assert "penetrates" in found[key]["flags"]
    # It stands 35 mm below its centre where it lay 25 mm above the floor: 10 mm down.
    assert found[key]["partners"]["penetrates"] == SUPPORT or found[key]["penetration_mm"] > 10
    assert found[key]["penetration_mm"] > 5.0


def test_annotate_records_the_figures_and_the_flags(copy: Path, capsys) -> None:
    assert main(["annotate", str(copy), "--quiet"]) == 0
    ann = json.loads((copy / "scenes" / SCENE / "annotation.json").read_text())
    truth = {p.key: p for p in read_poses(copy / "scenes" / SCENE / "gt.json")}
    assert all("physics" in rec for rec in ann["instances"])
    # The parts of the pile, posed within a millimetre, raise no physics flag; a pose of a
    # part that is not there (a misread marker, hugely uncertain) may, deep in the floor.
    for rec in ann["instances"]:
        key = f"{rec['object']}/{rec['instance']}"
        good = key in truth and np.linalg.norm(truth[key].t - rec["cam_t_m2c"]) < 1.0
        if good:
            assert not {"penetrates", "floats"} & set(rec["flags"]), rec
        if "penetrates" in rec["flags"]:
            partner = rec["physics"]["partners"]["penetrates"]
            assert rec["physics"]["penetration_mm"] > 3 * rec["uncertainty_mm"], rec
            assert partner == SUPPORT or partner in {
                f"{r['object']}/{r['instance']}" for r in ann["instances"]
            }
    assert main(["check", str(copy), "--physics"]) == 0
    out = capsys.readouterr().out
    flagged = [r for r in ann["instances"] if {"penetrates", "floats"} & set(r["flags"])]
    assert out.count("warning: physics:") == len(flagged)


def test_thresholds_follow_the_uncertainty() -> None:
    # Two unit cubes overlapping by 2 mm: flagged for exact poses, not for poses 1 mm unsure.
    cube = _cube()
    a = Body("cube/a", cube, np.eye(4))
    b = Body("cube/b", cube, _shift(np.array([8.0, 0.0, 0.0])))
    floor = Support(SupportPlane(np.array([0.0, 0.0, 1.0]), 0.0))
    exact = check_bodies([a, b], floor)
    assert [r.flags for r in exact] == [["penetrates"], ["penetrates"]]
    assert exact[0].check.penetration_mm == pytest.approx(2.0, abs=0.05)
    assert exact[0].check.partners == {"penetrates": "cube/b"}
    unsure = check_bodies([a, b], floor, uncertainty={"cube/a": 1.0, "cube/b": 1.0})
    assert [r.flags for r in unsure] == [[], []]  # 2 mm < 3 x 1.41 mm
    lifted = Body("cube/c", cube, _shift(np.array([40.0, 0.0, 4.0])))
    (rec,) = check_bodies([lifted], floor, settings=PhysicsSettings())
    assert rec.flags == ["floats"] and rec.check.gap_mm == pytest.approx(4.0)


def _bodies(ds, root: Path) -> list[Body]:
    return bodies_of(ds, read_poses(root / "scenes" / SCENE / "gt.json"))


def _results_from_truth(root: Path, out: Path, sink: str | None = None) -> None:
    """A results folder holding every true pose (score 1), ``sink`` 20 mm into the floor."""
    out.mkdir()
    for scene in sorted((root / "scenes").iterdir()):
        rows = []
        for p in read_poses(scene / "gt.json"):
            t = p.t.copy()
            if p.key == sink:
                t = t - 20.0 * _up(root)
            rows.append({"object": p.object, "R": p.R.tolist(), "t": t.tolist(), "score": 1.0})
        (out / f"{scene.name}.json").write_text(json.dumps(rows))


def _up(root: Path) -> np.ndarray:
    _, _, support = _truth(root)
    return np.array(support["normal"])


def test_evaluate_gives_the_share_of_impossible_estimates(pile: Path, tmp_path, capsys) -> None:
    perfect = tmp_path / "perfect"
    _results_from_truth(pile, perfect)
    report = tmp_path / "report.json"
    args = ["evaluate", str(pile), "--results"]
    assert main([*args, str(perfect), "--physics", "--json", str(report)]) == 0
    assert json.loads(report.read_text())["physics"]["impossible_share"] == 0.0
    sunk = tmp_path / "sunk"
    key = next(p.key for p in read_poses(pile / "scenes" / SCENE / "gt.json"))
    _results_from_truth(pile, sunk, sink=key)
    assert main([*args, str(sunk), "--physics", "--json", str(report), "--overwrite"]) == 0
    physics = json.loads(report.read_text())["physics"]
    obj = key.split("/")[0]
    assert physics["per_object"][obj]["penetrating"] == 1
    assert sum(o["penetrating"] for o in physics["per_object"].values()) == 1
    assert "physically impossible" in capsys.readouterr().out


def test_evaluate_physics_needs_our_dataset(tmp_path, capsys) -> None:
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "models_info.json").write_text("{}")  # a BOP dataset, as detected
    assert main(["evaluate", str(tmp_path), "--results", str(tmp_path), "--physics"]) == 2
    assert "--physics" in capsys.readouterr().err


def test_pick_labels_say_what_lies_on_top() -> None:
    cube = _cube()
    floor = Support(SupportPlane(np.array([0.0, 0.0, 1.0]), 0.0))
    under = Body("cube/under", cube, np.eye(4))
    over = Body("cube/over", cube, _shift(np.array([3.0, 2.0, 14.0])))  # 4 mm above it
    apart = Body("cube/apart", cube, _shift(np.array([30.0, 0.0, 0.0])))
    labels = pick_labels([under, over, apart], floor)
    assert [lb.on_top for lb in labels] == [False, True, True]
    assert labels[0].free_height_mm == pytest.approx(4.0, abs=1e-3)
    assert labels[1].free_height_mm is None


def test_the_bop_export_carries_pick_labels(pile: Path, tmp_path) -> None:
    out = tmp_path / "bop"
    args = ["export", str(pile), str(out), "--format", "bop", "--include-pending", "--quiet"]
    assert main([*args, "--poses", "gt"]) == 0
    scene = out / "test" / f"{int(SCENE):06d}"
    gt = json.loads((scene / "scene_gt_left.json").read_text())
    pick = json.loads((scene / "scene_pick_left.json").read_text())
    info = json.loads((scene / "scene_gt_info_left.json").read_text())
    assert [len(v) for v in pick.values()] == [len(v) for v in gt.values()]
    rows = pick["0"]
    assert [r["obj_id"] for r in rows] == [g["obj_id"] for g in gt["0"]]
    assert [r["visib_fract"] for r in rows] == [i["visib_fract"] for i in info["0"]]
    assert any(r["on_top"] for r in rows) and not all(r["on_top"] for r in rows)
    assert all((r["free_height_mm"] is None) == r["on_top"] for r in rows)


def _cube() -> Mesh:
    """A 10 mm cube from (0, 0, 0) to (10, 10, 10), faces turned outwards."""
    box = trimesh.creation.box(extents=(10.0, 10.0, 10.0))
    return Mesh(np.asarray(box.vertices) + 5.0, np.asarray(box.faces, np.int32))


def test_the_review_panel_shows_the_physics_and_the_partner() -> None:
    check = PhysicsCheck(3.14, "brick/02", 0.0, SUPPORT, None, {"penetrates": "brick/02"})
    pose = InstanceAnnotation(
        "brick", "01", np.eye(3), np.zeros(3), physics=check, flags=[Flag.PENETRATES]
    )
    info = SceneInfo("000000", True, (pose,), Review(), False, True, None, auto=(pose,))
    table = instance_table(info, None)
    assert "penetrates brick/02" in table and "| 3.1/0.0 |" in table
    assert info.physics_flagged


def test_a_sequence_is_checked_in_its_scene_frame(sequence: Path, capsys) -> None:
    # The support comes from the first posed frame's depth, away from the parts (a moving
    # rig has no empty bin's depth); the truth of a dropped pile raises no flag.
    ann = json.loads((sequence / "scenes" / SCENE / "annotation.json").read_text())
    assert all("physics" in rec for rec in ann["instances"])
    assert main(["check", str(sequence), "--physics", "--poses", "gt", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)["physics"]
    found = doc["scenes"][SCENE]
    assert found["support"] is not None and doc["flagged"] == 0, found


def test_the_floor_of_a_pile_seen_close_by_is_not_the_bins_rim() -> None:
    # A full bin seen from close by: its rim (500 mm away) holds most of the depth, the
    # floor (620 mm) shows only between the parts resting on it. The dominant plane is the
    # rim; the pile's floor is the one the parts rest on.
    rng = np.random.default_rng(3)
    rim = rng.uniform(-150, 150, (6000, 2))
    rim = rim[np.abs(rim).max(axis=1) > 120]
    floor = rng.uniform(-100, 100, (1500, 2))
    points = np.concatenate([np.c_[rim, np.full(len(rim), 500.0)],
                             np.c_[floor, np.full(len(floor), 620.0)]])  # fmt: skip
    parts = [Body(f"cube/{k}", _cube(), _shift(np.array([x, y, 610.0])))
             for k, (x, y) in enumerate([(-60, 0), (0, 40), (50, -30)])]  # fmt: skip
    assert fit_support_plane(points).d == pytest.approx(500.0, abs=0.5)
    plane = floor_of_pile(points, parts)
    assert plane is not None and plane.d == pytest.approx(620.0, abs=0.5)
    assert plane.n == pytest.approx([0.0, 0.0, -1.0], abs=1e-3)
