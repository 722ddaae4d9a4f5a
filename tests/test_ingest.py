"""`annotator ingest`: a video or a folder of RealSense/ROS-style images into a moving rig's
dataset: frames paired by name or by time, every N-th, blurred ones dropped, sizes checked,
nothing written over what ingest did not write, one line for every bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from cli_calls import one_error_line, run_cli

from annotator.dataset import load_dataset
from annotator.dataset.model import DepthSpec, Rig
from annotator.dataset.write import write_dataset_yaml
from annotator.geometry.camera import Camera
from annotator.ingest.readers.folder import open_source, read_name
from annotator.ingest.scene import IngestSettings, ingest_recording
from annotator.ingest.selection import running_median, select, sharpness

W, H = 160, 120
BLURRED = {4, 7}  # frames made blurry with cv2.GaussianBlur


def _dataset(root: Path, sample: Path, *, cameras: tuple[str, ...] = ("cam",)) -> Path:
    """A moving rig's dataset of one camera (or several) with depth on the first one."""
    shutil.copytree(sample / "objects", root / "objects")
    K = np.array([[150.0, 0, (W - 1) / 2], [0, 150.0, (H - 1) / 2], [0, 0, 1]])
    cams = tuple(Camera(n, W, H, K) for n in cameras)
    rig = Rig(cameras=cams, depth=DepthSpec(cameras[0], 0.1), moving=True)
    objects = sorted(p.name for p in (sample / "objects").iterdir())
    write_dataset_yaml(root, name="moving", dictionary="DICT_4X4_1000", rig=rig, objects=objects)
    return root


