"""The authors' evaluation definitions, one test each, on hand-made scenes; a worked example;
a literal reference implementation on random problems; the readers and ``annotator evaluate``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from annotator.cli import main
from annotator.evaluation.metrics import average_precision, scene_curve, summarise

THR = 1.0
FAR = 9.0


def _curve(D, scores, occlusion, *, thr=THR, max_occ=0.5):
    D = np.asarray(D, float).reshape(len(scores), len(occlusion))
    return scene_curve(
        D,
        np.asarray(scores, float),
        np.asarray(occlusion, float),
        threshold=thr,
        max_occlusion=max_occ,
    )


def _all(c):
    """(TP, FP, FN) with every result kept."""
    return int(c.tp[-1]), int(c.fp[-1]), int(c.fn[-1])


# ----------------------------------------------------------------- one test per definition


def test_occlusion_exactly_at_the_bound_is_to_find() -> None:
    c = _curve([[0.1]], [1.0], [0.5])
    assert _all(c) == (1, 0, 0)
    c = _curve([[0.1]], [1.0], [0.5000001])
    assert _all(c) == (0, 0, 0)  # matched, but not to find: neither TP nor FP


def test_distance_exactly_at_the_threshold_matches() -> None:
    assert _all(_curve([[THR]], [1.0], [0.0])) == (1, 0, 0)
    assert _all(_curve([[THR * (1 + 1e-12)]], [1.0], [0.0])) == (0, 1, 1)


def test_nearest_true_pose_is_searched_over_all_true_poses() -> None:
    # The result is within the threshold of t0 (to find) but nearer to t1 (not to find): its
    # nearest true pose is t1, so it counts neither way, and t0 is missed.
    c = _curve([[0.5, 0.3]], [1.0], [0.0, 0.9])
    assert _all(c) == (0, 0, 1)


def test_nearest_result_is_searched_among_the_kept_results() -> None:
    # p0 (score 0.9) is farther from t0 than p1 (score 0.5): alone, p0 is a TP; once p1 is
    # kept, p1 is t0's nearest result and p0 a duplicate.
    c = _curve([[0.6], [0.1]], [0.9, 0.5], [0.0])
    assert (c.tp[1], c.fp[1], c.fn[1]) == (1, 0, 0)
    assert (c.tp[2], c.fp[2], c.fn[2]) == (1, 1, 0)


def test_duplicates_and_unmatched_results_are_false_positives() -> None:
    D = [[0.1, FAR], [0.5, FAR], [5.0, 4.0]]  # p0 on t0, p1 its duplicate, p2 unmatched
    assert _all(_curve(D, [0.9, 0.8, 0.7], [0.0, 0.0])) == (1, 2, 1)


def test_false_negative_when_the_nearest_kept_result_does_not_match_back() -> None:
    # t0's nearest result p0 belongs to t1 (nearer): t0 is missed although p0 is close.
    c = _curve([[0.4, 0.2]], [1.0], [0.0, 0.0])
    assert _all(c) == (1, 0, 1)


def test_ties_enter_together() -> None:
    # Same score: an FP and a TP. One curve point for both (no split into two).
    c = _curve([[FAR], [0.1]], [0.9, 0.9], [0.0])
    assert list(c.thresholds()) == [np.inf, 0.9]
    p, r = c.points(c.kept(c.thresholds()))
    assert list(p) == [1.0, 0.5] and list(r) == [0.0, 1.0]
    assert summarise([c]).ap == pytest.approx(0.5)


def test_nothing_kept_has_precision_one() -> None:
    c = _curve([[0.1]], [0.3], [0.0])
    p, r = c.points(c.kept([np.inf]))
    assert (p[0], r[0]) == (1.0, 0.0)


def test_scene_with_nothing_to_find_has_recall_one_and_stays_in_the_mean() -> None:
    empty = _curve(np.zeros((1, 0)), [0.8], [])
    p, r = empty.points(empty.kept(empty.thresholds()))
    assert list(r) == [1.0, 1.0] and list(p) == [1.0, 0.0]
    perfect = _curve([[0.1]], [0.9], [0.0])
    s = summarise([perfect, empty])
    assert s.scenes == 2
    # Mean curve: inf (1, 0.5); 0.9 (1, 1); 0.8 (0.5, 1) -> AP = 1 * 0.5 + 1 * 0.5.
    assert s.ap == pytest.approx(1.0)
    assert list(s.precision) == [1.0, 1.0, 0.5] and list(s.recall) == [0.5, 1.0, 1.0]


def test_scene_without_results() -> None:
    c = _curve(np.zeros((0, 2)), [], [0.0, 0.7])
    assert _all(c) == (0, 0, 1)
    s = summarise([c])
    assert s.ap == 0.0 and list(s.precision) == [1.0] and list(s.recall) == [0.0]


def test_recall_with_at_most_n_results_when_n_exceeds_the_true_poses() -> None:
    # 2 poses to find, 2 correct results: with n = 5, recall = TP / min(5, TP + FN) = 2 / 2.
    c = _curve([[0.1, FAR], [FAR, 0.1]], [0.9, 0.8], [0.0, 0.0])
    _, r5 = c.points(c.kept(c.thresholds()), max_results=5)
    assert list(r5) == [0.0, 0.5, 1.0]
    _, r1 = c.points(c.kept(c.thresholds()), max_results=1)
    assert list(r1) == [0.0, 1.0, 1.0]  # TP / min(1, 2) with the single best result kept


def test_recall_with_at_most_n_results_is_one_with_nothing_to_find() -> None:
    c = _curve(np.zeros((1, 0)), [0.5], [])
    _, r = c.points(c.kept(c.thresholds()), max_results=1)
    assert list(r) == [1.0, 1.0]


def test_worked_example_by_hand() -> None:
    # Scene A: t0, t1 to find. p0 (0.9) on t0, p1 (0.8) unmatched, p2 (0.7) on t1.
    #   inf: P 1, R 0; 0.9: 1, 1/2; 0.8: 1/2, 1/2; 0.7: 2/3, 1.  AP_A = 1/2 + 2/3 * 1/2 = 5/6.
    # Scene B: nothing to find; one result (0.8), an FP.
    #   inf: 1, 1; 0.8: 0, 1.  AP_B = 1.
    # Mean curve: inf (1, 1/2); 0.9 (1, 3/4); 0.8 (1/4, 3/4); 0.7 (1/3, 1).
    #   AP = 1 * 1/2 + 1 * 1/4 + 1/4 * 0 + 1/3 * 1/4 = 5/6; mean scene AP = (5/6 + 1) / 2;
    #   best F1 = 2 * 1 * 3/4 / (1 + 3/4) = 6/7.
    # At most 1 result: A inf (1, 0), then (1, 1) three times; B inf (1, 1), 0.8 (0, 1).
    #   Mean: (1, 1/2), (1, 1), (1/2, 1), (1/2, 1): AP_1 = 1/2 + 1/2 = 1.
    a = _curve([[0.1, FAR], [FAR, FAR], [FAR, 0.2]], [0.9, 0.8, 0.7], [0.1, 0.3])
    b = _curve(np.zeros((1, 0)), [0.8], [])
    s = summarise([a, b], max_results=[1])
    assert s.precision == pytest.approx([1, 1, 1 / 4, 1 / 3])
    assert s.recall == pytest.approx([1 / 2, 3 / 4, 3 / 4, 1])
    assert s.ap == pytest.approx(5 / 6)
    assert s.mean_scene_ap == pytest.approx((5 / 6 + 1) / 2)
    assert s.best_f1 == pytest.approx(6 / 7)
    assert s.ap_n[1] == pytest.approx(1.0)
    assert (s.tp, s.fp, s.fn) == (2, 2, 0)


def test_average_precision_has_no_interpolation() -> None:
    assert average_precision([1.0, 0.5, 1.0], [0.0, 0.5, 1.0]) == pytest.approx(0.75)


# ------------------------------------------------- a literal reference on random problems


def _reference(D, scores, occ, thr, max_occ, n=None):
    """The definitions executed literally: for each threshold, the kept set, n_T, n_P, then
    TP/FP/FN by the rules; returns the scene's (precision, recall) per threshold."""
    to_find = [not (o > max_occ) for o in occ]
    thresholds = [np.inf] + sorted(set(scores), reverse=True)
    out = []
    for s in thresholds:
        kept = [i for i in range(len(scores)) if scores[i] >= s]
        if n is not None and len(kept) > n:
            kept = sorted(kept, key=lambda i: -scores[i])[:n]
        tp = fp = fn = 0
        if not kept:
            fn = sum(to_find)
        elif D.shape[1] == 0:
            fp = len(kept)
        else:
            near_p = {
                t: min(kept, key=lambda p: (D[p, t], kept.index(p))) for t in range(D.shape[1])
            }
            for p in kept:
                t = int(np.argmin(D[p]))
                if D[p, t] > thr or near_p[t] != p:
                    fp += 1
                elif to_find[t]:
                    tp += 1
            for t in range(D.shape[1]):
                p = near_p[t]
                if to_find[t] and (int(np.argmin(D[p])) != t or D[p, t] > thr):
                    fn += 1
        prec = tp / (tp + fp) if tp + fp else 1.0
        denom = tp + fn if n is None else min(n, tp + fn)
        out.append((s, prec, tp / denom if denom else 1.0))
    return out


