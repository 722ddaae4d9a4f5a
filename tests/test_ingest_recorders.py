"""`annotator ingest` of recorders' files: ROS 1 bags laid out as RealSense Viewer writes
them, ROS 2 (MCAP) bags, Azure Kinect MKV files and Record3D exports, all made here from
rendered frames of a textured plane seen by a colour camera of known K and a depth camera
of known K and pose; then the rig written from them, depth registered to colour, times,
and the damaged-file cases."""

from __future__ import annotations

import json
import struct
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from cli_calls import one_error_line, run_cli

from annotator.dataset import load_dataset
from annotator.geometry.camera import Camera
from annotator.ingest.readers.kinect import SensorCamera, mode_camera, parse_calibration
from annotator.ingest.recording import quaternion_matrix
from annotator.ingest.registration import register_depth

W, H = 160, 120  # colour
DW, DH = 128, 96  # depth (RealSense-like bags)
KC = np.array([[150.0, 0, 79.5], [0, 150.0, 59.5], [0, 0, 1]])
KD = np.array([[110.0, 0, 63.5], [0, 110.0, 47.5], [0, 0, 1]])
NORMAL = np.array([0.1, 0.25, 1.0]) / np.linalg.norm([0.1, 0.25, 1.0])
PLANE_D = 700.0  # mm: the plane is NORMAL . X = PLANE_D in the colour camera's frame
T0 = 1_700_000_000.0


def _rot_y(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def _colour_T_depth(deg: float = 3.0, t: tuple[float, float, float] = (25.0, -1.0, 2.0)):
    T = np.eye(4)
    T[:3, :3] = _rot_y(deg)
    T[:3, 3] = t
    return T


def _rays(K: np.ndarray, w: int, h: int) -> np.ndarray:
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)


def plane_depth(K: np.ndarray, w: int, h: int, colour_T_cam: np.ndarray) -> np.ndarray:
    """z (mm) of the plane at each pixel of a camera whose points map into the colour
    camera by ``colour_T_cam``."""
    R, t = colour_T_cam[:3, :3], colour_T_cam[:3, 3]
    # n . (R X + t) = d  <=>  (R^T n) . X = d - n . t
    return (PLANE_D - NORMAL @ t) / (_rays(K, w, h) @ (R.T @ NORMAL))


def render(k: int, K: np.ndarray = KC, w: int = W, h: int = H) -> np.ndarray:
    """Frame k of the colour camera: the plane's texture (shifted 3 mm a frame), BGR."""
    z = plane_depth(K, w, h, np.eye(4))
    X = _rays(K, w, h) * z[..., None]
    a = (X[..., 0] + 3 * k) / 18.0
    b = X[..., 1] / 18.0
    checker = (np.floor(a) + np.floor(b)) % 2
    img = np.stack([60 + 150 * checker, 90 + 40 * np.sin(a * 2), 200 - 120 * checker], -1)
    return np.clip(img, 0, 255).astype(np.uint8)


def depth_frame(c_T_d: np.ndarray, K: np.ndarray = KD, w: int = DW, h: int = DH) -> np.ndarray:
    """The depth camera's view of the plane, uint16 mm (a hole in one corner)."""
    z = plane_depth(K, w, h, c_T_d)
    d = np.round(z).astype(np.uint16)
    d[:4, :4] = 0
    return d


def expected_on_colour() -> np.ndarray:
    return plane_depth(KC, W, H, np.eye(4))


def _registration_error(depth: np.ndarray) -> tuple[float, float]:
    """Median |error| (mm) over the measured pixels, and the share of pixels measured."""
    ok = np.isfinite(depth)
    return float(np.median(np.abs(depth[ok] - expected_on_colour()[ok]))), float(ok.mean())


def ingest_new(ds: Path, src: Path, capture, *extra: str, scene: str = "s") -> dict:
    """``ingest DS SRC --rig-from-source --json``: exit 0, nothing on stderr (FFmpeg's
    lines included); its summary."""
    args = ["ingest", str(ds), str(src), "--scene", scene, "--rig-from-source", "--json"]
    code, out, err = run_cli([*args, "--quiet", *extra], capture)
    assert code == 0 and err == "", err
    return json.loads(out)


# ---------------------------------------------------------------------------- ROS 1 bags


