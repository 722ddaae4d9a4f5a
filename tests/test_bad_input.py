"""Bad input met by a new user and a hostile one: every reader answers in one line naming the
file, the entry and the field; nothing wrong is accepted in silence.

Each test sets up one of the inputs that once gave a traceback, a hang or a silent wrong
answer, then checks what the user sees.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from annotator.cli import main
from annotator.dataset import load_dataset, read_poses
from annotator.dataset.review import Review, now_iso, poses_fingerprint, write_review
from annotator.errors import UserError
from annotator.evaluation.metrics import scene_curve
from annotator.io.documents import MAX_NESTING, json_depth, parse_json


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "Traceback" not in err
    return err


def _edit_json(path: Path, edit) -> None:
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))


def _check(root: Path, capsys) -> tuple[int, str]:
    code = main(["check", str(root)])
    return code, capsys.readouterr().out


# ------------------------------------------------------------------ values of the wrong type


@pytest.mark.parametrize(
    "file, field, value, message",
    [
        ("gt.json", ("occlusion", "rate"), "abc", "occlusion.rate must be a number, got 'abc'"),
        ("gt.json", ("occlusion", "rate"), 1.5, "occlusion.rate is 1.5, outside [0, 1]"),
        ("annotation.json", ("uncertainty_mm",), "abc", "uncertainty_mm must be a number"),
        ("annotation.json", ("depth", "agreement"), True, "depth.agreement must be a number"),
    ],
)
def test_a_string_where_a_number_belongs_is_named(
    sample_copy, capsys, file, field, value, message
) -> None:
    path = sample_copy / "scenes" / "000001" / file

    def edit(doc):
        node = doc["instances"][2]
        for key in field[:-1]:
            node = node.setdefault(key, {})
        node[field[-1]] = value

    _edit_json(path, edit)
    assert main(["evaluate", str(sample_copy)]) == 2
    err = _one_line(capsys)
    assert f"{path}: instances[2] (" in err and message in err
    code, out = _check(sample_copy, capsys)
    assert code == 1 and message in out


@pytest.mark.parametrize("field, where", [("cam_t_m2c", 1), ("cam_R_m2c", 4)])
def test_nan_in_a_pose_is_refused(sample_copy, capsys, field, where) -> None:
    path = sample_copy / "scenes" / "000000" / "gt.json"
    # json writes NaN as the bare word NaN, which Python's reader takes.
    _edit_json(path, lambda d: d["instances"][0][field].__setitem__(where, float("nan")))
    assert main(["evaluate", str(sample_copy)]) == 2
    assert "instances[0] (" in (err := _one_line(capsys)) and f"{field} has a NaN" in err
    code, out = _check(sample_copy, capsys)
    assert code == 1 and f"{field} has a NaN" in out


@pytest.mark.slow
def test_a_nan_pose_is_never_exported(sample_copy, tmp_path, capsys) -> None:
    scene = sample_copy / "scenes" / "000000"
    fp = poses_fingerprint(read_poses(scene / "annotation.json"))
    write_review(scene / "review.json", Review("accepted", {}, now_iso(), fp))
    _edit_json(
        scene / "annotation.json", lambda d: d["instances"][0]["cam_t_m2c"].__setitem__(0, None)
    )
    for fmt in ("bop", "sileane"):
        out = tmp_path / fmt
        code = main(
            ["export", str(sample_copy), str(out), "--format", fmt, "--quiet", "--include-pending"]
        )
        err = capsys.readouterr().err
        assert code == 1 and "failed: scene 000000:" in err and "cam_t_m2c has a NaN" in err


def test_unknown_objects_and_duplicated_instances_in_gt_are_reported(sample_copy, capsys) -> None:
    gt = sample_copy / "scenes" / "000002" / "gt.json"
    _edit_json(gt, lambda d: d["instances"][0].__setitem__("object", "sprocket"))
    code, out = _check(sample_copy, capsys)
    assert code == 1 and f"{gt}: unknown object 'sprocket'" in out
    assert main(["evaluate", str(sample_copy)]) == 2
    assert "instances[0]: unknown object 'sprocket'" in _one_line(capsys)

    _edit_json(gt, lambda d: d["instances"].append(dict(d["instances"][1])))
    code, out = _check(sample_copy, capsys)
    assert code == 1 and "is listed twice" in out
    assert main(["evaluate", str(sample_copy)]) == 2
    assert "the instance is listed twice" in _one_line(capsys)


# ------------------------------------------------------------------------- nesting bombs


def _deep_json(depth: int) -> str:
    return "[" * depth + "]" * depth


def test_deeply_nested_json_is_one_line_and_annotate_goes_on(sample_copy, capsys) -> None:
    scenes = sample_copy / "scenes"
    (scenes / "000000" / "annotation.json").write_text(_deep_json(100_000))
    (scenes / "000001" / "gt.json").write_text('{"instances": ' + _deep_json(100_000) + "}")
    (scenes / "000002" / "review.json").write_text(_deep_json(MAX_NESTING + 1))
    code, out = _check(sample_copy, capsys)
    assert code == 1
    assert f"nested deeper than {MAX_NESTING} levels" in out
    assert "000002/review.json: corrupt review file (nested deeper" in out
    assert main(["evaluate", str(sample_copy)]) == 2
    assert "000001/gt.json: nested deeper" in _one_line(capsys)
    # annotate: the corrupt annotation.json is not up to date, so the scene is redone.
    code = main(["annotate", str(sample_copy), "--scenes", "000000", "--quiet", "--workers", "1"])
    assert code == 0, capsys.readouterr().err
    assert read_poses(scenes / "000000" / "annotation.json")


@pytest.mark.parametrize(
    ("text", "depth"),
    [
        ("[]", 1),
        ('[[1, 2], {"a": [3]}]', 3),
        ('"[[["', 0),  # brackets inside a string do not nest
        (r'["a\\", ["\"]"]]', 2),  # an escaped backslash ends the string; \" does not
        (r'{"k\"[": [[[]]]}', 4),
        ('["é[", {}]', 2),
    ],
)
def test_nesting_counts_brackets_outside_strings(text: str, depth: int) -> None:
    assert json_depth(text) == depth
    assert parse_json(text, "x.json") == json.loads(text)


def test_json_the_fast_parser_refuses_is_read_as_the_standard_library_reads_it() -> None:
    # NaN and Infinity are Python's JSON; the formats' checks then name them.
    assert math.isnan(parse_json("[NaN]", "x.json")[0])
    assert parse_json('{"t": -Infinity}', "x.json") == {"t": -math.inf}
    with pytest.raises(UserError, match=r"x.json: not valid JSON \(Expecting value: line 1"):
        parse_json("[1, ]", "x.json")
    with pytest.raises(UserError, match=f"nested deeper than {MAX_NESTING}"):
        parse_json(_deep_json(MAX_NESTING + 1), "x.json")
    assert parse_json(_deep_json(MAX_NESTING), "x.json") is not None


@pytest.mark.slow
def test_deeply_nested_results_and_yaml_are_one_line(sample_copy, tmp_path, capsys) -> None:
    results = tmp_path / "results"
    results.mkdir()
    (results / "000000.json").write_text(_deep_json(100_000))
    assert main(["evaluate", str(sample_copy), "--results", str(results)]) == 2
    assert f"000000.json: nested deeper than {MAX_NESTING} levels" in _one_line(capsys)
    (sample_copy / "dataset.yaml").write_text("a: " + "[" * 5000 + "]" * 5000 + "\n")
    code, out = _check(sample_copy, capsys)
    assert code == 1 and "dataset.yaml: nested deeper than" in out
    assert main(["annotate", str(sample_copy)]) == 2
    assert "dataset.yaml: nested deeper than" in _one_line(capsys)


# ------------------------------------------------------------------------------- paths


def _set_mesh(root: Path, value: str) -> Path:
    path = root / "objects" / "brick" / "object.yaml"
    doc = yaml.safe_load(path.read_text())
    doc["mesh"] = value
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.parametrize("kind", ["absolute", "parent", "passwd", "symlink"])
def test_mesh_paths_stay_inside_the_dataset(sample_copy, tmp_path, capsys, kind) -> None:
    mesh = (
        sample_copy
        / "objects"
        / "brick"
        / yaml.safe_load((sample_copy / "objects" / "brick" / "object.yaml").read_text())["mesh"]
    )
    outside = tmp_path / "elsewhere.ply"
    outside.write_bytes(mesh.read_bytes())
    if kind == "absolute":
        value = str(outside)
    elif kind == "parent":
        value = "../../../elsewhere.ply"
    elif kind == "passwd":
        value = "../" * 40 + "etc/passwd"
    else:
        (mesh.parent / "link.ply").symlink_to(outside)
        value = "link.ply"
    yaml_path = _set_mesh(sample_copy, value)
    code, out = _check(sample_copy, capsys)
    assert code == 1 and f"{yaml_path}: mesh {value!r} lies outside the dataset" in out
    assert main(["annotate", str(sample_copy), "--quiet"]) == 2
    assert "lies outside the dataset" in _one_line(capsys)


def test_a_mesh_of_an_unknown_type_is_named(sample_copy, capsys) -> None:
    (sample_copy / "objects" / "brick" / "notes.txt").write_text("not a mesh")
    _set_mesh(sample_copy, "notes.txt")
    code, out = _check(sample_copy, capsys)
    assert code == 1 and "notes.txt: not a mesh file type this tool reads (.ply" in out


def test_an_inside_out_mesh_is_reported(sample_copy, capsys) -> None:
    import trimesh

    obj = sample_copy / "objects" / "brick"
    name = yaml.safe_load((obj / "object.yaml").read_text())["mesh"]
    mesh = trimesh.load(obj / name, force="mesh", process=False)
    trimesh.Trimesh(mesh.vertices, mesh.faces[:, ::-1], process=False).export(obj / name)
    code, out = _check(sample_copy, capsys)
    assert code == 1 and "mesh is inside out (signed volume -" in out


@pytest.mark.slow
def test_scenes_that_is_a_file_or_broken_links_are_reported(sample_copy, capsys) -> None:
    scenes = sample_copy / "scenes"
    (scenes / "000009").symlink_to(scenes / "nowhere")  # dangling
    (scenes / "loop").symlink_to(scenes / "loop")  # a loop
    code, out = _check(sample_copy, capsys)
    assert code == 1
    assert f"{scenes / '000009'}: a symbolic link that leads nowhere" in out
    assert f"{scenes / 'loop'}: a symbolic link that leads nowhere" in out
    code = main(["annotate", str(sample_copy), "--quiet", "--workers", "1"])
    err = capsys.readouterr().err
    assert code == 1 and "failed: scene 000009:" in err and "failed: scene loop:" in err

    other = sample_copy.parent / "flat"
    (other).mkdir()
    for f in ("dataset.yaml", "objects", "background_depth.png"):
        os.symlink(sample_copy / f, other / f)
    (other / "scenes").write_text("not a folder")
    code, out = _check(other, capsys)
    assert code == 1 and f"{other / 'scenes'}: is not a folder" in out


def test_an_image_that_is_a_folder_is_called_a_folder(sample_copy, capsys) -> None:
    image = sample_copy / "scenes" / "000000" / "left.png"
    image.unlink()
    image.mkdir()
    code, out = _check(sample_copy, capsys)
    assert code == 1 and f"{image}: is a folder, not an image file" in out


# ------------------------------------------------------------------------- CLI values


@pytest.mark.parametrize(
    "argv, option",
    [
        (["synth", "OUT", "--seed", "-1"], "--seed"),
        (["synth", "OUT", "--blur", "nan"], "--blur"),
        (["synth", "OUT", "--noise", "inf"], "--noise"),
        (["synth", "OUT", "--scenes", "0"], "--scenes"),
        (["markers", "brick", "OUT", "--seed", "-3"], "--seed"),
        (["markers", "brick", "OUT", "--size", "nan"], "--size"),
        (["evaluate", "GT", "--max-occlusion", "nan"], "--max-occlusion"),
        (["evaluate", "GT", "--threshold=-inf"], "--threshold"),
        (["occlusion", "DS", "--depth-tolerance", "nan"], "--depth-tolerance"),
        (["annotate", "DS", "--ray", "auto", "--ray-wait", "nan"], "--ray-wait"),
    ],
)
def test_negative_seeds_and_non_finite_options_are_refused(tmp_path, capsys, argv, option) -> None:
    argv = [str(tmp_path / a) if a.isupper() else a for a in argv]
    assert main(argv) == 2
    assert f"error: argument {option}: must be a" in _one_line(capsys)
    assert not any(tmp_path.iterdir())


# ------------------------------------------------------------------------- results CSV


def _results_lines(sample: Path) -> list[tuple[str, str, str, str, str, str]]:
    rows = []
    for sc in load_dataset(sample).scenes():
        for k, p in enumerate(read_poses(sc.gt_path)):
            R = " ".join(f"{v:.9f}" for v in p.R.ravel())
            t = " ".join(f"{v:.6f}" for v in p.t)
            rows.append((sc.id, "0", p.object, f"{1 - 0.01 * k:.2f}", R, t))
    return rows


def test_a_bom_and_any_column_order_are_read(sample, tmp_path, capsys) -> None:
    rows = _results_lines(sample)

    def scores(path: Path) -> dict:
        out = tmp_path / f"{path.stem}.json"
        assert main(["evaluate", str(sample), "--results", str(path), "--json", str(out)]) == 0
        capsys.readouterr()
        return json.loads(out.read_text())["overall"]

    plain = tmp_path / "plain.csv"
    plain.write_text(
        "scene_id,im_id,obj_id,score,R,t,time\n" + "".join(",".join(r) + ",-1\n" for r in rows)
    )
    reference = scores(plain)
    assert reference["TP"] > 0
    bom_header = tmp_path / "bom_header.csv"
    bom_header.write_text(plain.read_text(), encoding="utf-8-sig")
    bom_only = tmp_path / "bom_only.csv"
    bom_only.write_text("".join(",".join(r) + ",-1\n" for r in rows), encoding="utf-8-sig")
    reordered = tmp_path / "reordered.csv"
    reordered.write_text(
        "time,t,R,score,obj_id,im_id,scene_id\n"
        + "".join(f"-1,{r[5]},{r[4]},{r[3]},{r[2]},{r[1]},{r[0]}\n" for r in rows)
    )
    for path in (bom_header, bom_only, reordered):
        assert scores(path) == reference, path.name


def test_numeric_csv_read_in_one_go_names_bad_lines_as_before(tmp_path, capsys) -> None:
    """The fast path (numbers only) and the cell-by-cell one name the same line and field."""
    from test_evaluation import _bop

    root = _bop(tmp_path)
    good = "1,0,1,0.9,1 0 0 0 1 0 0 0 1,0 0 500,-1\n"
    cases = {
        "1,0,1,0.9,1 0 0 0 1 0 0 0,0 0 500 7,-1\n": "line 3: R must be 9 numbers",
        "1,0,1,0.9,2 0 0 0 1 0 0 0 1,0 0 500,-1\n": "line 3: R is not a rotation matrix",
        "1,0,9,0.9,1 0 0 0 1 0 0 0 1,0 0 500,-1\n": "line 3: result for unknown object '9'",
    }
    for bad, message in cases.items():
        csv = tmp_path / "r.csv"
        csv.write_text("scene_id,im_id,obj_id,score,R,t,time\n" + good + bad + good)
        assert main(["evaluate", str(root), "--results", str(csv)]) == 2
        assert f"r.csv: {message}" in _one_line(capsys)
    header = tmp_path / "h.csv"
    header.write_text("scene_id,im_id,score,R,t\n" + good)
    assert main(["evaluate", str(root), "--results", str(header)]) == 2
    assert "line 1: the header lacks obj_id" in _one_line(capsys)


def test_a_scene_with_many_results_needs_memory_linear_in_them() -> None:
    """200,000 results against 5 true poses in one scene: a |P| x |P| table would need
    hundreds of GB; the counts must still be those of the definition."""
    rng = np.random.default_rng(3)
    n_p, n_t = 200_000, 5
    D = rng.uniform(0, 20, (n_p, n_t))
    D[7, 2] = 0.5  # one clear match of true pose 2
    scores = rng.random(n_p)
    scores[7] = 2.0  # ranked first
    curve = scene_curve(D, scores, np.zeros(n_t), threshold=1.0, max_occlusion=0.5)
    matched = (D.min(axis=1) <= 1.0).sum()
    assert curve.tp[1] == 1 and curve.fp[1] == 0 and curve.fn[1] == n_t - 1
    assert curve.tp[-1] + curve.fp[-1] == n_p and curve.tp[-1] <= min(n_t, matched)
    assert curve.fn[-1] == n_t - curve.tp[-1]
