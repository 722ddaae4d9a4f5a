"""The paper's metrics on hand-made scenes, the readers, and ``annotator evaluate``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from annotator.cli import main
from annotator.evaluation.metrics import precision_recall, scene_counts, summarise

THR = 1.0


def _counts(D, scores, interest):
    D = np.asarray(D, float).reshape(len(scores), len(interest))
    return scene_counts(D, np.asarray(scores, float), np.asarray(interest, bool), THR)


def test_tp_fp_fn_with_duplicates_unmatched_and_uninteresting() -> None:
    # Ground truth: t0, t1 of interest, t2 of no interest. Results by decreasing score:
    # p0 on t0, p1 a duplicate of t0 (farther), p2 on t2 (uninteresting), p3 unmatched.
    D = [
        [0.1, 9.0, 9.0],
        [0.5, 9.0, 9.0],
        [9.0, 9.0, 0.2],
        [5.0, 4.0, 6.0],
    ]
    c = _counts(D, [0.9, 0.8, 0.7, 0.6], [True, True, False])
    assert c.tp[-1] == 1  # p0 -> t0
    assert c.fp[-1] == 2  # the duplicate p1 and the unmatched p3; p2 is neither
    assert c.fn[-1] == 1  # t1
    precision, recall = precision_recall(c)
    assert precision[-1] == pytest.approx(1 / 3) and recall[-1] == pytest.approx(0.5)
    # Prefixes: after p0 only, precision 1 and recall 0.5.
    assert (c.tp[1], c.fp[1]) == (1, 0)


def test_a_better_duplicate_takes_the_match_from_a_higher_scored_one() -> None:
    # p0 (higher score) is farther from t0 than p1: p1 is n_P(t0), so p0 becomes an FP.
    c = _counts([[0.6], [0.1]], [0.9, 0.5], [True])
    assert (c.tp[1], c.fp[1]) == (1, 0)
    assert (c.tp[2], c.fp[2]) == (1, 1)


def test_no_results_and_no_ground_truth() -> None:
    c = _counts(np.zeros((0, 2)), [], [True, True])
    assert c.tp[-1] == 0 and c.fn[-1] == 2 and c.fp[-1] == 0
    c = _counts(np.zeros((2, 0)), [0.5, 0.4], [])
    assert c.fp[-1] == 2 and c.n_interest == 0
    s = summarise([c])
    assert s.scenes == 0 and s.ap == 0.0


def test_recall_with_at_most_n_results() -> None:
    # 5 instances of interest, 3 correct results: recall <= 1 result is 1, <= 3 is 1.
    D = np.full((3, 5), 9.0)
    for k in range(3):
        D[k, k] = 0.1
    c = _counts(D, [0.9, 0.8, 0.7], [True] * 5)
    _, r1 = precision_recall(c, max_results=1)
    _, r3 = precision_recall(c, max_results=3)
    _, r = precision_recall(c)
    assert r1[-1] == 1.0 and r3[-1] == 1.0 and r[-1] == pytest.approx(0.6)
    s = summarise([c], max_results=[1, 3])
    assert s.ap_n[1] == pytest.approx(1.0) and s.ap_n[3] == pytest.approx(1.0)
    assert s.ap == pytest.approx(0.6, abs=0.011)  # precision 1 up to recall 0.6, then 0


def test_ap_of_two_scenes_is_the_area_under_the_mean_curve() -> None:
    perfect = _counts([[0.1]], [1.0], [True])
    half = _counts([[5.0, 5.0], [5.0, 0.1]], [0.9, 0.8], [True, True])  # FP first, then TP
    s = summarise([perfect, half])
    # Scene 2: precision 0.5 at recall 0.5 (0 beyond). Mean: 0.75 up to r=0.5, then 0.5.
    assert s.ap == pytest.approx(0.75 * 0.5 + 0.5 * 0.5, abs=0.01)
    assert s.mean_scene_ap == pytest.approx((1.0 + 0.25) / 2, abs=0.01)


def _bop(tmp_path):
    import trimesh

    root = tmp_path / "bop"
    (root / "models").mkdir(parents=True)
    (root / "test" / "000001").mkdir(parents=True)
    trimesh.creation.cylinder(radius=10, height=40).export(root / "models" / "obj_000001.ply")
    info = {
        "1": {
            "diameter": 45.0,
            "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
            "symmetries_discrete": [[1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]],
        }
    }
    (root / "models" / "models_info.json").write_text(json.dumps(info))
    R = np.eye(3).ravel().tolist()
    gt = {
        "0": [
            {"obj_id": 1, "cam_R_m2c": R, "cam_t_m2c": [0, 0, 500]},
            {"obj_id": 1, "cam_R_m2c": R, "cam_t_m2c": [100, 0, 500]},
        ]
    }
    (root / "test" / "000001" / "scene_gt.json").write_text(json.dumps(gt))
    (root / "test" / "000001" / "scene_gt_info.json").write_text(
        json.dumps({"0": [{"visib_fract": 0.9}, {"visib_fract": 0.2}]})
    )
    return root


def test_bop_ground_truth_and_csv_results(tmp_path, capsys) -> None:
    root = _bop(tmp_path)
    flip = (
        "1 0 0 0 -1 0 0 0 -1"  # the cylinder upside down: the same pose for a flip-symmetric part
    )
    csv = tmp_path / "res.csv"
    csv.write_text(
        "scene_id,im_id,obj_id,score,R,t,time\n"
        f"1,0,1,0.9,{flip},0 0 500.5,-1\n"
        f"1,0,1,0.8,{flip},100 0 500,-1\n"
        f"1,0,1,0.7,{flip},300 0 500,-1\n"
    )
    out = tmp_path / "report.json"
    assert (
        main(
            [
                "evaluate",
                str(root),
                "--results",
                str(csv),
                "--json",
                str(out),
                "-n",
                "1",
                "3",
                "--plot",
                str(tmp_path / "pr.png"),
            ]
        )
        == 0
    )
    rep = json.loads(out.read_text())["overall"]
    # t0 matched (TP); t1 is 80% occluded: matched but of no interest; the third is an FP.
    assert (rep["TP"], rep["FP"], rep["FN"]) == (1, 1, 0)
    assert rep["AP_1"] == pytest.approx(1.0)
    assert (tmp_path / "pr.png").stat().st_size > 1000
    assert "AP_1" in capsys.readouterr().out


@pytest.mark.parametrize(
    "line, message",
    [
        ("1,0,1,0.9,1 0 0 0 1 0 0 0,0 0 500,-1", "line 2: R must have 9 numbers"),
        ("1,0,7,0.9,1 0 0 0 1 0 0 0 1,0 0 500,-1", "line 2: result for unknown object '7'"),
        ("1,0,1,0.9,2 0 0 0 1 0 0 0 1,0 0 500,-1", "line 2: R is not a rotation matrix"),
        ("1,0,1,high,1 0 0 0 1 0 0 0 1,0 0 500,-1", "line 2: malformed number"),
        ("1,0,1", "line 2: expected scene_id,im_id,obj_id,score,R,t,time"),
    ],
)
def test_bad_result_lines_name_file_and_line(tmp_path, capsys, line, message) -> None:
    root = _bop(tmp_path)
    csv = tmp_path / "bad.csv"
    csv.write_text("scene_id,im_id,obj_id,score,R,t,time\n" + line + "\n")
    assert main(["evaluate", str(root), "--results", str(csv)]) == 2
    err = capsys.readouterr().err.strip()
    assert f"bad.csv: {message}" in err and len(err.splitlines()) == 1


def test_sileane_ground_truth_with_json_results(tmp_path) -> None:
    import trimesh
    import yaml

    root = tmp_path / "gear"
    (root / "gt").mkdir(parents=True)
    trimesh.creation.box((40, 20, 10)).export(root / "mesh.ply")
    (root / "symmetry.yaml").write_text(
        yaml.safe_dump({"class": "finite", "generators": [{"axis": [0, 0, 1], "order": 2}]})
    )
    identity = np.eye(3).tolist()
    (root / "gt" / "000.json").write_text(
        json.dumps([{"R": identity, "t": [0, 0, 0.5], "occlusion_rate": 0.1, "segmentation_id": 1}])
    )
    res = tmp_path / "res"
    res.mkdir()
    half = [[-1, 0, 0], [0, -1, 0], [0, 0, 1]]
    (res / "000.json").write_text(json.dumps([{"R": half, "t": [0, 0, 500.2], "score": 1.0}]))
    out = tmp_path / "r.json"
    assert main(["evaluate", str(root), "--results", str(res), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["overall"]["TP"] == 1


def test_evaluate_sample_annotations(sample, tmp_path, capsys) -> None:
    assert main(["evaluate", str(sample), "--json", str(tmp_path / "e.json")]) == 0
    out = capsys.readouterr().out
    assert "auto-annotation" in out and "0.1 x diameter" in out
    assert json.loads((tmp_path / "e.json").read_text())["overall"]["AP"] > 0.8
