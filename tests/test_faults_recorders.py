"""Issue 53's recorder input, each case on a file the test writes itself: nothing that fails
validation reaches the dataset (damaged depth, a depth topic taken for colour, a calibration
no camera has), no traceback (one depth frame for two colour frames, repeated stamps, odd
Record3D times, a scene id too long), and nothing silent (a whole depth stream that does not
pair, depth only as compressedDepth, an MKV without its calibration, stamps going back)."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from cli_calls import one_error_line, run_cli
from test_ingest_recorders import (
    K_KINECT_DEPTH,
    KDH,
    KDW,
    _colour_T_depth,
    _mkv,
    _r3d,
    _ros1_bag,
    depth_frame,
    ingest_new,
)

from annotator.dataset import load_dataset
from annotator.ingest.recording import damaged_rows

COLOUR = "/device_0/sensor_1/Color_0/image/data"
DEPTH = "/device_0/sensor_0/Depth_0/image/data"


def _ingest(ds: Path, src: Path, capture, *extra: str) -> tuple[int, str, str]:
    args = ["ingest", str(ds), str(src), "--scene", "s", "--rig-from-source", "--quiet"]
    return run_cli([*args, *extra], capture)


def test_a_whole_depth_stream_that_does_not_pair_is_refused_with_the_gap(
    tmp_path: Path, capsys
) -> None:
    # Depth 100 ms after each colour frame, frames 250 ms apart: none within 20 ms.
    bag = _ros1_bag(tmp_path / "late.bag", times=[(k * 0.25, k * 0.25 + 0.1) for k in range(6)])
    line = one_error_line(
        ["ingest", str(tmp_path / "ds"), str(bag), "--scene", "s", "--rig-from-source",
         "--tolerance-ms", "20", "--quiet"],
        capsys,
    )  # fmt: skip
    assert "100 ms apart" in line and "--tolerance-ms 110" in line and "--no-depth" in line
    assert not (tmp_path / "ds").exists()
    summary = ingest_new(tmp_path / "ds", bag, capsys, "--tolerance-ms", "110")
    assert summary["depth"] and summary["written"] == 6


def test_one_depth_frame_for_two_colour_frames_and_repeated_stamps(tmp_path: Path, capsys):
    # Colour frames 0 and 1 both nearest depth frame 0; colour frame 3 repeats 2's stamp.
    times = [(0, 0), (0.005, 0.2), (0.1, 0.1), (0.1, 0.3), (0.4, 0.4), (0.5, 0.5)]
    bag = _ros1_bag(tmp_path / "a.bag", times=times)
    summary = ingest_new(tmp_path / "ds", bag, capsys)
    assert summary["written"] == 5 and summary["depth"]
    assert summary["dropped"] == [
        {"frame": 3, "why": "the same time as frame 2 (a repeated frame)"}
    ]
    ds = load_dataset(tmp_path / "ds")
    frames = ds.scene("s").frames()
    assert frames[0].read_depth(ds.rig) is not None and frames[1].read_depth(ds.rig) is not None


def test_stamps_that_go_back_are_said(tmp_path: Path, capsys) -> None:
    times = [(0.1, 0.1), (0.0, 0.0), (0.2, 0.2), (0.4, 0.4), (0.3, 0.3), (0.5, 0.5)]
    summary = ingest_new(tmp_path / "ds", _ros1_bag(tmp_path / "b.bag", times=times), capsys)
    assert summary["written"] == 6
    assert any("times go back at frame 1 (-0.100 s), frame 4" in n for n in summary["notes"])


def test_depth_as_compressed_depth_only_is_read(tmp_path: Path, capsys) -> None:
    bag = _ros1_bag(tmp_path / "c.bag", compressed_depth=True)
    summary = ingest_new(tmp_path / "ds", bag, capsys)
    assert summary["depth"] and summary["streams"]["depth"] == f"{DEPTH}/compressedDepth"
    ds = load_dataset(tmp_path / "ds")
    raw = ingest_new(tmp_path / "raw", _ros1_bag(tmp_path / "r.bag"), capsys, scene="s")
    assert raw["depth"]
    plain = load_dataset(tmp_path / "raw")
    a = ds.scene("s").frames()[2].read_depth(ds.rig)
    b = plain.scene("s").frames()[2].read_depth(plain.rig)
    assert a is not None and b is not None
    assert np.array_equal(np.isnan(a), np.isnan(b)) and np.nanmax(np.abs(a - b)) < 1e-6


def test_a_depth_topic_named_as_colour_is_refused(tmp_path: Path, capsys) -> None:
    bag = _ros1_bag(tmp_path / "d.bag")
    line = one_error_line(
        ["ingest", str(tmp_path / "ds"), str(bag), "--scene", "s", "--rig-from-source",
         "--color-topic", DEPTH, "--quiet"],
        capsys,
    )  # fmt: skip
    assert "holds depth images (mono16), not colour" in line and COLOUR in line
    assert not (tmp_path / "ds").exists()


def _damaged_depth_mkv(tmp_path: Path) -> Path:
    """An Azure Kinect recording whose middle has random bytes written over a depth frame
    (the demuxer still hands it over whole)."""
    good = _mkv(tmp_path / "good.mkv", n=8)
    data = bytearray(good.read_bytes())
    rng = np.random.default_rng(0)
    at, length = int(len(data) * rng.uniform(0.2, 0.8)), int(len(data) * rng.uniform(0.01, 0.05))
    data[at : at + length] = rng.integers(0, 256, length, dtype=np.uint8).tobytes()
    bad = tmp_path / "bad.mkv"
    bad.write_bytes(bytes(data))
    return bad


def test_a_kinect_recording_with_noise_for_depth_never_writes_it(tmp_path: Path, capfd) -> None:
    summary = ingest_new(tmp_path / "ds", _damaged_depth_mkv(tmp_path), capfd)
    assert any("hold noise (the file is damaged there)" in d["why"] for d in summary["dropped"])
    ds = load_dataset(tmp_path / "ds")
    plane = depth_frame(_colour_T_depth(2.0, (-32.0, -2.0, 4.0)), K_KINECT_DEPTH, KDW, KDH)
    lo, hi = plane[plane > 0].min(), plane[plane > 0].max()
    for frame in ds.scene("s").frames():  # every depth written is the plane's
        depth = frame.read_depth(ds.rig)
        assert depth is not None
        ok = np.isfinite(depth)
        assert ok.mean() > 0.5 and lo - 5 <= depth[ok].min() and depth[ok].max() <= hi + 5


def test_damaged_rows_are_found_and_edges_are_not() -> None:
    depth = np.full((60, 80), 800.0)
    depth[:, 40:] = 1200.0  # a step: one jump per row
    depth[20:25, 30:34] = np.nan
    assert damaged_rows(depth) is None
    depth[30:33] = np.random.default_rng(1).uniform(0, 65535, (3, 80))
    assert damaged_rows(depth) == (30, 32)


def test_an_mkv_with_depth_but_no_calibration_says_so(tmp_path: Path, capfd) -> None:
    data = bytearray(_mkv(tmp_path / "k.mkv").read_bytes())
    at = data.find(b"calibration.json")
    data[at : at + 1] = b"x"  # the attachment renamed: an MKV without its calibration
    bare = tmp_path / "bare.mkv"
    bare.write_bytes(bytes(data))
    ds = tmp_path / "ds"
    line = one_error_line(["ingest", str(ds), str(bare), "--scene", "s", "--quiet"], capfd)
    assert "has a DEPTH track but no calibration.json attachment" in line and "--no-depth" in line


@pytest.mark.parametrize(
    ("change", "says"),
    [
        ({"K": [0.0] * 9}, "focal lengths fx 0, fy 0"),
        ({"K": [float("nan")] * 9}, "intrinsics that are not finite numbers"),
        ({"w": -160}, "a size of -160x120"),
        ({"frameTimestamps": {"a": 1}}, "frameTimestamps is a dict, not a list of times"),
        ({"frameTimestamps": ["x", 1, 2, 3]}, "frameTimestamps[0] is 'x'"),
    ],
)
def test_a_record3d_file_no_camera_has_never_reaches_the_dataset(
    tmp_path: Path, capsys, change, says
) -> None:
    src = _r3d(tmp_path / "scan.r3d")
    with zipfile.ZipFile(src) as z:
        items = {n: z.read(n) for n in z.namelist()}
    meta = json.loads(items["metadata"])
    meta.update(change)
    items["metadata"] = json.dumps(meta).encode()
    with zipfile.ZipFile(src, "w") as z:
        for name, blob in items.items():
            z.writestr(name, blob)
    ds = tmp_path / "ds"
    args = ["ingest", str(ds), str(src), "--scene", "s", "--rig-from-source", "--quiet"]
    assert says in one_error_line(args, capsys)
    assert not ds.exists()  # no dataset.yaml, no folder


def test_a_scene_id_too_long_for_the_file_system(tmp_path: Path, capsys) -> None:
    bag = _ros1_bag(tmp_path / "e.bag")
    args = ["ingest", str(tmp_path / "ds"), str(bag), "--scene", "s" * 300, "--rig-from-source"]
    assert "--scene is 300 bytes long" in one_error_line(args, capsys)


def test_the_compressed_depth_decoder_reads_32_bit_depth() -> None:
    from annotator.ingest.readers.ros_image import image_of

    class Msg:
        format = "32FC1; compressedDepth png"

    a, b = 2.0, 1.0  # depth = a / (v - b) metres
    v = np.array([[0, 3], [5, 9]], np.uint16)
    header = np.concatenate(
        [np.zeros(4, np.uint8), np.frombuffer(np.array([a, b], "<f4").tobytes(), np.uint8)]
    )
    msg = Msg()
    msg.data = np.concatenate([header, cv2.imencode(".png", v)[1].reshape(-1)])  # type: ignore[attr-defined]
    img, problem = image_of(msg, "sensor_msgs/msg/CompressedImage")
    assert problem is None and img is not None
    assert np.isnan(img[0, 0]) and img[0, 1] == pytest.approx(1.0) and img[1, 1] == 0.25
