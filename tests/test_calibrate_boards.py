"""Calibration from captures as users make them: colour-inverted boards, a mirrored camera, a
camera behind the board and a board turned round (seen through the paper), a custom
dictionary, a plain chessboard, videos, a board that covers only the image centre (held-out
error, model choice, extrapolation warning), a rig that does not hold together, and their
bad inputs.

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
from annotator.runner.files import description_files
from annotator.synthesis.board import CaptureSettings, write_captures
from annotator.synthesis.board_video import write_videos

pytestmark = pytest.mark.slow  # calibration captures rendered and solved

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
    assert "camera right: a mirrored camera (the board reads only in the flipped image" in out
    assert "its board poses agree with camera left's" in out
    reading = doc["cameras"][1]["reading"]
    assert reading["mirrored"] and not reading["behind_shots"]
    # Decided by the geometry: the other reading's board poses drift by far more.
    chosen, other = reading["spread_mm"]
    assert chosen < 5 and other > 10 * chosen
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
    """Two images stored unmirrored among a mirrored camera's: read the one way they are a
    board seen from behind, whose pose does not agree with the other camera's; they are
    left out, saying why, and the rest calibrates."""
    caps = _subset(awkward, tmp_path / "caps", 9)
    for shot in ("003", "007"):
        p = caps / "right" / f"{shot}.png"
        cv2.imwrite(str(p), cv2.imread(str(p), cv2.IMREAD_UNCHANGED)[:, ::-1])
    out, doc, rig = _calibrate(caps, tmp_path, capsys, "--dist-coeffs", "4", "--folds", "3")
    assert [c.get("flip") for c in rig["cameras"]] == [None, "horizontal"]
    left_out = {(r["shot"], r["camera"]): r["reason"] for r in doc["rejected"]}
    assert set(left_out) == {("003", "right"), ("007", "right")}, left_out
    assert all("is this image mirrored?" in why for why in left_out.values())
    assert "rejected: shot 003, camera right: its board pose is" in out
    errors = _rig_errors(rig, _truth(awkward))
    assert all(errors[k] < 2 * tol for k, tol in TOLERANCE.items()), errors


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


# ---------------------------------------------------------------- a board seen from behind


@pytest.fixture(scope="module")
def behind(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The right camera placed behind a thin back-lit board (it sees the print through the
    paper, mirrored, with less contrast), and the board turned round in three shots: then the
    left camera sees its back and the right camera its front."""
    out = tmp_path_factory.mktemp("behind") / "captures"
    config = CaptureSettings(
        shots=SHOTS, noise=12.0, blur=1.0, size=(1024, 820), behind=("right",), turned=(2, 6, 10)
    )
    write_captures(config, out, workers=2)
    return out