def test_agrees_with_a_literal_reference_on_random_problems() -> None:
    rng = np.random.default_rng(3)
    for _ in range(40):
        scenes = []
        for _ in range(int(rng.integers(1, 6))):
            n_p, n_t = int(rng.integers(0, 9)), int(rng.integers(0, 7))
            D = rng.uniform(0, 3, (n_p, n_t))
            scores = list(np.round(rng.random(n_p), 1))  # ties
            occ = list(rng.choice([0.0, 0.5, 0.6, 1.0], n_t))
            scenes.append((D, scores, occ))
        curves = [_curve(D, s, o) for D, s, o in scenes]
        for n in (None, 1, 3):
            refs = [_reference(D, s, o, THR, 0.5, n) for D, s, o in scenes]
            # The mean curve, as the definitions describe it.
            allthr = [np.inf] + sorted({x for _, s, _ in scenes for x in s}, reverse=True)
            P, R = [], []
            for g in allthr:
                pts = [[(p, r) for s, p, r in ref if s >= g][-1] for ref in refs]
                P.append(np.mean([p for p, _ in pts]))
                R.append(np.mean([r for _, r in pts]))
            ap = sum(p * (r - r0) for p, r, r0 in zip(P, R, [0.0] + R[:-1]))
            s = summarise(curves, max_results=[] if n is None else [n])
            assert (s.ap if n is None else s.ap_n[n]) == pytest.approx(ap, abs=1e-12)
            if n is None:
                assert s.precision == pytest.approx(P) and s.recall == pytest.approx(R)
                maps = [
                    sum(
                        p * (r - r0) for (_, p, r), r0 in zip(ref, [0.0] + [x[2] for x in ref[:-1]])
                    )
                    for ref in refs
                ]
                assert s.mean_scene_ap == pytest.approx(np.mean(maps), abs=1e-12)


