"""Issue 53's scoring input: COCO masks that would hang pycocotools' C decoder are refused in
a second, and so are numbers no detector gives (NaN scores and times, negative boxes, ids,
masks of another size), empty or malformed targets and a sensors.json naming no sensor of
the scenes; what is scored without a word is said (results of unknown scenes, negative
BOP scores)."""

from __future__ import annotations

import copy
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from cli_calls import one_error_line, run_cli

pytestmark = pytest.mark.slow  # a BOP export of sample_scenes made first

DATA = Path(__file__).parent / "data"
COCO = json.loads((DATA / "coco_results.json").read_text())
CSV = (DATA / "bop24_results.csv").read_text().splitlines()


def _coco_file(tmp_path: Path, change) -> Path:
    doc = copy.deepcopy(COCO)
    change(doc)
    path = tmp_path / "results.json"
    path.write_text(json.dumps(doc))
    return path


def _counts(doc, f) -> None:
    seg = doc[2]["segmentation"]
    seg["counts"] = f(seg["counts"])


@pytest.mark.parametrize(
    ("change", "says"),
    [
        (lambda d: _counts(d, lambda c: c[: len(c) // 2]), "its runs add up to 932525 pixels"),
        (lambda d: _counts(d, lambda c: c[:-1] + "o"), "the RLE string is cut short"),
        (
            lambda d: _counts(d, lambda c: "".join(chr(48 + ord(x) * 7 % 64) for x in c)),
            "segmentation: ",
        ),
        (lambda d: _counts(d, lambda c: c + "~~"), "character '~' is not of an RLE string"),
    ],
)
def test_masks_that_would_hang_the_c_decoder_are_refused_at_once(
    bop_export: Path, tmp_path: Path, change, says
) -> None:
    results = _coco_file(tmp_path, change)
    t0 = time.monotonic()
    run = subprocess.run(
        [sys.executable, "-m", "annotator", "evaluate", str(bop_export), "--coco-results"]
        + [str(results)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 2 and time.monotonic() - t0 < 30
    (line,) = run.stderr.strip().splitlines()
    assert line.startswith(f"annotator: error: {results}: result 2: ") and says in line


@pytest.mark.parametrize(
    ("change", "says"),
    [
        (lambda d: d[2].update(score=float("nan")), "result 2: 'score' is not a finite number"),
        (lambda d: d[2].update(time=-3.0), "result 2: 'time' is negative"),
        (lambda d: d[2].update(category_id=-2), "result 2: 'category_id' is negative"),
        (lambda d: d[2].update(bbox=[10, 10, -5, 20]), "negative width or height"),
        (
            lambda d: [r["segmentation"].update(size=[100, 100]) for r in d],
            "its runs add up to 1310720 pixels, not 100 x 100",
        ),
    ],
)
def test_coco_numbers_no_detector_gives_are_refused(
    bop_export: Path, tmp_path: Path, capsys, change, says
) -> None:
    results = _coco_file(tmp_path, change)
    assert says in one_error_line(
        ["evaluate", str(bop_export), "--coco-results", str(results)], capsys
    )


def test_a_mask_of_another_size_than_its_image_is_refused(bop_export: Path, tmp_path, capsys):
    import numpy as np
    from pycocotools import mask

    whole = mask.encode(np.asfortranarray(np.ones((100, 80), np.uint8)))["counts"].decode()

    def change(doc) -> None:
        doc[0]["segmentation"] = {"size": [100, 80], "counts": whole}

    results = _coco_file(tmp_path, change)
    line = one_error_line(["evaluate", str(bop_export), "--coco-results", str(results)], capsys)
    assert "result 0: its mask is 80x100 but image" in line and "is 1280x1024" in line


def test_results_of_unknown_scenes_are_said(bop_export: Path, tmp_path: Path, capsys) -> None:
    results = _coco_file(tmp_path, lambda d: d[3].update(scene_id=99))
    code, out, err = run_cli(["evaluate", str(bop_export), "--coco-results", str(results)], capsys)
    assert code == 0, err
    assert "results of scenes the targets do not list (9, 99): not scored" in out


def _csv(tmp_path: Path, line: int, column: int, value: str) -> Path:
    rows = [r.split(",") for r in CSV]
    rows[line][column] = value
    path = tmp_path / "results.csv"
    path.write_text("\n".join(",".join(r) for r in rows) + "\n")
    return path


@pytest.mark.parametrize(
    ("column", "value", "says"),
    [
        (6, "nan", "line 4: time is nan; it must be seconds (or -1 when unknown"),
        (6, "-5", "line 4: time is -5"),
        (3, "nan", "line 4: score is 'nan'; it must be finite"),
    ],
)
def test_bop_times_and_scores_no_method_takes(
    bop_export: Path, tmp_path: Path, capsys, column, value, says
) -> None:
    results = _csv(tmp_path, 3, column, value)
    args = ["evaluate", str(bop_export), "--results", str(results), "--bop24"]
    assert says in one_error_line(args, capsys)


def test_a_negative_bop_score_is_said_and_unknown_time_is_fine(bop_export, tmp_path, capsys):
    results = _csv(tmp_path, 3, 3, "-0.5")
    rows = results.read_text().splitlines()
    rows[5] = ",".join(rows[5].split(",")[:6] + ["-1"])  # BOP's "time unknown"
    results.write_text("\n".join(rows) + "\n")
    code, out, err = run_cli(
        ["evaluate", str(bop_export), "--results", str(results), "--bop24"], capsys
    )
    assert code == 0, err
    assert "1 results of results.csv have a negative score" in out


def _refused(export: Path, name: str, content: str, tmp_path: Path, capsys) -> str:
    """``evaluate --bop24`` of a copy of ``export`` whose file ``name`` holds ``content``:
    its one error line."""
    data = tmp_path / "bop"
    shutil.copytree(export, data)
    (data / name).write_text(content)
    args = ["evaluate", str(data), "--results", str(DATA / "bop24_results.csv"), "--bop24"]
    return one_error_line(args, capsys)


@pytest.mark.parametrize(
    ("content", "says"),
    [
        ("[]", "lists no target: nothing would be scored"),
        ('[{"scene_id": 0.5, "im_id": 0}]', "entry 0: scene_id must be a whole number of 0 or more, got 0.5"),
        ('[{"scene_id": 0, "im_id": "3"}]', "entry 0: im_id must be a whole number of 0 or more, got '3'"),
        ('[{"scene_id": -1, "im_id": 0}]', "got -1"),
    ],
)  # fmt: skip
def test_empty_or_malformed_targets_are_refused(
    bop_export: Path, tmp_path: Path, capsys, content, says
) -> None:
    line = _refused(bop_export, "test_targets_bop24.json", content, tmp_path, capsys)
    assert "test_targets_bop24.json: " in line and says in line


@pytest.mark.parametrize(
    ("content", "says"),
    [
        ('{"sensors": ["left", "right"], "eval_sensor": "top"}',
         "eval_sensor must name a sensor the scenes have (left, right), got 'top'"),
        ("{oops", "not valid JSON"),
    ],
)  # fmt: skip
def test_a_sensors_json_naming_no_sensor_is_refused(
    bop_sensors_export: Path, tmp_path: Path, capsys, content, says
) -> None:
    line = _refused(bop_sensors_export, "sensors.json", content, tmp_path, capsys)
    assert "sensors.json: " in line and says in line
