"""Faults, round four: outputs written over inputs, a hang on depth holes, and wrong inputs
accepted without a word (BOP files, dictionaries, review edits, the Python API).

Each test first sets up what went wrong before, then checks what the user sees.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

import annotator
from annotator.cli import main
from annotator.dataset import load_dataset, read_poses
from annotator.dataset.review import EditedPose, Review, now_iso, poses_fingerprint, write_review
from annotator.errors import UserError
from annotator.formats.bop import evaluated_sensor
from annotator.io import atomic

ROOT = Path(__file__).resolve().parent.parent


def _digest(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def _one_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


# ------------------------------------------------------------------ 1. outputs over inputs


def test_no_output_is_written_over_an_input(sample_copy: Path, tmp_path: Path, capsys) -> None:
    ds = sample_copy
    results = tmp_path / "r.csv"
    results.write_text("scene_id,im_id,obj_id,score,R,t,time\n")
    before = _digest(ds)
    res_before = results.read_bytes()
    cases = [
        (["estimate", str(ds), str(ds / "dataset.yaml")], "would write over a file of the dataset"),
        (["estimate", str(ds), str(ds / "scenes/000000/gt.json")], "would write over a file"),
        (["estimate", str(ds), str(ds / "scenes/000000/left.png")], "would write over a file"),
        (["estimate", str(ds), str(ds / "scenes/000000/new.csv")], "where the dataset's own"),
        (["evaluate", str(ds), "--json", str(ds / "dataset.yaml")], "--json would write over"),
        (["evaluate", str(ds), "--plot", str(ds / "scenes/000000/left.png")], "--plot would"),
        (["evaluate", str(ds), "--results", str(results), "--json", str(results)], "is the input"),
        (["evaluate", str(ds), "--json", str(tmp_path / "a"), "--plot", str(tmp_path / "a")],
         "--plot is also --json"),
    ]  # fmt: skip
    for args, message in cases:
        assert main(args) == 2, args
        err = _one_line(capsys)
        assert message in err, (args, err)
    assert _digest(ds) == before and results.read_bytes() == res_before
    # A new file beside the dataset's own is fine.
    assert main(["evaluate", str(ds), "--json", str(ds / "report.json")]) == 0
    assert json.loads((ds / "report.json").read_text())["overall"]["AP"] > 0


# ------------------------------------------------------------------ 3. depth holes as 65535


@pytest.mark.timeout(120)
@pytest.mark.slow
def test_depth_holes_written_as_65535_are_holes(sample_copy: Path, tmp_path: Path) -> None:
    args = ["--scenes", "000000", "--workers", "1", "--quiet"]
    assert main(["estimate", str(sample_copy), str(tmp_path / "zero.csv"), *args]) == 0
    for name in ("scenes/000000/depth.png", "background_depth.png"):
        path = sample_copy / name
        d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert (d == 0).any()
        d[d == 0] = 65535
        cv2.imwrite(str(path), d)
    assert main(["estimate", str(sample_copy), str(tmp_path / "max.csv"), *args]) == 0

    def rows(name: str) -> list[list[str]]:  # the time column aside
        return [r.split(",")[:6] for r in (tmp_path / name).read_text().splitlines()]

    assert rows("max.csv") == rows("zero.csv")


def test_points_beyond_the_farthest_background_are_setting() -> None:
    from annotator.estimation.cloud import setting_mask
    from annotator.geometry.camera import Camera

    cam = Camera("c", 8, 8, np.array([[100.0, 0, 4], [0, 100, 4], [0, 0, 1]]))
    background = np.full((8, 8), 800.0)
    background[:4] = np.nan  # holes in the empty bin's depth
    depth = np.full((8, 8), 700.0)
    depth[0, 0] = 6000.0  # a far junk value where the background has a hole
    mask = setting_mask(cam, depth.astype(np.float32), background)
    assert mask[0, 0] and not mask[0, 1] and not mask[5, 5]


# ------------------------------------------------------------------ 5. rejected ground truth


def test_evaluate_leaves_out_what_a_reviewer_rejected(sample_copy: Path, capsys) -> None:
    ds = load_dataset(sample_copy)
    scenes = ds.scenes()
    for sc in scenes:
        sc.gt_path.unlink()  # the annotation is the ground truth, as on real data
    poses = [read_poses(sc.annotation_path) for sc in scenes]
    write_review(
        scenes[0].review_path, Review("rejected", {}, now_iso(), poses_fingerprint(poses[0]))
    )
    key = poses[1][0].key
    write_review(
        scenes[1].review_path,
        Review("accepted", {key: "rejected"}, now_iso(), poses_fingerprint(poses[1])),
    )
    gt = annotator.read_ground_truth(sample_copy)
    assert gt.scenes == [scenes[2].id, scenes[3].id]
    assert any(
        "1 scene(s) without gt.json" in n and "rejected by a reviewer" in n for n in gt.notes
    )
    assert any("an instance rejected" in n for n in gt.notes)
    results = sample_copy.parent / "r.csv"
    results.write_text("scene_id,im_id,obj_id,score,R,t,time\n")
    assert main(["evaluate", str(sample_copy), "--results", str(results)]) == 0
    out = capsys.readouterr().out
    assert "rejected by a reviewer" in out


# ------------------------------------------------------------------ 6, 9. impossible poses


def _edit(sample_copy: Path, index: int, key: str, t: list[float], *, auto: bool) -> Path:
    sc = load_dataset(sample_copy).scenes()[index]
    poses = read_poses(sc.annotation_path)
    fingerprint = None
    if auto:
        from annotator.dataset.review import instance_fingerprint

        fingerprint = instance_fingerprint(next(p for p in poses if p.key == key))
    edit = EditedPose(np.eye(3), np.array(t, float), auto_fingerprint=fingerprint)
    review = Review("accepted", {}, now_iso(), poses_fingerprint(poses), poses={key: edit})
    write_review(sc.review_path, review)
    return sc.review_path


def test_impossible_edits_are_reported_and_never_exported(
    sample_copy: Path, tmp_path: Path, capsys
) -> None:
    first = read_poses(load_dataset(sample_copy).scenes()[2].annotation_path)[0].key
    paths = [
        _edit(sample_copy, 0, "sprocket/01", [0, 0, 500], auto=False),
        _edit(sample_copy, 1, "brick/99", [0, 0, 500], auto=False),
        _edit(sample_copy, 2, first, [0, 0, -300], auto=True),
    ]
    assert main(["check", str(sample_copy)]) == 1
    out = capsys.readouterr().out
    assert f"{paths[0]}: poses['sprocket/01']: unknown object 'sprocket'" in out
    assert f"{paths[1]}: poses['brick/99']: unknown instance 'brick/99'" in out
    assert f"{paths[2]}: poses['{first}']: '{first}' lies behind the reference camera" in out
    out_dir = tmp_path / "bop"
    code = main(["export", str(sample_copy), str(out_dir), "--format", "bop", "--include-pending"])
    err = capsys.readouterr().err
    assert code in (0, 1) and "Traceback" not in err
    exported = json.loads((out_dir / "test" / "scene_ids.json").read_text())
    assert sorted(exported.values()) == ["000003"], exported


def test_sites_goes_past_an_annotation_of_a_removed_instance(sample_copy: Path, capsys) -> None:
    path = sample_copy / "objects" / "brick" / "object.yaml"
    doc = yaml.safe_load(path.read_text())
    named = {p.instance for sc in load_dataset(sample_copy).scenes() for p in read_poses(sc.annotation_path) if p.object == "brick"}  # fmt: skip
    gone = sorted(named)[0]
    doc["instances"] = [i for i in doc["instances"] if i["name"] != gone]
    path.write_text(yaml.safe_dump(doc))
    code = main(["sites", str(sample_copy), "--dry-run", "--quiet", "--workers", "1"])
    captured = capsys.readouterr()
    assert code == 1 and "Traceback" not in captured.err
    assert f"unknown instance 'brick/{gone}'" in captured.err


# ------------------------------------------------------------------ 7. BOP files


@pytest.fixture(scope="module")
def bop_export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("bop") / "bop"
    sample = ROOT / "sample_scenes"
    assert (
        main(["export", str(sample), str(out), "--format", "bop", "--include-pending", "--quiet"])
        == 0
    )
    return out


def _results_for(root: Path, tmp_path: Path) -> Path:
    """One result per true pose of the first image (so that --bop19 has something to score)."""
    scene = _scene(root)
    gt = json.loads((scene / f"scene_gt{evaluated_sensor(scene)}.json").read_text())
    im, insts = next(iter(gt.items()))
    rows = ["scene_id,im_id,obj_id,score,R,t,time"]
    for g in insts:
        R = " ".join(map(str, g["cam_R_m2c"]))
        t = " ".join(map(str, g["cam_t_m2c"]))
        rows.append(f"{int(scene.name)},{im},{g['obj_id']},1,{R},{t},-1")
    csv = tmp_path / "r.csv"
    csv.write_text("\n".join(rows) + "\n")
    return csv


def _scene(root: Path) -> Path:
    return root / "test" / "000000"


def _copy(bop_export: Path, tmp_path: Path) -> Path:
    root = tmp_path / "bop"
    shutil.copytree(bop_export, root)
    return root


@pytest.mark.slow
@pytest.mark.slow
def test_bop_discrete_symmetries_must_fit_the_continuous_axis(bop_export, tmp_path, capsys) -> None:
    from annotator.geometry.transforms import axis_angle
    from annotator.symmetry.classes import symmetry_from_bop

    def element(R: np.ndarray) -> list[float]:
        M = np.eye(4)
        M[:3, :3] = R
        return M.ravel().tolist()

    Z, X = np.array([0.0, 0, 1]), np.array([1.0, 0, 0])
    cont = [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]
    ok = [axis_angle(Z, 0.7), axis_angle(X, np.pi), axis_angle(axis_angle(Z, 0.3) @ X, np.pi)]
    # 90 and 100 degrees about an axis across, and a flip about an axis 10 degrees off.
    for R in ok:  # a turn about the axis, flips across it
        symmetry_from_bop({"symmetries_continuous": cont, "symmetries_discrete": [element(R)]})
    tilted = axis_angle(axis_angle(X, np.radians(10)) @ Z, np.pi)  # a flip 10 degrees off
    for R in [axis_angle(X, np.pi / 2), axis_angle(X, np.radians(100)), tilted]:
        with pytest.raises(ValueError, match="neither a turn about the continuous axis"):
            symmetry_from_bop({"symmetries_continuous": cont, "symmetries_discrete": [element(R)]})
    root = _copy(bop_export, tmp_path)
    info_path = root / "models" / "models_info.json"
    info = json.loads(info_path.read_text())
    key = next(k for k, v in info.items() if v.get("symmetries_continuous"))
    info[key]["symmetries_discrete"] = [element(axis_angle(X, np.radians(45)))]
    info_path.write_text(json.dumps(info))
    assert main(["evaluate", str(root), "--results", str(_results_for(root, tmp_path))]) == 2
    err = _one_line(capsys)
    assert f"models_info.json: object {key}: symmetries_discrete[0]" in err


@pytest.mark.slow
def test_bop_scene_gt_naming_an_unknown_object_is_refused(bop_export, tmp_path, capsys) -> None:
    root = _copy(bop_export, tmp_path)
    csv = _results_for(root, tmp_path)
    path = _scene(root) / f"scene_gt{evaluated_sensor(_scene(root))}.json"
    gt = json.loads(path.read_text())
    im = next(iter(gt))
    gt[im][0]["obj_id"] = 77
    path.write_text(json.dumps(gt))
    assert main(["evaluate", str(root), "--results", str(csv)]) == 2
    err = _one_line(capsys)
    assert (
        f"scene_gt_left.json: image {im}, entry 0: object 77 is not in models/models_info.json"
        in err
    )


@pytest.mark.parametrize("diameter", [-45.0, float("nan"), 0.0])
@pytest.mark.slow
def test_bop_diameters_must_be_positive(bop_export, tmp_path, capsys, diameter) -> None:
    root = _copy(bop_export, tmp_path)
    csv = _results_for(root, tmp_path)
    info_path = root / "models" / "models_info.json"
    info = json.loads(info_path.read_text())
    key = next(iter(info))
    info[key]["diameter"] = diameter
    info_path.write_text(json.dumps(info).replace("NaN", "NaN"))
    assert main(["evaluate", str(root), "--results", str(csv), "--bop19"]) == 2
    err = _one_line(capsys)
    assert f"object {key}: diameter must be a positive number of mm" in err


@pytest.mark.slow
def test_bop_cam_k_must_be_a_camera_matrix(bop_export, tmp_path, capsys) -> None:
    root = _copy(bop_export, tmp_path)
    csv = _results_for(root, tmp_path)
    path = _scene(root) / f"scene_camera{evaluated_sensor(_scene(root))}.json"
    cams = json.loads(path.read_text())
    im = next(iter(cams))
    cams[im]["cam_K"][0] = float("nan")
    path.write_text(json.dumps(cams))
    assert main(["evaluate", str(root), "--results", str(csv), "--bop19"]) == 2
    err = _one_line(capsys)
    assert "cam_K must be a camera matrix" in err and "scene_camera_left.json" in err


# ------------------------------------------------------------------ 8. dictionaries


def _dictionary_file(tmp_path: Path, codes: dict[int, str]) -> Path:
    from annotator.markers.dictionary import write_dictionary

    path = tmp_path / "dict.yml"
    write_dictionary(path, cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    text = path.read_text()
    for k, code in codes.items():
        text = re.sub(rf'marker_{k}: "?[01]+"?', f'marker_{k}: "{code}"', text)
    path.write_text(text)
    return path


def test_dictionaries_with_markers_alike_are_refused(tmp_path: Path, capsys) -> None:
    from annotator.markers.dictionary import dictionary, marker_bit_grids

    grids = marker_bit_grids(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))

    def code(bits: np.ndarray) -> str:
        return "".join(str(int(b)) for b in bits.ravel())

    cases = [
        ({5: code(grids[2])}, "marker_5 is marker_2: a reading could not tell them apart"),
        ({7: code(np.rot90(grids[2]))}, "marker_7 is marker_2 turned by 90 degrees"),
        ({3: "1001000000001001"}, "marker_3 looks the same turned by 90 degrees"),
    ]
    for codes, message in cases:
        path = _dictionary_file(tmp_path, codes)
        with pytest.raises(UserError, match=message):
            dictionary(str(path))
        out = tmp_path / "sheets"
        assert main(["markers", "brick", str(out), "--dictionary", str(path)]) == 2
        assert message in _one_line(capsys)
        assert not out.exists()
    assert dictionary(str(_dictionary_file(tmp_path, {}))).bytesList.shape[0] == 50


# ------------------------------------------------------------------ 10. killed writers


_SLOW_WRITER = """
import os, sys
from annotator.io import atomic
os.fsync = lambda fd: (print("writing", flush=True), __import__("time").sleep(600))
atomic.write_bytes(sys.argv[1], b"x" * 1000)
"""


def _start_writer(target: Path) -> subprocess.Popen[str]:
    proc = subprocess.Popen(
        [sys.executable, "-c", _SLOW_WRITER, str(target)], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "writing"
    return proc


def _temporaries(folder: Path) -> list[Path]:
    return sorted(folder.glob(".*.tmp"))


def test_a_killed_writers_temporary_file_is_removed_by_the_next_write(tmp_path: Path) -> None:
    folder = tmp_path / "scene"
    folder.mkdir()
    (folder / ".notes.txt.keepme.tmp").write_text("the user's")  # not a name we make
    live = _start_writer(folder / "other.json")
    dead = _start_writer(folder / "review.json")
    dead.send_signal(signal.SIGKILL)
    dead.wait()
    assert dead.stdout is not None
    dead.stdout.close()
    try:
        left = [p for p in _temporaries(folder) if p.name.startswith(".review.json.")]
        assert len(left) == 1
        old = time.time() - 2 * atomic.ABANDONED_AFTER_S
        for p in _temporaries(folder):
            os.utime(p, (old, old))
        # A new process's first write there sweeps what the dead one left, nothing else.
        code = (
            "import sys; from annotator.io.atomic import write_text; write_text(sys.argv[1], 'new')"
        )
        subprocess.run([sys.executable, "-c", code, str(folder / "review.json")], check=True)
        names = {p.name for p in _temporaries(folder)}
        assert not any(n.startswith(".review.json.") for n in names)
        assert any(n.startswith(".other.json.") for n in names)  # its writer is alive
        assert ".notes.txt.keepme.tmp" in names
        assert (folder / "review.json").read_text() == "new"
    finally:
        live.kill()
        live.communicate()


def test_a_corrupt_journal_is_one_line(sample_copy: Path, capsys) -> None:
    (sample_copy / atomic.JOURNAL).write_text("{not json")
    assert main(["check", str(sample_copy)]) in (1, 2)
    out = capsys.readouterr()
    assert ".annotator-journal.json: cannot finish the files" in out.out + out.err
    assert "Traceback" not in out.err


# ------------------------------------------------------------------ 11. the Python API


def test_the_api_refuses_what_the_commands_refuse(sample_copy: Path, capsys) -> None:
    cases = [
        (lambda: annotator.annotate_dataset(sample_copy, workers=-1), ["annotate", str(sample_copy), "--workers", "-1"]),
        (lambda: annotator.EvaluationSettings(max_occlusion=-1), ["evaluate", str(sample_copy), "--max-occlusion", "-1"]),
        (lambda: annotator.EvaluationSettings(threshold_mm=float("nan")), ["evaluate", str(sample_copy), "--threshold", "nan"]),
        (lambda: annotator.EvaluationSettings(max_results=(0,)), ["evaluate", str(sample_copy), "-n", "0"]),
    ]  # fmt: skip
    for call, args in cases:
        with pytest.raises(UserError) as info:
            call()
        assert main(args) == 2
        err = capsys.readouterr().err
        reason = str(info.value).split(": ", 1)[1].replace("-1.0", "-1")
        api_words = re.sub(r"not .*$", "", reason)
        assert api_words in err, (api_words, err)


def test_the_api_names_a_wrong_type(sample_copy: Path) -> None:
    ds = annotator.load_dataset(sample_copy)
    cases = [
        (lambda: annotator.annotate_dataset(42), "ds must be a Dataset"),
        (lambda: annotator.evaluate("gt.json", None), "gt must be a GroundTruth"),
        (lambda: annotator.annotate_scene(ds, "000000", None), "scene must be a Scene"),
        (lambda: annotator.annotate_dataset(ds, scenes=3), "scenes must be an fnmatch pattern"),
        (lambda: annotator.read_ground_truth(5), "path must be a dataset folder"),
        (lambda: annotator.read_results("r.csv", ds), "gt must be a GroundTruth"),
    ]
    for call, message in cases:
        with pytest.raises(TypeError, match=message):
            call()
    # A dataset folder is taken where a Dataset is.
    summary = annotator.annotate_dataset(str(sample_copy), scenes="000000")
    assert summary.to_json()["scenes"] == 1