# ------------------------------------------------------------------- readers and the CLI


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
    flip = "1 0 0 0 -1 0 0 0 -1"  # upside down: the same pose for a flip-symmetric part
    csv = tmp_path / "res.csv"
    csv.write_text(
        "scene_id,im_id,obj_id,score,R,t,time\n"
        f"1,0,1,0.9,{flip},0 0 500.5,-1\n"
        f"1,0,1,0.8,{flip},100 0 500,-1\n"
        f"1,0,1,0.7,{flip},300 0 500,-1\n"
        f"7,0,1,0.7,{flip},300 0 500,-1\n"
    )
    out = tmp_path / "report.json"
    args = ["evaluate", str(root), "--results", str(csv), "--json", str(out), "-n", "1", "3"]
    assert main(args + ["--plot", str(tmp_path / "pr.png")]) == 0
    rep = json.loads(out.read_text())["overall"]
    # t0 matched (TP); t1 is 80% occluded: matched but not to find; the third is an FP.
    assert (rep["TP"], rep["FP"], rep["FN"]) == (1, 1, 0)
    assert rep["AP_1"] == pytest.approx(1.0)
    assert (tmp_path / "pr.png").stat().st_size > 1000
    captured = capsys.readouterr()
    assert "AP_1" in captured.out
    # The result for a scene that does not exist is not dropped in silence.
    assert "warning: 1 result scenes have no ground truth and are not scored: 7/0" in captured.err


@pytest.mark.parametrize(
    "line, message",
    [
        ("1,0,1,0.9,1 0 0 0 1 0 0 0,0 0 500,-1", "line 2: R must be 9 numbers"),
        ("1,0,7,0.9,1 0 0 0 1 0 0 0 1,0 0 500,-1", "line 2: result for unknown object '7'"),
        ("1,0,1,0.9,2 0 0 0 1 0 0 0 1,0 0 500,-1", "line 2: R is not a rotation matrix"),
        ("1,0,1,high,1 0 0 0 1 0 0 0 1,0 0 500,-1", "line 2: score must be a number"),
        ("1,0,1,nan,1 0 0 0 1 0 0 0 1,0 0 500,-1", "line 2: score is 'nan'; it must be finite"),
        ("1,0,1,inf,1 0 0 0 1 0 0 0 1,0 0 500,-1", "line 2: score is 'inf'; it must be finite"),
        ("1,0,1,0.9,1 0 0 0 1 0 0 0 1,0 nan 500,-1", "line 2: t has a NaN or infinite value"),
        ("1,0,1,0.9,1 0 0 0 1 0 0 0 1,0 0 inf,-1", "line 2: t has a NaN or infinite value"),
        ("1,0,1,0.9,1 0 0 0 nan 0 0 0 1,0 0 500,-1", "line 2: R has a NaN or infinite value"),
        ("1,0,1", "line 2: expected scene_id,im_id,obj_id,score,R,t,time"),
    ],
)
def test_bad_result_lines_name_file_line_and_field(tmp_path, capsys, line, message) -> None:
    root = _bop(tmp_path)
    csv = tmp_path / "bad.csv"
    csv.write_text("scene_id,im_id,obj_id,score,R,t,time\n" + line + "\n")
    assert main(["evaluate", str(root), "--results", str(csv)]) == 2
    err = capsys.readouterr().err.strip()
    assert f"bad.csv: {message}" in err and len(err.splitlines()) == 1