def _picture(k: int) -> np.ndarray:
    """A textured colour frame (random blocks that shift with k), blurred for BLURRED."""
    blocks = np.random.default_rng(0).integers(30, 225, (H // 4, W // 4 + 8, 3), np.uint8)
    texture = np.repeat(np.repeat(blocks, 4, axis=0), 4, axis=1)
    img = np.ascontiguousarray(texture[:, k : k + W])
    noise = np.random.default_rng(k).normal(0, 2, img.shape)
    img = np.clip(img + noise, 0, 255).astype(np.uint8)
    if k in BLURRED:
        img = cv2.GaussianBlur(img, (0, 0), 3.0)
    return img


def _depth(k: int) -> np.ndarray:
    d = np.full((H, W), 500 + 10 * k, np.uint16)  # mm
    d[:5, :5] = 0  # no measurement
    return d


def _realsense_folder(root: Path, n: int = 10) -> Path:
    """realsense-viewer snapshot names: colour and depth a few ms apart, ms since the epoch."""
    root.mkdir()
    t0 = 1_700_000_000_000.0
    for k in range(n):
        tc = t0 + k * 33.333
        td = tc + (4.2 if k % 2 else -3.1)
        cv2.imwrite(str(root / f"_Color_{tc:.3f}.png"), _picture(k))
        cv2.imwrite(str(root / f"_Depth_{td:.3f}.png"), _depth(k))
        (root / f"_Color_{tc:.3f}_metadata.csv").write_text("x\n")
    return root


def _video(path: Path, n: int = 12) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (W, H))
    assert writer.isOpened()
    for k in range(n):
        writer.write(_picture(k))
    writer.release()
    return path


def test_names_of_capture_tools_are_read() -> None:
    assert read_name(Path("cam_Depth_1700000000000.500.png"))[1:] == (
        "depth",
        "1700000000000.500",
        1700000000.0005,
    )
    assert read_name(Path("_Color_17.png"))[1:] == ("colour", "17", None)  # rs-convert
    assert read_name(Path("frame0003.jpg")) == ("frame", "colour", "0003", None)
    assert read_name(Path("left0003.png"))[0] == "left"
    assert read_name(Path("1650000000.250000000.png"))[3] == pytest.approx(1650000000.25)
    assert read_name(Path("cam_Infrared_12.png"))[1] == "other"


def test_a_realsense_folder_is_paired_by_time_and_the_blurred_frames_dropped(
    tmp_path: Path, sample: Path, capsys
) -> None:
    ds = _dataset(tmp_path / "ds", sample)
    src = _realsense_folder(tmp_path / "rs")
    code, out, err = run_cli(["ingest", str(ds), str(src), "--scene", "s1", "--json"], capsys)
    assert code == 0, err
    summary = json.loads(out)
    assert summary["written"] == 8 and summary["depth"] and summary["source_frames"] == 10
    doc = json.loads((ds / "scenes" / "s1" / "frames.json").read_text())
    labels = [e["source"] for e in doc["frames"].values()]
    dropped = sorted(doc["blurred"])
    assert dropped == sorted(summary["blurred"])
    assert dropped == sorted(lbl for k, lbl in enumerate(_names(src)) if k in BLURRED)
    assert list(doc["frames"]) == [f"{k:06d}" for k in range(8)]
    for entry in doc["frames"].values():  # each colour with the depth taken 3-4 ms from it
        assert entry["depth_source"].startswith("_Depth_") and entry["sharpness"] > 0
    assert doc["frames"]["000000"]["time_s"] == 0.0
    assert doc["frames"]["000001"]["time_s"] == pytest.approx(0.0333, abs=1e-3)
    assert labels[0] == _names(src)[0]
    # The dataset reads the frames; depth at the rig's scale (0.1 mm), holes kept.
    loaded = load_dataset(ds)
    frames = loaded.scene("s1").frames()
    assert len(frames) == 8
    img = frames[1].read_image(loaded.rig.cameras[0])
    assert img.shape == (H, W, 3) and np.array_equal(img, _picture(1))
    depth = frames[1].read_depth(loaded.rig)
    assert depth is not None and np.isnan(depth[0, 0])
    assert np.nanmax(np.abs(depth - 510.0)) < 1e-3


def _names(src: Path) -> list[str]:
    return sorted(p.name for p in src.glob("_Color_*.png"))


def test_a_video_every_second_frame_and_the_summary_line(
    tmp_path: Path, sample: Path, capsys
) -> None:
    ds = _dataset(tmp_path / "ds", sample)
    video = _video(tmp_path / "take.avi")
    code, out, err = run_cli(
        ["ingest", str(ds), str(video), "--scene", "v", "--every", "2", "--quiet"], capsys
    )
    assert code == 0, err
    assert out.startswith("ingest: 5 frames of") and "1 dropped as blurred" in out
    doc = json.loads((ds / "scenes" / "v" / "frames.json").read_text())
    # Candidates 0, 2, ..., 10: frame 4 is blurred (7 is not a candidate).
    assert doc["blurred"] == [4] and doc["every"] == 2
    assert [e["source"] for e in doc["frames"].values()] == [0, 2, 6, 8, 10]
    times = [e["time_s"] for e in doc["frames"].values()]
    assert times == sorted(times) and times[1] == pytest.approx(2 / 30, abs=1e-3)
    assert not list((ds / "scenes" / "v" / "frames" / "000000").glob("depth.png"))


def test_blur_dropping_picks_the_blurred_frames_of_a_video(tmp_path: Path, sample: Path) -> None:
    ds = _dataset(tmp_path / "ds", sample)
    video = _video(tmp_path / "take.avi")
    summary = ingest_recording(ds, video, "v")
    assert sorted(summary.blurred) == sorted(BLURRED)
    assert summary.written == 10
    again = ingest_recording(ds, video, "w", IngestSettings(blur_threshold=0.0))
    assert again.written == 12 and again.blurred == []
    # The measure itself: blurring lowers it a lot.
    assert sharpness(_picture(4)) < 0.3 * sharpness(_picture(2))


def test_pairing_by_name_and_rejecting_a_colour_without_depth(
    tmp_path: Path, sample: Path, capsys
) -> None:
    src = tmp_path / "bag"
    (src / "color").mkdir(parents=True)
    (src / "depth").mkdir()
    for k in range(4):
        name = f"{1650000000 + k}.{k * 1000:09d}.png"
        cv2.imwrite(str(src / "color" / name), _picture(k))
        cv2.imwrite(str(src / "depth" / name), _depth(k))
    source = open_source(src)
    assert [f.depth.name for f in source.frames] == [f.colour.name for f in source.frames]
    ds = _dataset(tmp_path / "ds", sample)
    (src / "depth" / f"{1650000002}.{2000:09d}.png").unlink()
    line = one_error_line(["ingest", str(ds), str(src), "--scene", "b"], capsys)
    assert "has no depth partner" in line and "1650000002.000002000.png" in line
    code, _, err = run_cli(["ingest", str(ds), str(src), "--scene", "b", "--no-depth"], capsys)
    assert code == 0, err


def test_bad_inputs_are_one_line_and_write_nothing(tmp_path: Path, sample: Path, capsys) -> None:
    ds = _dataset(tmp_path / "ds", sample)
    empty = tmp_path / "empty"
    empty.mkdir()
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"not a video at all")
    big = tmp_path / "big"
    big.mkdir()
    cv2.imwrite(str(big / "frame0000.png"), np.zeros((H + 2, W, 3), np.uint8))
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    cv2.imwrite(str(mixed / "frame0000.png"), _picture(0))
    cv2.imwrite(str(mixed / "frame0001.png"), np.zeros((H // 2, W // 2, 3), np.uint8))
    fixed = _dataset(tmp_path / "fixed", sample)
    text = (fixed / "dataset.yaml").read_text().replace("  moving: true\n", "")
    (fixed / "dataset.yaml").write_text(text)
    cases = [
        ([str(ds), str(empty)], "no colour images found"),
        ([str(ds), str(broken)], "not a readable video"),
        ([str(ds), str(tmp_path / "nothing")], "no such video file or image folder"),
        ([str(ds), str(big)], f"image is {W}x{H + 2} but camera cam"),
        ([str(ds), str(mixed)], "frames of different sizes"),
        ([str(fixed), str(big)], "the rig is not a moving one"),
        ([str(ds), str(big), "--camera", "nope"], "--camera 'nope' is not a camera"),
    ]
    for args, message in cases:
        line = one_error_line(["ingest", *args, "--scene", "x"], capsys)
        assert message in line, line
    assert "frame0000.png" in one_error_line(["ingest", str(ds), str(big), "--scene", "x"], capsys)
    assert "frame0001.png" in one_error_line(
        ["ingest", str(ds), str(mixed), "--scene", "x"], capsys
    )
    assert not (ds / "scenes").exists() or not any((ds / "scenes").iterdir())
    two = _dataset(tmp_path / "two", sample, cameras=("left", "right"))
    line = one_error_line(["ingest", str(two), str(mixed), "--scene", "x"], capsys)
    assert "several cameras (left, right)" in line


def test_an_existing_scene_is_replaced_only_when_ingest_wrote_it(
    tmp_path: Path, sample: Path, capsys
) -> None:
    ds = _dataset(tmp_path / "ds", sample)
    video = _video(tmp_path / "take.avi", n=4)
    args = ["ingest", str(ds), str(video), "--scene", "s", "--quiet"]
    assert run_cli(args, capsys)[0] == 0
    assert "use --overwrite" in one_error_line(args, capsys)
    assert run_cli([*args, "--overwrite", "--every", "2"], capsys)[0] == 0
    assert len(load_dataset(ds).scene("s").frames()) == 2
    (ds / "scenes" / "s" / "review.json").write_text("{}")
    assert "reviewer's decisions" in one_error_line([*args, "--overwrite"], capsys)
    mine = ds / "scenes" / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    line = one_error_line(["ingest", str(ds), str(video), "--scene", "mine", "--overwrite"], capsys)
    assert "replaces only a scene that `annotator ingest` wrote" in line
    assert (mine / "notes.txt").read_text() == "keep"
    assert not [p for p in (ds / "scenes").iterdir() if p.name.startswith(".")]
    inside = ds / "scenes" / "s" / "frames"
    (ds / "scenes" / "s" / "review.json").unlink()
    line = one_error_line(["ingest", str(ds), str(inside), "--scene", "s", "--overwrite"], capsys)
    assert "lies in the scene it would be written to" in line


def test_a_folder_of_two_streams_needs_one_chosen(tmp_path: Path, sample: Path, capsys) -> None:
    src = tmp_path / "stereo"
    src.mkdir()
    for k in range(3):
        cv2.imwrite(str(src / f"left{k:04d}.png"), _picture(k))
        cv2.imwrite(str(src / f"right{k:04d}.png"), _picture(k + 8))
    ds = _dataset(tmp_path / "ds", sample)
    line = one_error_line(["ingest", str(ds), str(src), "--scene", "s"], capsys)
    assert "several streams ('left', 'right')" in line and "--stream" in line
    args = ["ingest", str(ds), str(src), "--scene", "s", "--stream", "right", "--json"]
    code, out, err = run_cli(args, capsys)
    assert code == 0, err
    doc = json.loads((ds / "scenes" / "s" / "frames.json").read_text())
    assert [e["source"] for e in doc["frames"].values()] == [f"right{k:04d}.png" for k in range(3)]


def test_selection_helpers() -> None:
    assert running_median([5.0], window=15).tolist() == [5.0]
    s = select([0, 5, 10], [1.0, 1.0, 0.1], threshold=0.5)
    assert s.kept == (0, 5) and s.blurred == (10,) and s.of(10) == pytest.approx(0.1)


def test_help_lists_the_options(capsys) -> None:
    with pytest.raises(SystemExit) as stop:
        run_cli(["ingest", "--help"], capsys)
    assert stop.value.code == 0
    out = capsys.readouterr().out
    for option in ("--scene", "--every", "--blur-threshold", "--depth-scale", "--camera"):
        assert option in out