def test_camera_behind_the_board_and_a_board_turned_round(
    behind: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # As recorded: the right camera's board reads only flipped except in the turned shots,
    # the left camera's only flipped in them.
    img = cv2.imread(str(behind / "right" / "000.png"), cv2.IMREAD_GRAYSCALE)
    aruco = cv2.aruco.ArucoDetector(dictionary("DICT_4X4_50"))
    plain = aruco.detectMarkers(img)[1]
    assert (
        (0 if plain is None else len(plain)) < 3 <= len(aruco.detectMarkers(img[:, ::-1].copy())[1])
    )
    out, doc, rig = _calibrate(behind, tmp_path, capsys, "--folds", "3")
    assert (
        "camera right: sees the board from behind, through the paper (or a board printed mirrored from the front), in 11 of its 14"
        in out
    )
    assert (
        "camera left: sees the board from behind, through the paper (or a board printed mirrored from the front), in 3 of its 14"
        in out
    )
    # Nobody is mirrored: no flip anywhere.
    assert [c.get("flip") for c in rig["cameras"]] == [None, None]
    readings = [c["reading"] for c in doc["cameras"]]
    assert readings[0]["behind_shots"] == ["002", "006", "010"]
    assert readings[1]["behind_shots"] == [f"{k:03d}" for k in range(SHOTS) if k not in (2, 6, 10)]
    chosen, other = readings[1]["spread_mm"]
    assert chosen < 5 and other > 10 * chosen
    assert all(s["used"] for s in doc["shots"]) and not doc["refused"]
    # As accurate as the through-paper corners allow: the intrinsics within the ordinary
    # tolerances, the pose of a camera 1.3 m away within three of its reported sigmas.
    truth = _truth(behind)
    errors = _rig_errors(rig, truth)
    assert errors["focal_pct"] < 2 * TOLERANCE["focal_pct"], errors
    assert errors["principal_px"] < TOLERANCE["principal_px"], errors
    std = doc["cameras"][1]["std"]
    assert errors["position_mm"] < 3 * std["position_mm"], (errors, std)
    assert errors["rotation_deg"] < 3 * std["rotation_deg"], (errors, std)
    T = np.reshape(rig["cameras"][1]["rig_T_cam"], (4, 4))
    assert T[2, 2] < -0.9  # it looks back at the rig
    assert doc["held_out"]["rms_px"] < 1.0


def test_a_rig_that_diverges_is_never_written(
    tmp_path_factory: pytest.TempPathFactory, capsys: pytest.CaptureFixture
) -> None:
    """A plain chessboard looks the same mirrored, so a camera mirrored in some shots is only
    seen by the geometry. A few such views disagree with their shots and are left out; in half
    the shots they are too many to leave out (the camera would keep too few): the joint solve
    runs off (focal lengths of thousands of px, a held-out error of hundreds); it is refused,
    naming the camera and the check, the report is written, dataset.yaml is not."""
    root = tmp_path_factory.mktemp("diverge")
    captures = _synth(root / "captures", "--scenes", "10", "--board-kind", "chessboard")
    for shot in ("001", "002", "004", "007", "009"):
        p = captures / "right" / f"{shot}.png"
        cv2.imwrite(str(p), cv2.imread(str(p), cv2.IMREAD_UNCHANGED)[:, ::-1])
    ds, report = root / "ds", root / "report"
    args = ["calibrate", str(captures), "--dataset", str(ds), "--report", str(report)]
    code, out, err = run_cli([*args, "--yes", "--dist-coeffs", "4", "--folds", "2"], capsys)
    assert code == 1
    assert not ds.exists() and not (report / "rig.yaml").exists()
    doc = json.loads((report / "report.json").read_text())
    checks = {p["check"] for p in doc["refused"]}
    assert {"focal", "rms", "held_out"} <= checks, doc["refused"]
    assert f"error: {ds / 'dataset.yaml'}: not written: camera " in err
    assert "focal length fx = " in err and "against 11" in err  # ~1110 px alone
    assert "error: try --cameras " in err
    assert "Traceback" not in err and "the rig does not hold together" in out
    # The camera to try without is the one whose images were flipped.
    assert "error: try --cameras left to calibrate without camera right" in err
    # Without a dataset, and as JSON: refused all the same.
    code, out, err = run_cli([*args[:2], "--report", str(report), "--json", "--folds", "2"], capsys)
    assert code == 1 and "Traceback" not in err
    doc = json.loads(out)
    assert doc["written"] is False and doc["refused"] and doc["advice"].startswith("try --cameras")


def test_report_inside_a_camera_folder_is_refused(
    awkward: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    caps = _subset(awkward, tmp_path / "caps", 6)
    for report, words in (
        (caps / "right", "--report is the camera folder right of the captures"),
        (caps / "right" / "rep", "--report lies inside the camera folder right of the captures"),
        (caps, "--report is the captures folder itself"),
        (caps / "board.yaml", "--report exists and is not a folder"),
    ):
        line = one_error_line(["calibrate", str(caps), "--report", str(report)], capsys)
        assert line.startswith(f"annotator: error: {report}: {words}"), line
    assert sorted(p.name for p in (caps / "right").iterdir()) == [f"{k:03d}.png" for k in range(6)]


# ---------------------------------------------------------------- a real rig's session (issue 48)

#: Four webcams that are not synchronised, one behind a board printed colour-inverted and
#: mirrored: the cameras in front read it only flipped, the one behind (through the paper,
#: dimmer and blurred) as it is; each webcam takes its image 33 ms after the one before, give
#: or take 10 ms, while the hand-held board is mostly still, now and then moving.
WEBCAMS = CaptureSettings(
    shots=16,
    noise=14.0,
    blur=1.3,
    size=(1280, 720),
    extra_cameras=2,
    behind=("cam3",),
    inverted=True,
    printed_mirrored=True,
    paper_blur=1.5,
    timing_ms=10.0,
    rolling_ms=33.0,
    speed=(40.0, 8.0),
)


@pytest.fixture(scope="module")
def webcams(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("webcams") / "captures"
    write_captures(WEBCAMS, out, workers=2)
    return out


def test_four_webcams_one_behind_a_mirrored_print_join_as_one_rig(
    webcams: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """All four cameras join, none declared mirrored (the board is printed mirrored: the
    three in front see its back in the board's own frame, the fourth its front), and the
    views taken at another moment than their shot's others are left out, named."""
    out, doc, rig = _calibrate(webcams, tmp_path, capsys)
    assert [c.get("flip") for c in rig["cameras"]] == [None] * 4
    assert not doc["refused"]
    # The cameras in folder order: cam2 (the rig frame), cam3 (behind), left, right.
    names = [c["name"] for c in doc["cameras"]]
    behind = {c["name"]: len(c["reading"]["behind_shots"]) for c in doc["cameras"]}
    assert behind == {"cam2": 16, "cam3": 0, "left": 16, "right": 16}
    assert all(c["shots"] >= 6 for c in doc["cameras"])
    # The rig, in its own frame, against the truth moved into it.
    true = {
        c["name"]: np.reshape(c["rig_T_cam"], (4, 4)) for c in _truth(webcams)["rig"]["cameras"]
    }
    for cam, c in zip(rig["cameras"], doc["cameras"]):
        T0 = invert(true[names[0]]) @ true[cam["name"]]
        T = np.reshape(cam["rig_T_cam"], (4, 4))
        off = float(np.linalg.norm(T[:3, 3] - T0[:3, 3]))
        assert off <= max(1.0, 3 * c["std"]["position_mm"]), (cam["name"], off, c["std"])
    # The views left out disagree with their shots' others: the board moved between the
    # cameras' images; each is named with its shot and camera.
    moved = [r for r in doc["rejected"] if "another moment" in r["reason"]]
    assert moved and f"rejected: shot {moved[0]['shot']}, camera {moved[0]['camera']}: " in out
    assert doc["held_out"]["rms_px"] <= 1.3
