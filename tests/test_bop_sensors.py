"""BOP's multi-sensor layout (its industrial datasets: ``gray_<sensor>/``,
``scene_gt_<sensor>.json``, ``camera_<sensor>.json``...): the sample's rig written in it by
``export --sensors`` and read back, and the sensor BOP evaluates picked as bop_toolkit does."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_bop24 import BOP_TOOLKIT

import annotator
from annotator.formats.bop import evaluated_sensor

pytestmark = pytest.mark.slow  # a BOP export of sample_scenes made first

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def sensors(sample: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sensors") / "bop"
    subprocess.run(
        [sys.executable, "-m", "annotator", "export", str(sample), str(out), "--format", "bop"]
        + ["--include-pending", "--poses", "gt", "--sensors", "--quiet"],
        check=True,
        capture_output=True,
    )
    return out


def test_one_sensor_per_rig_camera(sensors: Path, sample: Path) -> None:
    cameras = [c.name for c in annotator.load_dataset(sample).rig.cameras]
    assert json.loads((sensors / "sensors.json").read_text()) == {
        "sensors": cameras,
        "eval_sensor": cameras[0],
    }
    scene = sensors / "test" / "000000"
    for cam in cameras:
        assert (sensors / f"camera_{cam}.json").is_file()
        for name in ("scene_gt", "scene_gt_info", "scene_camera", "scene_gt_coco"):
            assert (scene / f"{name}_{cam}.json").is_file(), (name, cam)
        for folder in ("gray", "mask", "mask_visib"):
            assert any((scene / f"{folder}_{cam}").iterdir()), (folder, cam)
    assert not (scene / "scene_gt.json").exists() and not (scene / "gray").exists()
    # the same instances in every sensor, each in its own camera's frame
    left, right = (json.loads((scene / f"scene_gt_{c}.json").read_text())["0"] for c in cameras)
    assert [g["obj_id"] for g in left] == [g["obj_id"] for g in right]
    assert not np.allclose(left[0]["cam_t_m2c"], right[0]["cam_t_m2c"])


def test_read_back(sensors: Path) -> None:
    """The ground truth read back is the first camera's: its sensor's poses, image by image."""
    scene = sensors / "test" / "000000"
    assert evaluated_sensor(scene) == "_left"
    gt = annotator.read_ground_truth(sensors)
    assert gt.format == "bop" and gt.scenes == ["0/0", "1/0", "2/0", "3/0"]
    written = json.loads((scene / "scene_gt_left.json").read_text())["0"]
    for oid in {g["obj_id"] for g in written}:
        mine = [g for g in written if g["obj_id"] == oid]
        got = gt.poses[("0/0", gt.object_ids[oid])]
        assert np.allclose(np.asarray(got.t), [g["cam_t_m2c"] for g in mine])


def test_bop24_on_the_sensor_layout(sensors: Path, tmp_path: Path) -> None:
    """bop_toolkit's numbers: the results are in the first camera, which is evaluated.
    bop_toolkit itself, given this export as an industrial dataset (sensors ``left`` with gray
    and depth and ``right`` with gray, ``eval_sensor`` left, added to its dataset_params.py),
    printed these same numbers."""
    report = tmp_path / "report.json"
    run = subprocess.run(
        [sys.executable, "-m", "annotator", "evaluate", str(sensors), "--bop24", "--results"]
        + [str(DATA / "bop24_results.csv"), "--json", str(report)],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr
    got = json.loads(report.read_text())["bop24"]
    for key, value in BOP_TOOLKIT.items():
        assert got[key] == pytest.approx(value, abs=1e-12), key


@pytest.mark.parametrize(
    ("dataset", "want"),
    [("ipd", "_photoneo"), ("xyzibd", "_xyz"), ("itoddmv", "_3dlong"), ("mine", "_3dlong")],
)
def test_bop_evaluates_its_own_sensor(tmp_path: Path, dataset: str, want: str) -> None:
    scene = tmp_path / dataset / "test" / "000000"
    scene.mkdir(parents=True)
    for sensor in ("cam1", "photoneo", "xyz", "3dlong"):
        (scene / f"scene_gt_{sensor}.json").write_text("{}")
        (scene / f"scene_gt_info_{sensor}.json").write_text("{}")
    assert evaluated_sensor(scene) == want


def test_the_multiview_targets_list_every_sensors_image_of_a_shot(sensors: Path, sample: Path):
    """BOP 2025's multi-view targets: one entry per shot, the image of every sensor (as in
    BOP's IPD: ``{"scene_id": 0, "im_id": [["photoneo", 0], ["cam1", 0], ...]}``)."""
    cameras = [c.name for c in annotator.load_dataset(sample).rig.cameras]
    moments = json.loads((sensors / "test_targets_multiview_bop25.json").read_text())
    images = json.loads((sensors / "test_targets_bop24.json").read_text())
    assert len(moments) == len(images) == 4
    for moment, image in zip(moments, images):
        assert moment == {
            "scene_id": image["scene_id"],
            "im_id": [[c, image["im_id"]] for c in cameras],
        }


def test_a_dataset_with_only_multiview_targets_scores_the_evaluated_sensors_images(
    sensors: Path, tmp_path: Path
) -> None:
    """Without test_targets_bop24.json, 6D detection is scored on the evaluated sensor's
    images of the multi-view targets: the same images, so the same numbers."""
    import shutil

    only = tmp_path / "bop"
    shutil.copytree(sensors, only)
    (only / "test_targets_bop24.json").unlink()
    (only / "test_targets_bop19.json").unlink()
    report = tmp_path / "report.json"
    args = [sys.executable, "-m", "annotator", "evaluate", str(only), "--bop24", "--results"]
    run = subprocess.run(
        [*args, str(DATA / "bop24_results.csv"), "--json", str(report)],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr
    assert "test_targets_multiview_bop25.json" in run.stdout  # the targets it scored on
    got = json.loads(report.read_text())["bop24"]
    for key, value in BOP_TOOLKIT.items():
        assert got[key] == pytest.approx(value, abs=1e-12), key
    (only / "test_targets_multiview_bop25.json").write_text('[{"scene_id": 0, "im_id": 3}]')
    run = subprocess.run([*args, str(DATA / "bop24_results.csv")], capture_output=True, text=True)
    assert run.returncode == 2
    err = run.stderr.strip()
    assert len(err.splitlines()) == 1 and "entry 0" in err and "multiview" in err