def _ros1_bag(
    path: Path,
    n: int = 6,
    *,
    damaged: int | None = None,
    two_colour: bool = False,
    robot: bool = False,
    tf_static: bool = True,
    compression: str | None = None,
    units_option: str = "Depth_Units",
    times: list[tuple[float, float]] | None = None,
    compressed_depth: bool = False,
) -> Path:
    """A bag as RealSense Viewer records one: colour rgb8 and depth mono16 (1 mm units)
    from two cameras, each with CameraInfo and tf/0 from the depth (reference) stream. With
    ``robot``, as a robot's realsense-ros records one: /camera/color/image_raw and
    /camera/depth/image_rect_raw, their camera_info with frame ids, and (``tf_static``) the
    optical frames' static transforms from camera_link. ``times``: each frame's colour and
    depth stamps (s after the first second; default 30 fps, depth 3-4 ms apart); with
    ``compressed_depth``, depth only as a ``compressedDepth`` topic (PNG, as image_transport
    writes it)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(
        get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage")
    )
    T = ts.types
    c_T_d = _colour_T_depth()

    def header(t: float, frame: str = "") -> object:
        sec = int(t)
        stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)))
        return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)

    def info(K: np.ndarray, w: int, h: int, frame: str = "") -> object:
        roi = T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        return T["sensor_msgs/msg/CameraInfo"](
            header=header(0.0, frame),
            height=h,
            width=w,
            distortion_model="Brown Conrady",
            D=np.zeros(5),
            K=K.reshape(-1),
            R=np.zeros(9),
            P=np.zeros(12),
            binning_x=0,
            binning_y=0,
            roi=roi,
        )

    def image(t: float, arr: np.ndarray, enc: str) -> object:
        data = np.ascontiguousarray(arr).view(np.uint8).reshape(-1)
        h, w = arr.shape[:2]
        return T["sensor_msgs/msg/Image"](
            header=header(t),
            height=h,
            width=w,
            encoding=enc,
            is_bigendian=0,
            step=data.size // h,
            data=data,
        )

    def tf(ref_T: np.ndarray) -> object:
        R, t = ref_T[:3, :3], ref_T[:3, 3] / 1000.0
        w = np.sqrt(max(0.0, 1 + np.trace(R))) / 2
        q = [
            (R[2, 1] - R[1, 2]) / (4 * w),
            (R[0, 2] - R[2, 0]) / (4 * w),
            (R[1, 0] - R[0, 1]) / (4 * w),
            w,
        ]
        return T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
            rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )

    col = "/device_0/sensor_1/Color_0"
    dep = "/device_0/sensor_0/Depth_0"
    colour_topic, depth_topic = f"{col}/image/data", f"{dep}/image/data"
    if robot:
        colour_topic, depth_topic = "/camera/color/image_raw", "/camera/depth/image_rect_raw"
    writer = Writer(path)
    if compression:
        writer.set_compression(Writer.CompressionFormat[compression])
        writer.chunk_threshold = 64 * 1024  # several chunks, the last one cut
    with writer as bag:

        def put(topic: str, msgtype: str, msg: object, t: float) -> None:
            conn = conns.get(topic)
            if conn is None:
                conn = conns[topic] = bag.add_connection(topic, msgtype, typestore=ts)
            bag.write(conn, int(t * 1e9), ts.serialize_ros1(msg, msgtype))

        conns: dict[str, object] = {}
        info_type = "sensor_msgs/msg/CameraInfo"
        if robot:
            put("/camera/color/camera_info", info_type, info(KC, W, H, "colour_optical"), T0)
            put("/camera/depth/camera_info", info_type, info(KD, DW, DH, "depth_optical"), T0)
            if tf_static:
                # camera_link -> each optical frame, the colour one 40 mm aside and turned.
                link_T_colour = np.eye(4)
                link_T_colour[:3, :3] = _rot_y(-10.0)
                link_T_colour[:3, 3] = (40.0, 0.0, 0.0)
                link_T_depth = link_T_colour @ c_T_d
                stamped = [
                    T["geometry_msgs/msg/TransformStamped"](
                        header=header(T0, "camera_link"), child_frame_id=child, transform=tf(X)
                    )
                    for child, X in (
                        ("colour_optical", link_T_colour),
                        ("depth_optical", link_T_depth),
                    )
                ]
                msg = T["tf2_msgs/msg/TFMessage"](transforms=stamped)
                put("/tf_static", "tf2_msgs/msg/TFMessage", msg, T0)
        else:
            put(f"{col}/info/camera_info", info_type, info(KC, W, H), T0)
            put(f"{dep}/info/camera_info", info_type, info(KD, DW, DH), T0)
            put(f"{dep}/tf/0", "geometry_msgs/msg/Transform", tf(np.eye(4)), T0)
            # librealsense writes each stream's extrinsics from the reference (depth) to it.
            put(f"{col}/tf/0", "geometry_msgs/msg/Transform", tf(c_T_d), T0)
            # Newer librealsense writes "Depth_Units", older "Depth Units"; 0.1 mm a unit,
            # the depth frames' 1 mm values written as 10 units.
            units = T["std_msgs/msg/Float32"](data=0.0001)
            option = f"/device_0/sensor_0/option/{units_option}/value"
            put(option, "std_msgs/msg/Float32", units, T0)
        for k in range(n):
            tc = T0 + 1 + k / 30.0
            td = tc + (0.003 if k % 2 else -0.004)
            bag_tc, bag_td = tc, td
            if times is not None:  # the header stamps given; received as usual
                tc, td = T0 + 1 + times[k][0], T0 + 1 + times[k][1]
            rgb = cv2.cvtColor(render(k), cv2.COLOR_BGR2RGB)
            msg = image(tc, rgb, "rgb8")
            if k == damaged:  # a message cut short: half its pixels
                msg = image(tc, rgb, "rgb8")
                msg.data = msg.data[: msg.data.size // 2]  # type: ignore[attr-defined]
            put(colour_topic, "sensor_msgs/msg/Image", msg, bag_tc)
            if two_colour:
                put("/device_0/sensor_2/Color_1/image/data", "sensor_msgs/msg/Image", msg, tc)
            raw = depth_frame(c_T_d) * (1 if robot else 10)  # robot: mm, ROS's unit
            if compressed_depth:
                png = cv2.imencode(".png", raw)[1].reshape(-1)
                cmsg = T["sensor_msgs/msg/CompressedImage"](
                    header=header(td),
                    format="16UC1; compressedDepth png",
                    data=np.concatenate([np.zeros(12, np.uint8), png]),
                )
                ctopic = f"{depth_topic}/compressedDepth"
                put(ctopic, "sensor_msgs/msg/CompressedImage", cmsg, bag_td)
            else:
                put(depth_topic, "sensor_msgs/msg/Image", image(td, raw, "mono16"), bag_td)
            ir = np.full((DH, DW), 80, np.uint8)
            put(
                "/device_0/sensor_0/Infrared_1/image/data",
                "sensor_msgs/msg/Image",
                image(td, ir, "mono8"),
                td,
            )
    return path


def test_a_realsense_bag_makes_the_rig_and_registered_depth(tmp_path: Path, capsys) -> None:
    bag = _ros1_bag(tmp_path / "take.bag")
    ds = tmp_path / "new"
    summary = ingest_new(ds, bag, capsys, scene="s1")
    assert summary["written"] == 6 and summary["dropped"] == [] and summary["depth"]
    assert summary["depth_registered"] and summary["rig_written"]
    assert summary["streams"] == {
        "colour": "/device_0/sensor_1/Color_0/image/data",
        "depth": "/device_0/sensor_0/Depth_0/image/data",
    }
    assert summary["intrinsics"].startswith(
        "CameraInfo /device_0/sensor_1/Color_0/info/camera_info"
    )
    doc = yaml.safe_load((ds / "dataset.yaml").read_text())
    cam = doc["rig"]["cameras"][0]
    assert doc["rig"]["moving"] is True and doc["objects"] == []
    assert doc["markers"]["dictionary"] == "DICT_4X4_1000"
    assert cam["size"] == [W, H] and np.allclose(cam["K"], KC.reshape(-1))
    assert doc["rig"]["depth"]["camera"] == cam["name"]
    frames_doc = json.loads((ds / "scenes" / "s1" / "frames.json").read_text())
    times = [e["time_s"] for e in frames_doc["frames"].values()]
    assert times == pytest.approx([k / 30.0 for k in range(6)], abs=1e-6)
    assert frames_doc["time_origin_s"] == pytest.approx(T0 + 1)
    assert frames_doc["streams"]["colour"].endswith("Color_0/image/data")
    loaded = load_dataset(ds)  # a dataset with no objects yet is read
    frames = loaded.scene("s1").frames()
    depth = frames[2].read_depth(loaded.rig)
    assert depth is not None
    median, covered = _registration_error(depth)
    assert median < 0.6, median  # mm: the plane where it is
    assert covered > 0.85, covered
    img = frames[2].read_image(loaded.rig.cameras[0])
    assert np.abs(img.astype(int) - render(2).astype(int)).max() <= 1
    # The other commands take the dataset and say what it lacks.
    code, out, err = run_cli(["check", str(ds)], capsys)
    assert code == 0 and "warning: no objects yet" in out, out + err
    # Ingesting again into the dataset now there: its rig matches the file.
    code, out, err = run_cli(["ingest", str(ds), str(bag), "--scene", "s2", "--quiet"], capsys)
    assert code == 0, err


def test_registration_against_depth_taken_as_is_is_what_fixes_the_plane() -> None:
    """Without the transform the plane would be off: the test can fail."""
    c_T_d = _colour_T_depth()
    depth_cam = Camera("d", DW, DH, KD)
    colour_cam = Camera("c", W, H, KC)
    raw = depth_frame(c_T_d).astype(float)
    raw[raw == 0] = np.nan
    good = register_depth(raw, depth_cam, colour_cam, c_T_d)
    wrong = register_depth(raw, depth_cam, colour_cam, np.eye(4))
    assert _registration_error(good)[0] < 0.6
    assert _registration_error(wrong)[0] > 5.0
    # A nearer surface in front wins over the plane (z-buffer).
    raw[40:50, 60:70] = 300.0
    near = register_depth(raw, depth_cam, colour_cam, c_T_d)
    assert np.nanmin(near) == pytest.approx(300.0, abs=3.0)
    assert (np.abs(near - 300) < 3).sum() > 150  # 10 x 10 depth pixels, 1.36 x wider each


def test_a_robots_bag_places_its_depth_with_tf_static(tmp_path: Path, capsys) -> None:
    bag = _ros1_bag(tmp_path / "robot.bag", n=3, robot=True)
    ds = tmp_path / "new"
    summary = ingest_new(ds, bag, capsys)
    assert summary["streams"] == {
        "colour": "/camera/color/image_raw",
        "depth": "/camera/depth/image_rect_raw",
    }
    loaded = load_dataset(ds)
    depth = loaded.scene("s").frames()[1].read_depth(loaded.rig)
    assert depth is not None and _registration_error(depth)[0] < 0.6
    # Without the transforms, depth cannot be placed: left out, and the summary says why.
    bare = _ros1_bag(tmp_path / "bare.bag", n=3, robot=True, tf_static=False)
    code, out, err = run_cli(["ingest", str(ds), str(bare), "--scene", "b", "--quiet"], capsys)
    assert code == 0, err
    assert "depth: no" in out and "depth left out" in out and "tf_static" in out


def test_a_bag_with_a_message_cut_short_drops_that_frame(tmp_path: Path, capsys) -> None:
    bag = _ros1_bag(tmp_path / "cut.bag", damaged=3, units_option="Depth Units")
    ds = tmp_path / "new"
    summary = ingest_new(ds, bag, capsys)
    assert summary["written"] == 5
    assert [d["frame"] for d in summary["dropped"]] == [3]
    assert "cut short" in summary["dropped"][0]["why"]
    code, out, err = run_cli(["ingest", str(ds), str(bag), "--scene", "t", "--quiet"], capsys)
    assert "1 dropped as unusable: frame 3 (" in out and err == ""
    loaded = load_dataset(ds)
    depth = loaded.scene("t").frames()[0].read_depth(loaded.rig)
    assert depth is not None and _registration_error(depth)[0] < 0.6  # the unit was read


def test_a_failed_ingest_leaves_no_dataset_behind(tmp_path: Path, capsys) -> None:
    bag = _ros1_bag(tmp_path / "bad.bag", n=1, damaged=0)  # its only frame cut short
    ds = tmp_path / "deep" / "new"
    args = ["ingest", str(ds), str(bag), "--scene", "s", "--rig-from-source"]
    line = one_error_line(args, capsys)
    assert "no frame is left to write (none could be decoded)" in line
    assert not (tmp_path / "deep").exists()


@pytest.mark.parametrize("compression", [None, "LZ4", "BZ2"])
def test_a_ros1_bag_cut_short_gives_its_whole_messages_and_says_so(
    tmp_path: Path, capsys, compression: str | None
) -> None:
    data = _ros1_bag(tmp_path / "take.bag", n=6, compression=compression).read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[: len(data) * 2 // 3])
    summary = ingest_new(tmp_path / "ds", cut, capsys)
    assert "the bag ends early or was never closed" in summary["ended_early"]
    assert 0 < summary["written"] < 6
    # The last colour frames may have lost their depth partner to the cut.
    assert all(d["why"] == "no depth frame within 20 ms" for d in summary["dropped"])
    loaded = load_dataset(tmp_path / "ds")
    doc = json.loads((tmp_path / "ds" / "scenes" / "s" / "frames.json").read_text())
    sources = [e["source"] for e in doc["frames"].values()]
    assert sources == list(range(len(sources)))
    for k, frame in zip(sources, loaded.scene("s").frames()):
        img = frame.read_image(loaded.rig.cameras[0])
        assert np.abs(img.astype(int) - render(k).astype(int)).max() <= 1
        depth = frame.read_depth(loaded.rig)
        assert depth is not None and _registration_error(depth)[0] < 0.6


def test_an_mcap_bag_cut_short_says_so(tmp_path: Path, capsys) -> None:
    r2 = _ros2_bag(tmp_path / "r2", n=3)
    mcap = next(r2.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:-100])
    args = ["ingest", str(tmp_path / "ds"), str(r2), "--scene", "s", "--rig-from-source"]
    line = one_error_line(args, capsys)
    assert "the bag ends early" in line and "r2" in line and "mcap recover" in line
    assert not (tmp_path / "ds").exists()


def test_a_bag_of_two_colour_topics_needs_one_chosen(tmp_path: Path, capsys) -> None:
    bag = _ros1_bag(tmp_path / "two.bag", n=3, two_colour=True)
    ds = tmp_path / "new"
    args = ["ingest", str(ds), str(bag), "--scene", "s", "--rig-from-source", "--quiet"]
    line = one_error_line(args, capsys)
    assert "several colour topics" in line and "--color-topic" in line
    assert "/device_0/sensor_2/Color_1/image/data" in line and "two.bag" in line
    topic = "/device_0/sensor_1/Color_0/image/data"
    code, _, err = run_cli([*args, "--color-topic", topic], capsys)
    assert code == 0, err
    line = one_error_line([*args, "--color-topic", "/nope", "--scene", "u"], capsys)
    assert "--color-topic /nope: no such image topic" in line


def test_a_rig_that_is_not_the_recording_camera_is_refused(tmp_path: Path, capsys) -> None:
    from annotator.dataset.model import DepthSpec, Rig
    from annotator.dataset.write import write_dataset_yaml

    bag = _ros1_bag(tmp_path / "take.bag", n=2)
    ds = tmp_path / "ds"
    off = KC.copy()
    off[0, 0] *= 1.03
    rig = Rig(cameras=(Camera("cam", W, H, off),), depth=DepthSpec("cam", 0.1), moving=True)
    write_dataset_yaml(ds, name="x", dictionary="DICT_4X4_50", rig=rig, objects=[])
    line = one_error_line(["ingest", str(ds), str(bag), "--scene", "s"], capsys)
    assert "fx 150.0" in line and "fx 154.5" in line and "more than 1%" in line
    assert not (ds / "scenes").exists() or not any((ds / "scenes").iterdir())
    near = KC.copy()
    near[0, 0] *= 1.005
    rig = Rig(cameras=(Camera("cam", W, H, near),), depth=DepthSpec("cam", 0.1), moving=True)
    write_dataset_yaml(ds, name="x", dictionary="DICT_4X4_50", rig=rig, objects=[])
    code, _, err = run_cli(["ingest", str(ds), str(bag), "--scene", "s", "--quiet"], capsys)
    assert code == 0, err


# ------------------------------------------------------------------------ ROS 2 (MCAP)


def _ros2_bag(path: Path, n: int = 5, *, truncated: int | None = None) -> Path:
    """A ROS 2 bag (MCAP) as realsense-ros writes one: JPEG colour, depth aligned to colour."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types

    def header(t: float, frame: str) -> object:
        sec = int(t)
        stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)))
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    roi = T["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    dist = np.array([0.01, -0.02, 0.0005, -0.0003, 0.004])
    info = T["sensor_msgs/msg/CameraInfo"](
        header=header(T0, "camera_color_optical_frame"),
        height=H,
        width=W,
        distortion_model="plumb_bob",
        d=dist,
        k=KC.reshape(-1),
        r=np.eye(3).reshape(-1),
        p=np.zeros(12),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as bag:
        conns: dict[str, object] = {}

        def put(topic: str, msgtype: str, msg: object, t: float) -> None:
            conn = conns.get(topic)
            if conn is None:
                conn = conns[topic] = bag.add_connection(topic, msgtype, typestore=ts)
            bag.write(conn, int(t * 1e9), ts.serialize_cdr(msg, msgtype))

        put("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", info, T0)
        put("/camera/aligned_depth_to_color/camera_info", "sensor_msgs/msg/CameraInfo", info, T0)
        for k in range(n):
            t = T0 + k / 15.0
            jpeg = cv2.imencode(".jpg", render(k), [cv2.IMWRITE_JPEG_QUALITY, 95])[1].reshape(-1)
            if k == truncated:
                jpeg = jpeg[: len(jpeg) * 2 // 3]
            msg = T["sensor_msgs/msg/CompressedImage"](
                header=header(t, "camera_color_optical_frame"), format="jpeg", data=jpeg
            )
            put("/camera/color/image_raw/compressed", "sensor_msgs/msg/CompressedImage", msg, t)
            d = np.round(expected_on_colour()).astype(np.uint16).view(np.uint8).reshape(-1)
            dmsg = T["sensor_msgs/msg/Image"](
                header=header(t + 0.001, "camera_color_optical_frame"),
                height=H,
                width=W,
                encoding="16UC1",
                is_bigendian=0,
                step=2 * W,
                data=d,
            )
            put(
                "/camera/aligned_depth_to_color/image_raw", "sensor_msgs/msg/Image", dmsg, t + 0.001
            )
    return path


def test_a_ros2_mcap_bag_with_aligned_depth_and_a_truncated_jpeg(tmp_path: Path, capsys) -> None:
    bag = _ros2_bag(tmp_path / "take", truncated=2)
    ds = tmp_path / "new"
    summary = ingest_new(ds, bag, capsys, "--camera", "rgb")
    assert summary["written"] == 4 and summary["kind"] == "ROS 2 bag"
    assert summary["dropped"] == [{"frame": 2, "why": "a truncated JPEG (decoded partly)"}]
    assert summary["streams"]["depth"] == "/camera/aligned_depth_to_color/image_raw"
    doc = yaml.safe_load((ds / "dataset.yaml").read_text())
    cam = doc["rig"]["cameras"][0]
    assert cam["name"] == "rgb" and np.allclose(cam["K"], KC.reshape(-1))
    assert np.allclose(cam["dist"], [0.01, -0.02, 0.0005, -0.0003, 0.004])
    loaded = load_dataset(ds)
    frames = loaded.scene("s").frames()
    depth = frames[0].read_depth(loaded.rig)
    assert depth is not None
    assert _registration_error(depth)[0] < 0.6 and _registration_error(depth)[1] == 1.0
    times = [
        e["time_s"]
        for e in json.loads((ds / "scenes/s/frames.json").read_text())["frames"].values()
    ]
    assert times == pytest.approx([0, 1 / 15, 3 / 15, 4 / 15], abs=1e-6)


# ------------------------------------------------------------------------- Azure Kinect

KW, KH = 160, 90  # a 16:9 colour mode (the 4:3 sensor scaled to 160x120, 15 rows cropped)
KDW, KDH = 320, 288  # NFOV 2x2 binned


def _k4a_calibration(c_T_d: np.ndarray) -> dict:
    """calibration.json as the Azure Kinect writes it (normalised, corner-based)."""
    depth = [0.5, 234 / 512, 250 / 512, 250 / 512, *[0.0] * 6, 0.0, 0.0, 0.0, 0.0, 1.7]
    colour = [0.5, 0.5, 150 / 160, 150 / 120, *[0.0] * 6, 0.0, 0.0, 0.0, 0.0, 1.7]

    def cam(loc: str, params: list[float], size: tuple[int, int], T: np.ndarray) -> dict:
        return {
            "Intrinsics": {
                "ModelParameterCount": 14,
                "ModelParameters": params,
                "ModelType": "CALIBRATION_LensDistortionModelBrownConrady",
            },
            "Location": loc,
            "MetricRadius": 1.7,
            "Rt": {
                "Rotation": T[:3, :3].reshape(-1).tolist(),
                "Translation": (T[:3, 3] / 1000).tolist(),
            },
            "SensorHeight": size[1],
            "SensorWidth": size[0],
        }

    return {
        "CalibrationInformation": {
            "Cameras": [
                cam("CALIBRATION_CameraLocationD0", depth, (1024, 1024), np.eye(4)),
                cam("CALIBRATION_CameraLocationPV0", colour, (4096, 3072), c_T_d),
            ],
            "InertialSensors": [],
            "Metadata": {"SerialId": "000000000000"},
        }
    }


K_KINECT = np.array([[150.0, 0, 79.5], [0, 150.0, 44.5], [0, 0, 1]])
K_KINECT_DEPTH = np.array([[250.0, 0, 159.5], [0, 250.0, 143.5], [0, 0, 1]])


def _mkv(path: Path, n: int = 5, *, damage: int | None = None, cut: bool = False) -> Path:
    """A K4A-like MKV: COLOR (MJPEG), DEPTH (b16g: 16-bit big-endian grey, mm) and the
    calibration.json attachment. PyAV writes the attachment (add_attachment); Matroska
    takes raw 16-bit video only in VFW mode, whose header is then given the b16g FourCC
    the Azure Kinect uses (same length, patched in place)."""
    import av

    c_T_d = _colour_T_depth(2.0, (-32.0, -2.0, 4.0))
    out = av.open(str(path), "w", format="matroska", options={"allow_raw_vfw": "1"})
    colour = out.add_stream("mjpeg", rate=30)
    colour.width, colour.height, colour.pix_fmt = KW, KH, "yuvj444p"
    colour.metadata["title"] = "COLOR"
    colour.codec_context.options = {"q": "2"}
    depth = out.add_stream("rawvideo", rate=30)
    depth.width, depth.height, depth.pix_fmt = KDW, KDH, "gray16be"
    depth.metadata["title"] = "DEPTH"
    calib = json.dumps(_k4a_calibration(c_T_d)).encode()
    out.add_attachment("calibration.json", "application/octet-stream", calib)
    packets = []
    dz = depth_frame(c_T_d, K_KINECT_DEPTH, KDW, KDH)
    for k in range(n):
        rgb = cv2.cvtColor(render(k, K_KINECT, KW, KH), cv2.COLOR_BGR2RGB)
        f = av.VideoFrame.from_ndarray(rgb, format="rgb24")
        f.pts = k
        for p in colour.encode(f):
            packets.append(bytes(p))
            out.mux(p)
        g = av.VideoFrame.from_ndarray(dz, format="gray16be")
        g.pts = k
        for p in depth.encode(g):
            out.mux(p)
    for s in (colour, depth):
        for p in s.encode():
            out.mux(p)
    out.close()
    data = bytearray(path.read_bytes())
    at = data.find(b"\x63\xa2\xa8") + 3  # CodecPrivate: the 40-byte BITMAPINFOHEADER
    data[at + 8 : at + 12] = struct.pack("<i", KDH)
    data[at + 16 : at + 20] = b"b16g"
    if damage is not None:  # bytes overwritten inside one colour frame's JPEG data
        p = packets[damage]
        start = data.find(p)
        mid = start + len(p) // 2
        # Random bytes, with the 0xFF marker bytes a damaged stretch of this length holds.
        junk = np.random.default_rng(5).integers(0, 256, 40, np.uint8)
        junk[::9] = 0xFF
        data[mid : mid + 40] = junk.tobytes()
    if cut:
        data = data[: len(data) * 4 // 5]
    path.write_bytes(bytes(data))
    return path


def test_the_kinect_calibration_is_scaled_and_cropped_to_the_mode() -> None:
    sensors = _k4a_calibration(np.eye(4))["CalibrationInformation"]["Cameras"]
    colour = SensorCamera(
        tuple(sensors[1]["Intrinsics"]["ModelParameters"]), (4096, 3072), np.eye(4)
    )
    cam = mode_camera(colour, (KW, KH), "c", depth=False, path=Path("x"))
    assert np.allclose(cam.K, K_KINECT)
    depth = SensorCamera(
        tuple(sensors[0]["Intrinsics"]["ModelParameters"]), (1024, 1024), np.eye(4)
    )
    dcam = mode_camera(depth, (KDW, KDH), "d", depth=True, path=Path("x"))
    assert np.allclose(dcam.K, K_KINECT_DEPTH)
    # 720p from a real-looking sensor calibration: 1280x960 less 120 rows top and bottom.
    params = (
        0.4967,
        0.5109,
        0.4709,
        0.6274,
        0.72,
        -2.88,
        1.63,
        0.60,
        -2.71,
        1.56,
        0,
        0,
        -0.00014,
        0.00078,
    )
    cam = mode_camera(
        SensorCamera(params, (4096, 3072), np.eye(4)), (1280, 720), "c", depth=False, path=Path("x")
    )
    assert cam.K[0, 0] == pytest.approx(0.4709 * 1280)
    assert cam.K[1, 1] == pytest.approx(0.6274 * 960)
    assert cam.K[1, 2] == pytest.approx(0.5109 * 960 - 120 - 0.5)
    assert cam.dist.tolist() == pytest.approx(
        [0.72, -2.88, 0.00078, -0.00014, 1.63, 0.60, -2.71, 1.56]
    )


def test_a_calibration_naming_its_cameras_by_purpose_only_is_read() -> None:
    doc = _k4a_calibration(_colour_T_depth())
    for cam, purpose in zip(doc["CalibrationInformation"]["Cameras"], ("Depth", "PhotoVideo")):
        del cam["Location"]
        cam["Purpose"] = f"CALIBRATION_CameraPurpose{purpose}"
    cams = parse_calibration(json.dumps(doc), Path("x"))
    assert set(cams) == {"CALIBRATION_CameraLocationD0", "CALIBRATION_CameraLocationPV0"}
    assert np.allclose(cams["CALIBRATION_CameraLocationPV0"].cam_T_depth, _colour_T_depth())


def test_a_real_kinects_calibration_gives_what_the_sdk_reports() -> None:
    """One Azure Kinect's calibration.json parameters, published with the intrinsics the
    Sensor SDK reported for them (1080p colour, NFOV unbinned depth)."""
    colour = SensorCamera(
        (0.4967627227306366, 0.5108628273010254, 0.470907062292099, 0.6274453997612)
        + (0.7227460145950317, -2.8855903148651123, 1.6327226161956787, 0.6021990180015564)
        + (-2.7196261882781982, 1.565053105354309, 0, 0)
        + (-0.0001431911950930953, 0.0007828465895727277),
        (4096, 3072),
        np.eye(4),
    )
    depth = SensorCamera(
        (0.5122697949409485, 0.49451231956481934, 0.4921168386936188, 0.4921667277812958)
        + (3.1305770874023438, 2.324939012527466, 0.1304156482219696, 3.458651542663574)
        + (3.350114583969116, 0.6629416346549988, 0, 0)
        + (-0.0000511557373101823, 0.00008132171933539212),
        (1024, 1024),
        np.eye(4),
    )
    c = mode_camera(colour, (1920, 1080), "c", depth=False, path=Path("x"))
    assert [c.K[0, 2], c.K[1, 2], c.K[0, 0], c.K[1, 1]] == pytest.approx(
        [953.284424, 555.142456, 904.141541, 903.521362], abs=1e-3
    )
    assert c.dist[2:4].tolist() == pytest.approx([0.000783, -0.000143], abs=1e-6)  # p1, p2
    d = mode_camera(depth, (640, 576), "d", depth=True, path=Path("x"))
    assert [d.K[0, 2], d.K[1, 2], d.K[0, 0], d.K[1, 1]] == pytest.approx(
        [332.064270, 325.880615, 503.927643, 503.978729], abs=1e-3
    )
    # Its strong rational distortion is inverted to within a hundredth of a pixel.
    uv = d.project(d.pixel_rays(step=8))
    u, v = np.meshgrid(np.arange(0, 640, 8.0), np.arange(0, 576, 8.0))
    assert np.nanmax(np.hypot(uv[..., 0] - u, uv[..., 1] - v)) < 0.01


def test_an_azure_kinect_mkv_with_its_calibration_attachment(tmp_path: Path, capfd) -> None:
    mkv = _mkv(tmp_path / "k4a.mkv")
    ds = tmp_path / "new"
    summary = ingest_new(ds, mkv, capfd)
    assert summary["kind"] == "Azure Kinect recording" and summary["written"] == 5
    assert summary["intrinsics"] == "calibration.json attachment"
    doc = yaml.safe_load((ds / "dataset.yaml").read_text())
    assert np.allclose(doc["rig"]["cameras"][0]["K"], K_KINECT.reshape(-1))
    assert doc["rig"]["cameras"][0]["size"] == [KW, KH]
    loaded = load_dataset(ds)
    depth = loaded.scene("s").frames()[1].read_depth(loaded.rig)
    assert depth is not None
    expected = plane_depth(K_KINECT, KW, KH, np.eye(4))
    ok = np.isfinite(depth)
    assert ok.mean() > 0.9
    assert np.median(np.abs(depth[ok] - expected[ok])) < 0.6
    times = [
        e["time_s"]
        for e in json.loads((ds / "scenes/s/frames.json").read_text())["frames"].values()
    ]
    assert times == pytest.approx([k / 30 for k in range(5)], abs=2e-3)


def test_a_damaged_and_a_cut_kinect_recording(tmp_path: Path, capfd) -> None:
    mkv = _mkv(tmp_path / "bad.mkv", n=6, damage=2)
    ds = tmp_path / "new"
    summary = ingest_new(ds, mkv, capfd)  # FFmpeg's own lines stay hidden
    assert [d["frame"] for d in summary["dropped"]] == [2], summary["dropped"]
    assert summary["written"] == 5
    cut = _mkv(tmp_path / "cut.mkv", n=6, cut=True)
    code, out, err = run_cli(["ingest", str(ds), str(cut), "--scene", "c", "--quiet"], capfd)
    assert code == 0, err
    assert err == ""
    assert "the file ends early: its frames stop at" in out
    written = len(load_dataset(ds).scene("c").frames())
    assert written < 6


# ----------------------------------------------------------------------------- Record3D


def _r3d(path: Path, n: int = 4, *, damaged_depth: int | None = None) -> Path:
    """A Record3D-like export: metadata (K column-major), rgbd/i.jpg, rgbd/i.depth (LZFSE
    float32 metres at 64x48)."""
    import lzfse

    dw, dh = 64, 48
    kd = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])  # KC scaled by 0.4
    meta = {
        "w": W,
        "h": H,
        "dw": dw,
        "dh": dh,
        "K": KC.T.reshape(-1).tolist(),
        "fps": 60,
        "frameTimestamps": [100.0 + k / 60 for k in range(n)],
        "cameraType": 1,
    }
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("metadata", json.dumps(meta))
        for k in range(n):
            z.writestr(f"rgbd/{k}.jpg", cv2.imencode(".jpg", render(k))[1].tobytes())
            metres = (plane_depth(kd, dw, dh, np.eye(4)) / 1000).astype("<f4")
            blob = lzfse.compress(metres.tobytes())
            if k == damaged_depth:
                blob = blob[: len(blob) // 3]
            z.writestr(f"rgbd/{k}.depth", blob)
            conf = np.full((dh, dw), 2, np.uint8)
            conf[:8, :8] = 0  # ARKit unsure of one corner
            z.writestr(f"rgbd/{k}.conf", lzfse.compress(conf.tobytes()))
    return path


def test_a_record3d_export(tmp_path: Path, capsys) -> None:
    r3d = _r3d(tmp_path / "scan.r3d", damaged_depth=1)
    ds = tmp_path / "new"
    summary = ingest_new(ds, r3d, capsys)
    assert summary["written"] == 3 and [d["frame"] for d in summary["dropped"]] == ["rgbd/1.jpg"]
    doc = yaml.safe_load((ds / "dataset.yaml").read_text())
    assert np.allclose(doc["rig"]["cameras"][0]["K"], KC.reshape(-1))
    loaded = load_dataset(ds)
    depth = loaded.scene("s").frames()[0].read_depth(loaded.rig)
    assert depth is not None
    median, covered = _registration_error(depth)
    assert median < 1.0 and covered > 0.95
    assert np.isnan(depth[:15, :15]).all() and np.isfinite(depth[25:, 25:]).all()  # confidence
    times = [
        e["time_s"]
        for e in json.loads((ds / "scenes/s/frames.json").read_text())["frames"].values()
    ]
    assert times == pytest.approx([0, 2 / 60, 3 / 60], abs=1e-6)


# ------------------------------------------------------------------------ the rest


def test_helpers() -> None:
    R = quaternion_matrix(0.0, np.sin(0.1), 0.0, np.cos(0.1))
    assert np.allclose(R, _rot_y(np.degrees(0.2)))


@pytest.mark.parametrize(
    ("topics", "colour", "depth"),
    [
        (  # realsense-ros, with compressed and rectified copies
            [
                "/camera/color/image_raw",
                "/camera/color/image_raw/compressed",
                "/camera/color/image_rect_color",
                "/camera/depth/image_rect_raw",
                "/camera/aligned_depth_to_color/image_raw",
                "/camera/infra1/image_rect_raw",
            ],
            "/camera/color/image_raw",
            "/camera/aligned_depth_to_color/image_raw",
        ),
        (  # Azure Kinect ROS driver
            ["/rgb/image_raw", "/depth/image_raw", "/depth_to_rgb/image_raw", "/ir/image_raw"],
            "/rgb/image_raw",
            "/depth_to_rgb/image_raw",
        ),
        (  # openni
            ["/camera/rgb/image_color", "/camera/depth_registered/image_raw"],
            "/camera/rgb/image_color",
            "/camera/depth_registered/image_raw",
        ),
    ],
)
def test_the_topics_recorders_publish_are_told_apart(topics, colour, depth) -> None:
    from types import SimpleNamespace

    from annotator.ingest.readers.rosbag import COMPRESSED, IMAGE, _choose

    conns = [
        SimpleNamespace(topic=t, msgtype=COMPRESSED if t.endswith("compressed") else IMAGE)
        for t in topics
    ]
    assert _choose(Path("b.bag"), conns, None, want_depth=False).topic == colour
    assert _choose(Path("b.bag"), conns, None, want_depth=True).topic == depth


def test_realsense_inverse_brown_conrady_becomes_opencvs_forward_model() -> None:
    """A D455's colour camera comes as "Inverse Brown Conrady" (distorted -> undistorted);
    the rig gets OpenCV's coefficients of the same lens (undistorted -> distorted)."""
    from annotator.ingest.distortion import distort, forward_brown_conrady

    K = np.array([[640.0, 0, 642.5], [0, 639.0, 361.2], [0, 0, 1]])
    inverse = np.array([-0.0553, 0.0664, -0.0007, 0.0005, -0.0212])
    D = forward_brown_conrady(K, inverse, 1280, 720)
    u, v = np.meshgrid(np.arange(0, 1280, 37.0), np.arange(0, 720, 29.0))
    xd, yd = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    xu, yu = distort(xd, yd, np.concatenate([inverse, np.zeros(3)]))
    pts = np.stack([xu, yu, np.ones_like(xu)], -1).reshape(-1, 3)
    uv = Camera("c", 1280, 720, K, D).project(pts).reshape(*u.shape, 2)
    assert np.abs(uv[..., 0] - u).max() < 0.06 and np.abs(uv[..., 1] - v).max() < 0.06
    wrong = Camera("c", 1280, 720, K, inverse).project(pts).reshape(*u.shape, 2)
    assert np.abs(wrong[..., 0] - u).max() > 1.0  # taken as it comes, it would be off


def test_help_documents_the_recorders_options(capsys) -> None:
    with pytest.raises(SystemExit) as stop:
        run_cli(["ingest", "--help"], capsys)
    assert stop.value.code == 0
    out = capsys.readouterr().out
    for option in ("--color-topic", "--depth-topic", "--rig-from-source", "--dictionary"):
        assert option in out
    for kind in ("ROS 1 bag", "Azure Kinect", "Record3D", ".mcap"):
        assert kind in " ".join(out.split())


def test_record3d_depth_without_an_lzfse_reader_is_refused_in_one_line(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    import sys

    r3d = _r3d(tmp_path / "scan.r3d", n=2)
    monkeypatch.setitem(sys.modules, "lzfse", None)  # as if not installed
    args = ["ingest", str(tmp_path / "ds"), str(r3d), "--scene", "s", "--rig-from-source"]
    line = one_error_line(args, capsys)
    assert "the `lzfse` package is not installed" in line and "--no-depth" in line
    assert "scan.r3d" in line
    summary = ingest_new(tmp_path / "ds", r3d, capsys, "--no-depth")
    assert summary["written"] == 2 and not summary["depth"]
