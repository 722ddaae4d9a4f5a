"""Calibration from captures as users make them: colour-inverted boards, a mirrored camera, a
custom dictionary, a plain chessboard, videos, a board that covers only the image centre
(held-out error, model choice, extrapolation warning), and their bad inputs.

Each capture is rendered once per module by ``annotator synth --calibration`` with the truth
beside it, and calibrated through the command line; the recovered rig is compared with the
truth within the tolerances of tests/test_calibrate.py.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from cli_calls import one_error_line, run_cli

from annotator.annotation.batch import description_digest
from annotator.calibration.board import BoardSpec
from annotator.calibration.captures import find_captures
from annotator.cli import main
from annotator.dataset import load_dataset
from annotator.errors import UserError
from annotator.geometry.transforms import invert
from annotator.markers.dictionary import dictionary, min_distance
from annotator.runner.bundle import description_files
from annotator.synthesis.board import write_videos

TOLERANCE = {"focal_pct": 0.2, "principal_px": 5.0, "position_mm": 0.3, "rotation_deg": 0.2}
#: Smaller images and fewer shots than tests/test_calibrate.py's, to keep the module quick.
SYNTH = ["--noise", "12", "--blur", "1.0", "--size", "1024x820", "--workers", "2", "--quiet"]
SHOTS = 14


def _synth(out: Path, *extra: str) -> Path:
    assert main(["synth", "--calibration", str(out), *SYNTH, *extra]) == 0
    return out


def _rig_errors(rig_doc: dict, truth: dict) -> dict[str, float]:
    """Worst errors over the cameras of a ``rig:`` mapping against the truth's."""
    out = dict.fromkeys(TOLERANCE, 0.0)
    for cam, true in zip(rig_doc["cameras"], truth["rig"]["cameras"]):
        K, K0 = np.reshape(cam["K"], (3, 3)), np.reshape(true["K"], (3, 3))
        T, T0 = np.reshape(cam["rig_T_cam"], (4, 4)), np.reshape(true["rig_T_cam"], (4, 4))
        d = invert(T0) @ T
        angle = np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1)))
        for key, value in (
            ("focal_pct", max(abs(K[i, i] / K0[i, i] - 1) * 100 for i in (0, 1))),
            ("principal_px", np.linalg.norm(K[:2, 2] - K0[:2, 2])),
            ("position_mm", np.linalg.norm(T[:3, 3] - T0[:3, 3])),
            ("rotation_deg", angle),
        ):
            out[key] = max(out[key], float(value))
    return out


def _calibrate(
    captures: Path, tmp: Path, capsys: pytest.CaptureFixture, *extra: str
) -> tuple[str, dict, dict]:
    """Calibrate through the CLI; the printed lines, report.json and the rig written."""
    ds, report = tmp / "ds", tmp / "report"
    code, out, err = run_cli(
        [
            "calibrate",
            str(captures),
            "--dataset",
            str(ds),
            "--report",
            str(report),
            "--yes",
            *extra,
        ],
        capsys,
    )
    assert code == 0, err
    doc = json.loads((report / "report.json").read_text())
    rig = yaml.safe_load((ds / "dataset.yaml").read_text())["rig"]
    return out, doc, rig


def _truth(captures: Path) -> dict:
    return yaml.safe_load((captures / "truth.yaml").read_text())