def _paper_folder(tmp_path, results):
    """A folder in the paper's format with the authors' poseutils.json (metres)."""
    root = tmp_path / "bunny"
    (root / "gt").mkdir(parents=True)
    (root / "poseutils.json").write_text(
        json.dumps(
            {
                "type": "AffinePoseUtils",
                "Lambda": [[0.026, 0, 0], [0, 0.034, 0], [0, 0, 0.048]],
                "G": [np.eye(3).tolist()],
                "Rref2i": np.eye(3).tolist(),
                "tref2i": [[-0.003], [-0.0017], [-0.007]],
                "distance_threshold": 0.0234,
            }
        )
    )
    identity = np.eye(3).tolist()
    gt = [
        {"R": identity, "t": [0.0, 0.0, 0.5], "occlusion_rate": 0.1, "segmentation_id": 1},
        {"R": identity, "t": [0.1, 0.0, 0.5], "occlusion_rate": 0.2, "segmentation_id": 2},
    ]
    (root / "gt" / "s1.json").write_text(json.dumps(gt))
    res = tmp_path / "res"
    res.mkdir()
    for name, items in results.items():
        (res / f"{name}.json").write_text(json.dumps(items))
    return root, res


def test_paper_folder_results_are_read_in_metres(tmp_path, capsys) -> None:
    identity = np.eye(3).tolist()
    root, res = _paper_folder(
        tmp_path,
        {
            "s1": [
                {"R": identity, "t": [0.0, 0.0, 0.501], "score": 2.0},  # 1 mm off: TP
                {"R": identity, "t": [0.1, 0.0, 0.53], "score": 1.0},  # 30 mm off: FP
            ]
        },
    )
    out = tmp_path / "r.json"
    assert main(["evaluate", str(root), "--results", str(res), "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert (rep["overall"]["TP"], rep["overall"]["FP"], rep["overall"]["FN"]) == (1, 1, 1)
    assert rep["thresholds_mm"] == {"bunny": pytest.approx(23.4)}  # poseutils' own, in mm
    assert "lengths in metres" in capsys.readouterr().out


@pytest.mark.parametrize(
    "entry, message",
    [
        ({"R": "I", "t": [0, 0, 0.5], "score": float("nan")}, "entry 0: score is nan"),
        ({"R": "I", "t": [0, 0, float("inf")], "score": 1}, "entry 0: t has a NaN or infinite"),
        ({"R": "I", "t": [0, 0, 0.5]}, "entry 0: 'score' is missing"),
    ],
)
def test_bad_json_results_name_file_entry_and_field(tmp_path, capsys, entry, message) -> None:
    entry = {k: (np.eye(3).tolist() if v == "I" else v) for k, v in entry.items()}
    root, res = _paper_folder(tmp_path, {"s1": [entry]})
    assert main(["evaluate", str(root), "--results", str(res)]) == 2
    err = capsys.readouterr().err.strip()
    assert "s1.json: " + message in err and len(err.splitlines()) == 1


def test_results_for_unknown_scenes_are_reported(tmp_path, capsys) -> None:
    root, res = _paper_folder(tmp_path, {"s1": [], "s9": [], "s8": []})
    assert main(["evaluate", str(root), "--results", str(res)]) == 0
    err = capsys.readouterr().err
    assert "warning: 2 result scenes have no ground truth and are not scored: s8, s9" in err


def test_json_report_to_a_folder_is_a_one_line_error(tmp_path, capsys) -> None:
    root, res = _paper_folder(tmp_path, {"s1": []})
    assert main(["evaluate", str(root), "--results", str(res), "--json", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "is a folder" in err and len(err.splitlines()) == 1
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        code = main(["evaluate", str(root), "--results", str(res), "--json", str(ro / "r.json")])
        err = capsys.readouterr().err.strip()
        import os

        if os.geteuid() != 0:  # root writes anywhere
            assert code == 2 and "cannot write" in err and len(err.splitlines()) == 1
    finally:
        ro.chmod(0o700)


def test_evaluate_sample_annotations(sample, tmp_path, capsys) -> None:
    assert main(["evaluate", str(sample), "--json", str(tmp_path / "e.json")]) == 0
    out = capsys.readouterr().out
    assert "auto-annotation" in out and "0.1 x diameter" in out
    assert json.loads((tmp_path / "e.json").read_text())["overall"]["AP"] > 0.8
