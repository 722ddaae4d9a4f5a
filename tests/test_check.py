"""``annotator check`` lists every problem of a dataset, one line each naming its file."""

from __future__ import annotations

import json

import cv2
import numpy as np
import yaml

from annotator.cli import main


def _run(root, capsys) -> tuple[int, str]:
    code = main(["check", str(root)])
    return code, capsys.readouterr().out


def test_clean_sample_has_no_problem(sample, capsys) -> None:
    code, out = _run(sample, capsys)
    assert code == 0 and "0 problems" in out


def test_each_problem_is_reported(sample_copy, capsys) -> None:
    root = sample_copy
    scenes = sorted((root / "scenes").iterdir())
    (scenes[0] / "left.png").unlink()  # missing image
    (scenes[1] / "left.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")  # corrupt image
    cv2.imwrite(str(scenes[2] / "left.png"), np.zeros((100, 120), np.uint8))  # wrong size
    (scenes[3] / "review.json").write_text("{oops")  # corrupt review
    (scenes[3] / "gt.json").write_text(
        json.dumps({"instances": [{"object": "bracket"}]})
    )  # malformed gt
    doc = yaml.safe_load((root / "dataset.yaml").read_text())
    doc["rig"]["cameras"][1]["K"] = [1, 0, 2, 0, 1, 2]  # malformed K
    doc["rig"]["cameras"][1]["rig_T_cam"] = [2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
    del doc["rig"]["depth"]  # depth maps exist but no scale
    (root / "dataset.yaml").write_text(yaml.safe_dump(doc))
    obj_path = root / "objects" / "brick" / "object.yaml"
    obj = yaml.safe_load(obj_path.read_text())
    obj["symmetry"] = {"class": "twisted"}
    site = np.array(obj["markers"]["sites"][0])
    normal = np.cross(site[3] - site[0], site[1] - site[0])
    obj["markers"]["sites"][0] = (
        site + 3.0 * normal / np.linalg.norm(normal)
    ).tolist()  # off the surface
    obj["instances"][1]["marker_ids"][0] = obj["instances"][0]["marker_ids"][0]  # duplicate id
    obj["instances"][2]["marker_ids"][0] = 5000  # outside the dictionary
    obj_path.write_text(yaml.safe_dump(obj))
    code, out = _run(root, capsys)
    assert code == 1
    expect = [
        (f"{scenes[0].name}/left.png", "image file is missing"),
        (f"{scenes[1].name}/left.png", "unreadable or corrupt image"),
        (f"{scenes[2].name}/left.png", "image is 120x100, the rig says"),
        (f"{scenes[3].name}/review.json", "corrupt review file"),
        (f"{scenes[3].name}/gt.json", "needs object, instance"),
        ("dataset.yaml", "rig.cameras[1].K must have 9"),
        ("dataset.yaml", "rig.cameras[1].rig_T_cam is not a rigid transform"),
        ("depth.png", "depth map present but dataset.yaml has no rig.depth"),
        ("brick/object.yaml", "unknown symmetry class 'twisted'"),
        ("brick/object.yaml", "markers.sites[0] is 3.00 mm off the mesh surface"),
        ("brick/object.yaml", "is also used by brick/01"),
        ("brick/object.yaml", "marker ids [5000] are outside DICT_4X4_1000"),
    ]
    lines = out.splitlines()
    for where, what in expect:
        assert any(where in line and what in line for line in lines), (where, what, out)


def test_missing_dataset_is_one_line(tmp_path, capsys) -> None:
    code, out = _run(tmp_path / "nothing", capsys)
    assert code == 1 and "dataset folder does not exist" in out


def test_malformed_frames_on_a_fixed_rig_are_listed_as_every_reader_refuses_them(
    sample_copy, capsys
) -> None:
    """annotation.json's ``frames`` are typed records now, read (and refused when malformed)
    whatever the rig: check lists what evaluate and export would stop on."""
    path = sample_copy / "scenes" / "000000" / "annotation.json"
    doc = json.loads(path.read_text())
    doc["frames"] = "x"
    path.write_text(json.dumps(doc))
    code, out = _run(sample_copy, capsys)
    assert code == 1 and f"{path}: frames must map frame ->" in out
    assert main(["evaluate", str(sample_copy)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(path) in err