@pytest.fixture(scope="module")
def awkward(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A webcam-like capture: a colour-inverted board of a custom dictionary (written by
    `annotator markers --write-dictionary`), the right camera mirrored."""
    root = tmp_path_factory.mktemp("awkward")
    dict_file = root / "my_dict.yml"
    args = ["markers", "--write-dictionary", str(dict_file), "--count", "20", "--bits", "5"]
    assert main([*args, "--min-distance", "6"]) == 0
    return _synth(
        root / "captures",
        "--scenes", str(SHOTS), "--inverted", "--mirror", "right",
        "--board-dictionary", str(dict_file),
    )  # fmt: skip


def test_inverted_board_mirrored_camera_custom_dictionary(
    awkward: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    board = yaml.safe_load((awkward / "board.yaml").read_text())
    assert board["inverted"] is True and board["dictionary"] == "dictionary.yml"
    # The right camera's files really are mirrored: the board reads only once flipped back.
    img = cv2.imread(str(awkward / "right" / "000.png"), cv2.IMREAD_GRAYSCALE)
    aruco = cv2.aruco.ArucoDetector(dictionary(str(awkward / "dictionary.yml")))
    plain = aruco.detectMarkers(255 - img)[1]
    flipped = aruco.detectMarkers(255 - img[:, ::-1].copy())[1]
    assert (0 if plain is None else len(plain)) < 3 <= len(flipped)
    # Calibrated as a user would who does not know the board is inverted (auto overrides the
    # board.yaml of the synthetic captures, which says so).
    out, doc, rig = _calibrate(awkward, tmp_path, capsys, "--inverted", "auto", "--folds", "3")
    assert "camera right: its images are mirrored" in out
    assert f"camera left: the board reads colour-inverted in {SHOTS} of its {SHOTS} shots" in out
    assert [c.get("flip") for c in rig["cameras"]] == [None, "horizontal"]
    assert [c["flip"] for c in doc["cameras"]] == [None, "horizontal"]
    errors = _rig_errors(rig, _truth(awkward))
    assert all(errors[k] < tol for k, tol in TOLERANCE.items()), errors
    assert all(s["used"] for s in doc["shots"])
    # A board all over the image: the rig predicts shots it did not fit nearly as well as
    # those it did, and nothing is extrapolated.
    held = doc["held_out"]
    assert held["folds"] == 3 and doc["rms_px"] < held["rms_px"] < 1.6 * doc["rms_px"]
    assert {(p["from"], p["to"]) for p in held["pairs"]} == {("left", "right"), ("right", "left")}
    assert not any(c["extrapolation"]["extrapolated"] for c in doc["cameras"])


def test_video_captures_paired_by_timestamps(
    awkward: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    videos = tmp_path / "videos"
    videos.mkdir()
    for name in ("board.yaml", "dictionary.yml", "truth.yaml"):
        shutil.copy(awkward / name, videos / name)
    for cam in ("left", "right"):
        shutil.copytree(awkward / cam, videos / cam)
    write_videos(videos, ["left", "right"])
    assert sorted(p.name for p in videos.iterdir() if p.suffix in (".mkv", ".txt")) == [
        "left.mkv", "left.timestamps.txt", "right.mkv", "right.timestamps.txt",
    ]  # fmt: skip
    out, doc, rig = _calibrate(
        videos, tmp_path, capsys, "--stride", "1", "--dist-coeffs", "4", "--folds", "2"
    )
    # The right video starts one frame early: only the timestamps pair the frames right.
    assert (
        f"videos: {SHOTS} shots, frames 0..{SHOTS - 1} of left, paired by timestamps "
        "(frame offsets 1..1)"
    ) in out
    frames = doc["videos"]["frames"]
    assert doc["videos"]["pairing"] == "timestamps" and len(frames) == SHOTS
    assert all(f["right"] == f["left"] + 1 for f in frames.values())
    assert [c.get("flip") for c in rig["cameras"]] == [None, "horizontal"]
    errors = _rig_errors(rig, _truth(awkward))
    assert all(errors[k] < tol for k, tol in TOLERANCE.items()), errors


def test_videos_paired_by_frame_index_at_a_stride(tmp_path: Path) -> None:
    for cam in ("cam_0", "cam_1"):
        writer = cv2.VideoWriter(
            str(tmp_path / f"{cam}.mkv"), cv2.VideoWriter_fourcc(*"FFV1"), 10, (64, 48), False
        )
        for k in range(7 if cam == "cam_0" else 5):
            writer.write(np.full((48, 64), 30 * k, np.uint8))
        writer.release()
    caps = find_captures(tmp_path, stride=3)
    assert caps.cameras == ("cam_0", "cam_1") and caps.pairing == "frame index"
    assert caps.shots == ("f0000", "f0003") and caps.unpaired == (6,)
    assert [caps.frames[("cam_1", s)] for s in caps.shots] == [0, 3]


def test_chessboard(
    tmp_path_factory: pytest.TempPathFactory, capsys: pytest.CaptureFixture
) -> None:
    root = tmp_path_factory.mktemp("chessboard")
    captures = _synth(root / "captures", "--scenes", "10", "--board-kind", "chessboard")
    board = yaml.safe_load((captures / "board.yaml").read_text())
    assert board["kind"] == "chessboard" and "dictionary" not in board
    _, doc, rig = _calibrate(captures, root, capsys, "--dist-coeffs", "4", "--folds", "2")
    assert all(s["used"] for s in doc["shots"]) and not doc["rejected"]
    errors = _rig_errors(rig, _truth(captures))
    assert all(errors[k] < tol for k, tol in TOLERANCE.items()), errors
    # OpenCV's rational model on request: eight coefficients, measured the same way (on a
    # lens this mild it does not predict unseen shots better).
    _, doc8, rig8 = _calibrate(
        captures, root / "rational", capsys, "--dist-coeffs", "8", "--folds", "2"
    )
    assert [len(c["dist"]) for c in rig8["cameras"]] == [8, 8]
    assert doc8["distortion_model"]["coefficients"] == 8
    assert doc8["held_out"]["rms_px"] > 0.98 * doc["held_out"]["rms_px"]


def test_symmetric_chessboard_is_refused() -> None:
    with pytest.raises(UserError, match="looks the same turned half a turn"):
        BoardSpec(8, 6, 30.0, kind="chessboard")
    with pytest.raises(UserError, match="looks the same turned half a turn"):
        BoardSpec(7, 7, 30.0, kind="chessboard")


def test_board_in_the_image_centre_gets_the_warning_and_the_simpler_model(
    tmp_path_factory: pytest.TempPathFactory, capsys: pytest.CaptureFixture
) -> None:
    root = tmp_path_factory.mktemp("centre")
    captures = _synth(
        root / "captures",
        "--scenes", "10", "--centre", "0.3", "--distance", "800-1000",
    )  # fmt: skip
    out, doc, _ = _calibrate(captures, root, capsys)
    model = doc["distortion_model"]
    assert model["coefficients"] == 4
    held = model["held_out_rms_px"]
    assert held["4"] < held["5"], held
    assert doc["held_out"]["rms_px"] == pytest.approx(held["4"], abs=1e-4)
    assert {(p["from"], p["to"]) for p in doc["held_out"]["pairs"]} == {
        ("left", "right"),
        ("right", "left"),
    }
    for cam in doc["cameras"]:
        ex = cam["extrapolation"]
        assert ex["extrapolated"] and ex["covered_fraction"] < 0.15, ex
    assert sum("the distortion model is extrapolated" in w for w in doc["warnings"]) == 2
    assert "warning: camera left: the board covered" in out and "held-out error: RMS" in out
    # The coverage picture shows the extrapolated cells (orange) around the covered region.
    img = cv2.imread(str(root / "report" / "coverage_left.png"))
    orange = (img[..., 2] > 150) & (img[..., 1] > 60) & (img[..., 1] < 120) & (img[..., 0] < 60)
    assert orange.mean() > 0.2


# ---------------------------------------------------------------- flipped cameras in datasets


def test_flipped_camera_is_read_flipped_by_every_reader(sample_copy: Path) -> None:
    """A dataset whose right camera stores mirrored images: with flip: horizontal in its rig,
    annotate reads them as calibrated and gets the same poses as from the plain images."""
    assert main(["annotate", str(sample_copy), "--scenes", "000000", "--workers", "1"]) in (0, 1)
    scene = sample_copy / "scenes" / "000000"
    plain = json.loads((scene / "annotation.json").read_text())["instances"]
    path = scene / "right.png"
    original = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), original[:, ::-1])
    text = (sample_copy / "dataset.yaml").read_text()
    (sample_copy / "dataset.yaml").write_text(
        text.replace("  - name: right\n", "  - name: right\n    flip: horizontal\n")
    )
    ds = load_dataset(sample_copy)
    assert ds.rig.flipped == {"right"}
    read = ds.scene("000000").read_image(ds.rig.camera("right"))
    assert np.array_equal(read, original)
    assert main(["check", str(sample_copy)]) == 0
    assert main(
        ["annotate", str(sample_copy), "--scenes", "000000", "--force", "--workers", "1"]
    ) in (0, 1)
    flipped = json.loads((scene / "annotation.json").read_text())["instances"]
    assert [(i["object"], i["instance"]) for i in flipped] == [
        (i["object"], i["instance"]) for i in plain
    ]
    for a, b in zip(plain, flipped):
        assert np.allclose(a["cam_t_m2c"], b["cam_t_m2c"], atol=1e-6)


def test_bad_flip_value(sample_copy: Path, capsys: pytest.CaptureFixture) -> None:
    text = (sample_copy / "dataset.yaml").read_text()
    (sample_copy / "dataset.yaml").write_text(
        text.replace("  - name: right\n", "  - name: right\n    flip: sideways\n")
    )
    line = one_error_line(["annotate", str(sample_copy)], capsys)
    assert "dataset.yaml: rig.cameras[1].flip must be 'horizontal'" in line


# ---------------------------------------------------------------- custom dictionaries


def test_markers_writes_a_custom_dictionary_that_opencv_reads(tmp_path: Path) -> None:
    path = tmp_path / "d.yml"
    args = ["markers", "--write-dictionary", str(path), "--count", "30", "--bits", "6"]
    assert main([*args, "--min-distance", "9"]) == 0
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    d = cv2.aruco.Dictionary()
    assert d.readDictionary(fs.root()) and d.bytesList.shape[0] == 30 and d.markerSize == 6
    assert min_distance(d) >= 9
    # OpenCV's detector reads markers drawn from it.
    img = np.full((200, 200), 255, np.uint8)
    img[50:150, 50:150] = cv2.aruco.generateImageMarker(d, 17, 100)
    _, ids, _ = cv2.aruco.ArucoDetector(dictionary(str(path))).detectMarkers(img)
    assert np.asarray(ids).reshape(-1).tolist() == [17]


def test_dataset_names_a_custom_dictionary_relative_to_itself(
    sample_copy: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # The sample's own dictionary, as a file written by OpenCV itself.
    fs = cv2.FileStorage(str(sample_copy / "ids.yml"), cv2.FILE_STORAGE_WRITE)
    cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_1000).writeDictionary(fs)
    fs.release()
    path = sample_copy / "dataset.yaml"
    text = path.read_text()
    path.write_text(text.replace("dictionary: DICT_4X4_1000", "dictionary: ids.yml"))
    ds = load_dataset(sample_copy)
    assert ds.dictionary == str((sample_copy / "ids.yml").resolve())
    assert main(["check", str(sample_copy)]) == 0
    # The file is part of what annotations depend on, and what Ray workers are sent.
    assert "ids.yml" in description_files(ds)
    before = description_digest(ds)
    with open(sample_copy / "ids.yml", "a") as f:
        f.write("\n")
    assert description_digest(load_dataset(sample_copy)) != before
    # A dictionary file that does not parse: one line naming it.
    (sample_copy / "ids.yml").write_text("nmarkers: [\n")
    line = one_error_line(["annotate", str(sample_copy)], capsys)
    assert "ids.yml" in line and "not an ArUco dictionary file" in line


# ---------------------------------------------------------------- bad input


def _subset(captures: Path, dst: Path, shots: int) -> Path:
    """A copy of the first ``shots`` shots, with board.yaml and the dictionary."""
    for cam in ("left", "right"):
        (dst / cam).mkdir(parents=True)
        for p in sorted((captures / cam).glob("*.png"))[:shots]:
            shutil.copy(p, dst / cam / p.name)
    for name in ("board.yaml", "dictionary.yml"):
        shutil.copy(captures / name, dst / name)
    return dst


def test_camera_mirrored_in_some_shots_only(
    awkward: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    caps = _subset(awkward, tmp_path / "caps", 8)
    for shot in ("003", "007"):
        p = caps / "right" / f"{shot}.png"
        cv2.imwrite(str(p), cv2.imread(str(p), cv2.IMREAD_UNCHANGED)[:, ::-1])
    line = one_error_line(["calibrate", str(caps)], capsys)
    assert f"{caps / 'right'}: camera right's images are mirrored in some shots only" in line
    assert "as it is (not mirrored) in 2 of 8 shots (003, 007)" in line


def test_camera_without_the_board(
    awkward: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    caps = _subset(awkward, tmp_path / "caps", 6)
    for p in (caps / "right").glob("*.png"):
        cv2.imwrite(str(p), np.full((820, 1024), 60, np.uint8))
    line = one_error_line(["calibrate", str(caps)], capsys)
    assert (
        f"{caps / 'right'}: the board was not found in any of the 6 images of camera right" in line
    )


def test_custom_dictionary_that_does_not_parse(
    awkward: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    caps = tmp_path / "caps"
    caps.mkdir()
    shutil.copy(awkward / "board.yaml", caps / "board.yaml")
    (caps / "dictionary.yml").write_text("nmarkers: 3\nmarkersize: 5\nmarker_0: '0101'\n")
    line = one_error_line(["calibrate", str(caps)], capsys)
    assert str(caps / "board.yaml") in line and "dictionary.yml" in line
    assert "marker_0 must be a string of 25 bits" in line
