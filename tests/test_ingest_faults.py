"""`annotator ingest` against damaged input and misuse (issue 44's probe): damaged and cut
videos, FFmpeg's own lines, a depth unit that turns depth to nothing, a rig of two cameras,
and a killed ingest's temporary folder."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
from cli_calls import one_error_line, run_cli
from test_ingest import H, W, _dataset, _picture, _realsense_folder

from annotator.io.atomic import TEMPORARY_MARK, temporary_folder

N = 20


def _clean_video(path: Path) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (W, H))
    for k in range(N):
        writer.write(_picture(k))
    writer.release()
    return path


def _decoded(video: Path) -> list[np.ndarray]:
    """The undamaged video's frames as OpenCV decodes them (what a good frame looks like)."""
    cap = cv2.VideoCapture(str(video))
    frames = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        frames.append(img)
    cap.release()
    assert len(frames) == N
    return frames


def _frames_written(scene: Path) -> list[tuple[int, np.ndarray]]:
    doc = json.loads((scene / "frames.json").read_text())
    return [
        (int(e["source"]), cv2.imread(str(scene / "frames" / name / "cam.png")))
        for name, e in doc["frames"].items()
    ]


def test_a_video_with_a_tenth_of_its_bytes_overwritten(tmp_path: Path, sample: Path, capfd) -> None:
    video = _clean_video(tmp_path / "take.avi")
    data = bytearray(video.read_bytes())
    n = len(data)
    start = n // 2
    data[start : start + n // 10] = np.random.default_rng(3).bytes(n // 10)
    bad = tmp_path / "bad.avi"
    bad.write_bytes(bytes(data))
    ds = _dataset(tmp_path / "ds", sample)
    args = ["ingest", str(ds), str(bad), "--scene", "v", "--blur-threshold", "0", "--json"]
    code, out, err = run_cli([*args, "--quiet"], capfd)
    assert code == 0, err
    assert err == ""  # FFmpeg's lines stay hidden, at the descriptor too
    summary = json.loads(out)
    lost = N - summary["written"]
    assert lost >= 1
    # Every frame lost is said: dropped by name, or the file holding fewer than announced.
    assert summary["dropped"] or summary["ended_early"]
    if summary["ended_early"]:
        assert f"of the {N} frames its header announces" in summary["ended_early"]
    # No frame written is a partly decoded one: each is one of the video's frames, in
    # order (after frames lost with their container chunks, the decoder numbers the next
    # ones on from the last it saw, which the summary warns of).
    good = _decoded(video)
    seen = []
    for _, img in _frames_written(ds / "scenes" / "v"):
        errors = [np.abs(img.astype(int) - g.astype(int)).max() for g in good]
        assert min(errors) <= 2
        seen.append(int(np.argmin(errors)))
    assert seen == sorted(seen) and len(set(seen)) == len(seen)


def test_a_cut_video_says_it_ends_early_and_drops_its_last_half_frame(
    tmp_path: Path, sample: Path, capfd
) -> None:
    video = _clean_video(tmp_path / "take.avi")
    data = video.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    ds = _dataset(tmp_path / "ds", sample)
    args = ["ingest", str(ds), str(cut), "--scene", "v", "--blur-threshold", "0"]
    code, out, err = run_cli([*args, "--quiet"], capfd)
    assert code == 0, err
    assert err == ""
    assert "ends early" in out and f"of the {N} frames" in out
    good = _decoded(video)
    for index, img in _frames_written(ds / "scenes" / "v"):
        assert np.abs(img.astype(int) - good[index].astype(int)).max() <= 2, index
    doc = json.loads((ds / "scenes" / "v" / "frames.json").read_text())
    assert doc["ended_early"] and len(doc["frames"]) < N


def test_a_depth_scale_that_turns_depth_to_nothing_is_refused(
    tmp_path: Path, sample: Path, capsys
) -> None:
    ds = _dataset(tmp_path / "ds", sample)
    src = _realsense_folder(tmp_path / "rs")
    line = one_error_line(
        ["ingest", str(ds), str(src), "--scene", "s", "--depth-scale", "1000"], capsys
    )
    assert "--depth-scale 1000" in line and "values seen, 500..500" in line and "_Depth_" in line
    line = one_error_line(
        ["ingest", str(ds), str(src), "--scene", "s", "--depth-scale", "0.00001"], capsys
    )
    assert "--depth-scale 1e-05" in line
    assert not (ds / "scenes").exists() or not any((ds / "scenes").iterdir())


def test_a_rig_of_two_cameras_is_refused_with_or_without_camera(
    tmp_path: Path, sample: Path, capsys
) -> None:
    two = _dataset(tmp_path / "two", sample, cameras=("left", "right"))
    video = _clean_video(tmp_path / "take.avi")
    for extra in ([], ["--camera", "left"]):
        line = one_error_line(["ingest", str(two), str(video), "--scene", "s", *extra], capsys)
        assert "several cameras (left, right)" in line and "needs an image of each" in line
    assert not (two / "scenes").exists() or not any((two / "scenes").iterdir())


def test_a_killed_ingests_temporary_folder_is_swept(tmp_path: Path, sample: Path, capsys) -> None:
    ds = _dataset(tmp_path / "ds", sample)
    scenes = ds / "scenes"
    scenes.mkdir()
    # What a killed ingest of scene "a" leaves: a marked folder nobody holds.
    dead, lock = temporary_folder(scenes, ".a.")
    (dead / "frames").mkdir()
    (dead / "frames" / "big.bin").write_bytes(b"x" * 1000)
    assert lock is not None
    os.close(lock)
    # One that a running ingest of scene "b" is building: held.
    live, live_lock = temporary_folder(scenes, ".b.")
    # A hidden folder of the user's, not marked: never touched.
    mine = scenes / ".notes.12345678"
    mine.mkdir()
    try:
        video = _clean_video(tmp_path / "take.avi")
        code, _, err = run_cli(["ingest", str(ds), str(video), "--scene", "c", "--quiet"], capsys)
        assert code == 0, err
        assert not dead.exists()
        assert live.exists() and (live / TEMPORARY_MARK).exists()
        assert mine.exists()
    finally:
        if live_lock is not None:
            os.close(live_lock)


def test_an_h264_video_with_b_frames_keeps_every_frame_in_order(
    tmp_path: Path, sample: Path, capfd
) -> None:
    """Decoded in presentation order (B-frames arrive out of it), each frame named by its
    index: as OpenCV decodes the same file."""
    import av

    video = tmp_path / "phone.mp4"
    out = av.open(str(video), "w")
    stream = out.add_stream("libx264", rate=30)
    stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
    stream.options = {"bf": "2", "g": "6"}
    for k in range(12):
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(_picture(k)[..., ::-1]), "rgb24")
        frame.pts = k
        out.mux(stream.encode(frame))
    out.mux(stream.encode())
    out.close()
    cap = cv2.VideoCapture(str(video))
    reference = [cap.read()[1] for _ in range(12)]
    cap.release()
    ds = _dataset(tmp_path / "ds", sample)
    args = ["ingest", str(ds), str(video), "--scene", "v", "--blur-threshold", "0", "--quiet"]
    code, out_text, err = run_cli(args, capfd)
    assert code == 0 and err == "", err
    written = _frames_written(ds / "scenes" / "v")
    assert [i for i, _ in written] == list(range(12))
    for index, img in written:
        assert np.abs(img.astype(int) - reference[index].astype(int)).max() <= 3, index


def test_a_letterboxed_video_is_not_taken_for_a_damaged_one(
    tmp_path: Path, sample: Path, capfd
) -> None:
    """Flat bands at the top and the bottom (a letterbox) are the picture, not a decoder's
    filling."""
    video = tmp_path / "boxed.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (W, H))
    for k in range(6):
        img = _picture(k)
        img[:24] = (90, 120, 60)
        img[-24:] = (90, 120, 60)
        writer.write(img)
    writer.release()
    ds = _dataset(tmp_path / "ds", sample)
    args = ["ingest", str(ds), str(video), "--scene", "v", "--blur-threshold", "0", "--json"]
    code, out, err = run_cli([*args, "--quiet"], capfd)
    assert code == 0 and err == "", err
    summary = json.loads(out)
    assert summary["written"] == 6 and summary["dropped"] == []
