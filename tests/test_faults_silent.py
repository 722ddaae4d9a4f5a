"""What the faults probe of issue 44 found silent, said now: a sequence whose frames changed is
stale, results in the other layout are refused, visibility.json made from other poses is
stale, frames left out are named by annotate, check and export, object.yaml's bad sites and
ids are refused by every command, and the commands' advice fits what was typed."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

import annotator
from annotator.cli import main
from annotator.review import ReviewState

pytestmark = pytest.mark.slow  # sequences annotated again

SCENE = "000000"


@pytest.fixture()
def seq(sequence: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "seq"
    shutil.copytree(sequence, dst)
    return dst


def _frames(root: Path) -> list[Path]:
    return sorted((root / "scenes" / SCENE / "frames").iterdir())


def test_a_sequence_whose_frames_changed_is_annotated_again(seq: Path, capsys) -> None:
    assert main(["annotate", str(seq), "--quiet", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["skipped"] == 1  # nothing changed
    shutil.rmtree(_frames(seq)[-1])  # a frame folder deleted
    assert main(["annotate", str(seq), "--quiet", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["done"] == 1 and doc["skipped"] == 0
    ann = json.loads((seq / "scenes" / SCENE / "annotation.json").read_text())
    assert set(ann["frames"]) == {f.name for f in _frames(seq)}


def test_results_in_the_other_layout_are_refused_in_one_line(seq: Path, tmp_path, capsys):
    flat = tmp_path / "results"
    flat.mkdir()
    (flat / f"{SCENE}.json").write_text("[]")  # a fixed rig's layout, on a sequence
    assert main(["evaluate", str(seq), "--results", str(flat)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "<scene>/<frame>.json" in err and str(flat) in err


def test_results_per_frame_on_single_shots_are_refused(sample_copy: Path, tmp_path, capsys):
    nested = tmp_path / "results" / "000000"
    nested.mkdir(parents=True)
    (nested / "000000.json").write_text("[]")
    assert main(["evaluate", str(sample_copy), "--results", str(nested.parent)]) == 2
    assert "single shots" in capsys.readouterr().err


def test_occlusion_from_other_poses_is_not_up_to_date(sample_copy: Path, capsys) -> None:
    assert main(["occlusion", str(sample_copy), "--quiet", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["done"] == 4
    assert main(["occlusion", str(sample_copy), "--quiet", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["skipped"] == 4
    assert main(["occlusion", str(sample_copy), "--poses", "gt", "--quiet", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["done"] == 4  # other poses: done again
    vis = json.loads((sample_copy / "scenes" / SCENE / "visibility.json").read_text())
    assert vis["poses"] == "gt"
    args = ["occlusion", str(sample_copy), "--poses", "gt", "--depth-tolerance", "2"]
    assert main([*args, "--quiet", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["done"] == 4  # another tolerance: again


def test_frames_left_out_are_named_by_annotate_check_and_export(seq: Path, tmp_path, capsys):
    frames = _frames(seq)
    for frame in frames[2:4]:  # two frames that read no marker
        for png in frame.glob("*.png"):
            if png.name != "depth.png":
                img = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
                cv2.imwrite(str(png), np.full_like(img, 128))
    assert main(["annotate", str(seq), "--quiet"]) == 0
    err = capsys.readouterr().err
    ann = json.loads((seq / "scenes" / SCENE / "annotation.json").read_text())
    left = sorted(n for n, f in ann["frames"].items() if f["scene_T_rig"] is None)
    assert {frames[2].name, frames[3].name} <= set(left)
    line = f"{len(left)} of {len(frames)} frames left out: {', '.join(left)} not posed: "
    assert f"scene {SCENE}: {line}no_known_markers" in err
    assert main(["check", str(seq)]) == 0  # a warning, not an error
    assert f"warning: {line}" in capsys.readouterr().out
    dst = tmp_path / "bop"
    args = ["export", str(seq), str(dst), "--format", "bop", "--include-pending", "--quiet"]
    assert main([*args, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert sorted(doc["frames_left_out"][SCENE]) == left
    assert main([*args, "--overwrite"]) == 0
    exported = f"{len(left)} frames left out: {', '.join(left)} not posed: no_known_markers"
    assert f"scene {SCENE}: {exported}" in capsys.readouterr().err


def _edit_object(root: Path, edit) -> Path:
    path = root / "objects" / "brick" / "object.yaml"
    doc = yaml.safe_load(path.read_text())
    edit(doc)
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.parametrize(
    "edit, says",
    [
        (lambda d: d["markers"]["sites"][0][0].__setitem__(0, "-5.0"), "without quotes"),
        (lambda d: d["markers"]["sites"][1][0].__setitem__(0, 9.0), "is not a square"),
        (lambda d: d["instances"][0]["marker_ids"].__setitem__(0, 5000), "outside DICT_4X4_1000"),
    ],
)
def test_bad_sites_and_ids_are_refused_by_every_command(sample_copy: Path, capsys, edit, says):
    path = _edit_object(sample_copy, edit)
    assert main(["check", str(sample_copy)]) == 1
    assert says in capsys.readouterr().out
    assert main(["annotate", str(sample_copy), "--force", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(path) in err and says in err


def test_a_scene_pattern_matching_nothing_is_said_so(sample_copy: Path, capsys) -> None:
    assert main(["sites", str(sample_copy), "--scenes", "zzz*", "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert "no scene matches 'zzz*'" in err and "annotation.json" not in err


def test_the_advice_fits_the_options_given(sample_copy: Path, tmp_path, capsys) -> None:
    out = tmp_path / "bop"
    assert main(["export", str(sample_copy), str(out), "--format", "bop"]) == 2
    assert "4 pending" in capsys.readouterr().err.split("--include-pending")[0]
    state = ReviewState(sample_copy)
    for sid in state.ids:
        state.set_scene(sid, "rejected")
    for extra in ([], ["--include-pending"]):  # it would not help, given or not
        assert main(["export", str(sample_copy), str(out), "--format", "bop", *extra]) == 2
        err = capsys.readouterr().err
        assert "4 rejected" in err and "--include-pending" not in err


def test_a_frame_of_another_arrangement_never_reaches_an_export(seq: Path, tmp_path, capsys):
    other = tmp_path / "other"
    args = ["synth", str(other), "--scenes", "1", "--frames", "2", "--size", "640x512"]
    assert main([*args, "--supersample", "1", "--instances", "4-6", "--seed", "6", "--quiet"]) == 0
    foreign = seq / "scenes" / SCENE / "frames" / "000099"
    shutil.copytree(other / "scenes" / SCENE / "frames" / "000001", foreign)
    assert main(["annotate", str(seq), "--quiet"]) == 0
    assert "000099" in capsys.readouterr().err  # named among the frames left out
    ann = json.loads((seq / "scenes" / SCENE / "annotation.json").read_text())
    frame = ann["frames"]["000099"]
    assert frame["scene_T_rig"] is None or "inconsistent" in frame["flags"], frame
    out = tmp_path / "bop"
    export = ["export", str(seq), str(out), "--format", "bop", "--include-pending", "--quiet"]
    assert main([*export, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert "000099" in doc["frames_left_out"][SCENE]
    exported = json.loads((out / "test" / f"{int(SCENE):06d}" / "scene_gt_left.json").read_text())
    posed = [n for n, f in ann["frames"].items() if f["scene_T_rig"] is not None]
    assert len(exported) == len([n for n in posed if n not in doc["frames_left_out"][SCENE]])


def test_a_frame_flagged_inconsistent_is_neither_exported_nor_scored(seq: Path, tmp_path, capsys):
    path = seq / "scenes" / SCENE / "annotation.json"
    ann = json.loads(path.read_text())
    name = next(n for n, f in ann["frames"].items() if f["scene_T_rig"] is not None)
    ann["frames"][name]["flags"] = ["inconsistent"]
    ann["frames"][name]["reason"] = "its markers place 2 parts differently"
    path.write_text(json.dumps(ann))
    out = tmp_path / "bop"
    export = ["export", str(seq), str(out), "--format", "bop", "--include-pending", "--quiet"]
    assert main([*export, "--json"]) == 0
    left = json.loads(capsys.readouterr().out)["frames_left_out"][SCENE]
    assert left[name] == "flagged inconsistent (its markers place 2 parts differently)"
    gt = annotator.read_ground_truth(seq)
    scored = {key for key, _ in annotator.annotations_as_results(seq, gt).poses}
    assert f"{SCENE}/{name}" not in scored and len(scored) >= 3  # the others are scored
