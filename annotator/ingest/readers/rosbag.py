"""ROS bags: ROS 1 ``.bag`` files (RealSense Viewer's recordings are ROS 1 bags) and ROS 2
bags (a folder with ``metadata.yaml``, sqlite3 or MCAP), read with ``rosbags``.

Streams: colour is a ``sensor_msgs/Image`` or ``CompressedImage`` topic, depth an ``Image``
topic of ``16UC1``/``mono16`` (mm, or RealSense's ``Depth Units`` option, in metres a unit)
or ``32FC1`` (metres). A topic is chosen when only one fits (depth: ``depth`` in its name,
one drawn on the colour grid first: ``aligned_depth_to_color``, ``depth_to_rgb``,
``depth_registered``; colour: the others but infrared, raw before compressed, ``.../image_raw``
before a rectified copy), otherwise ``--color-topic`` / ``--depth-topic`` name it.

Calibration: each image topic's ``CameraInfo`` is the one in its namespace or a parent's
(``/camera/color/camera_info`` for ``/camera/color/image_raw``, RealSense's
``.../Color_0/info/camera_info`` for ``.../Color_0/image/data``). Depth from another camera
is moved into the colour camera with RealSense's ``<stream>/tf/<group>`` transforms (each
the extrinsics from the device's reference stream to the stream, as librealsense's recorder
writes them) or with ``/tf_static`` between the two ``CameraInfo`` frames; depth whose ``CameraInfo`` is the colour one's is taken as registered already.
Frame times are the messages' header stamps (the bag's receive times when a stamp is 0).
A ROS 1 bag without its index (cut short, or never closed) is read up to its last whole
message (:mod:`.rosbag1_salvage`) and said to end early.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.ingest.distortion import forward_brown_conrady
from annotator.ingest.readers import RecorderReader
from annotator.ingest.readers.ros_image import COMPRESSED, IMAGE, image_of
from annotator.ingest.readers.rosbag1_salvage import SalvageReader
from annotator.ingest.recording import (
    Calibration,
    Decoded,
    DepthGeometry,
    Recording,
    join_depth,
    pair_by_time,
    quaternion_matrix,
    transform,
)

CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
_REGISTERED = ("aligned", "depth_to_rgb", "depth_to_color", "depth_registered")
_OTHER = ("infra", "/ir", "_ir", "confidence", "fisheye", "compresseddepth", "thermal")
#: CameraInfo distortion models whose coefficients are OpenCV's (k1, k2, p1, p2[, k3...]).
#: (RealSense's "Modified Brown Conrady" differs from it only in second-order tangential
#: terms; its "Inverse Brown Conrady" is converted, :func:`forward_brown_conrady`.)
_OPENCV_MODELS = (
    "plumb_bob",
    "rational_polynomial",
    "brown conrady",
    "modified brown conrady",
    "inverse brown conrady",
    "",
)


def is_bag(path: Path) -> bool:
    """Whether ``path`` is a ROS 1 bag or a ROS 2 bag (its folder or its storage file)."""
    if path.is_file():
        return path.suffix.lower() in (".bag", ".mcap", ".db3")
    return path.is_dir() and (path / "metadata.yaml").is_file()


def open_bag(
    path: Path,
    *,
    color_topic: str | None,
    depth_topic: str | None,
    depth: bool,
    tolerance_s: float,
) -> Recording:
    """The bag's colour frames, their depth partners and the cameras (module docstring).

    Raises:
        UserError: an unreadable bag, no image topic, several and none chosen, a chosen
            topic that is not there, a distortion model that is not OpenCV's.
    """
    reader = _reader(path)
    try:
        conns = list(reader.connections)
        colour_conn = _choose(path, conns, color_topic, want_depth=False)
        depth_conn = _choose(path, conns, depth_topic, want_depth=True) if depth else None
        rec = _index(path, reader, conns, colour_conn, depth_conn, tolerance_s)
    except UserError:
        raise
    except Exception as exc:  # rosbags raises its own errors for damaged bags
        raise UserError(f"not a readable ROS bag ({exc})", path=path) from None
    finally:
        reader.close()
    if isinstance(reader, SalvageReader):
        rec.ended_early = (
            "the bag ends early or was never closed (its index, written last, is missing): "
            "read up to its last whole message"
        )
    return rec


def _reader(path: Path) -> Any:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from annotator.ingest.readers.rosbag1_salvage import is_unindexed

    if path.is_file() and path.suffix.lower() == ".bag" and is_unindexed(path):
        return SalvageReader(path)
    target = path
    if path.is_file() and path.suffix.lower() in (".mcap", ".db3"):
        if (path.parent / "metadata.yaml").is_file():
            target = path.parent
    try:
        reader = AnyReader([target], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except Exception as exc:
        cut = _cut_short(path, str(exc))
        raise UserError(cut or f"not a readable ROS bag ({exc})", path=path) from None
    return reader


def _cut_short(path: Path, error: str) -> str | None:
    """What to say of a bag that ends early (its index or summary, written last, missing)."""
    if path.is_file() and path.suffix.lower() == ".bag":
        try:
            with path.open("rb") as f:
                head = f.read(4096)
            size = path.stat().st_size
        except OSError:
            return None
        at = head.find(b"index_pos=")
        if at >= 0:
            index_pos = int.from_bytes(head[at + 10 : at + 18], "little")
            if index_pos == 0 or index_pos >= size:
                return (
                    "the bag ends early or was never closed: its index, written last, is "
                    "missing (`rosbag reindex` it, then ingest again)"
                )
    if "end magic" in error.lower() or "unexpected end" in error.lower():
        return "the bag ends early: its MCAP file stops before its end (`mcap recover` it)"
    return None


def _is_depth_name(topic: str) -> bool:
    return "depth" in topic.lower()


def _is_registered_name(topic: str) -> bool:
    """Whether a depth topic's name says it is drawn on the colour grid already
    (realsense-ros, Azure Kinect ROS driver, openni)."""
    low = topic.lower()
    return any(k in low for k in _REGISTERED)


def _is_other(topic: str) -> bool:
    low = topic.lower()
    return any(o in low for o in _OTHER)


def _choose(path: Path, conns: list[Any], wanted: str | None, *, want_depth: bool) -> Any:
    """The colour (or depth) topic's connection (module docstring)."""
    images = [c for c in conns if c.msgtype in (IMAGE, COMPRESSED)]
    option = "--depth-topic" if want_depth else "--color-topic"
    if wanted is not None:
        match = [c for c in images if c.topic == wanted]
        if not match:
            listed = ", ".join(sorted({c.topic for c in images})) or "none"
            raise UserError(
                f"{option} {wanted}: no such image topic (image topics: {listed})", path=path
            )
        return match[0]
    if want_depth:
        cands = [c for c in images if _is_depth_name(c.topic) and c.msgtype == IMAGE]
        cands = [c for c in cands if "compresseddepth" not in c.topic.lower()]
        # image_transport's compressedDepth (PNG of the 16-bit depth) when no raw depth is there
        cands = cands or [c for c in images if "compresseddepth" in c.topic.lower()]
        aligned = [c for c in cands if _is_registered_name(c.topic)]
        cands = aligned or cands
        if not cands:
            return None
    else:
        cands = [c for c in images if not _is_depth_name(c.topic) and not _is_other(c.topic)]
        raw = [c for c in cands if c.msgtype == IMAGE]
        cands = raw or cands
        named = [c for c in cands if any(k in c.topic.lower() for k in ("color", "colour", "rgb"))]
        if len(cands) > 1 and named:
            cands = named
        unrectified = [c for c in cands if "/image_raw" in c.topic]
        if len({c.topic for c in cands}) > 1 and len({c.topic for c in unrectified}) == 1:
            cands = unrectified  # its CameraInfo describes it (a rectified copy has no distortion)
        if not cands:
            listed = ", ".join(sorted({c.topic for c in conns})) or "none"
            raise UserError(f"has no colour image topic (topics: {listed})", path=path)
    topics = sorted({c.topic for c in cands})
    if len(topics) > 1:
        raise UserError(
            f"several {'depth' if want_depth else 'colour'} topics ({', '.join(topics)}): "
            f"choose one with {option}",
            path=path,
        )
    # One topic may come through several connections (a bag recorded in pieces).
    return cands[0]


def _stamp(msg: Any, bag_ns: int) -> float:
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if stamp is not None:
        sec = int(getattr(stamp, "sec", 0))
        nsec = int(getattr(stamp, "nanosec", 0))
        if sec or nsec:
            return sec + nsec * 1e-9
    return bag_ns * 1e-9


def _index(
    path: Path,
    reader: Any,
    conns: list[Any],
    colour_conn: Any,
    depth_conn: Any | None,
    tolerance_s: float,
) -> Recording:
    colour_times: list[float | None] = []
    depth_times: list[float | None] = []
    want = [c for c in conns if c.topic == colour_conn.topic]
    if depth_conn is not None:
        want += [c for c in conns if c.topic == depth_conn.topic]
    for conn, bag_ns, raw in reader.messages(connections=want):
        try:
            msg = reader.deserialize(raw, conn.msgtype)
            t: float | None = _stamp(msg, bag_ns)
        except Exception:  # a damaged message: no stamp; decode() says why
            t = bag_ns * 1e-9
        if conn.topic == colour_conn.topic:
            colour_times.append(t)
        else:
            depth_times.append(t)
    if not colour_times:
        raise UserError(f"topic {colour_conn.topic} holds no message", path=path)
    _check_colour_encoding(path, reader, conns, colour_conn)
    if depth_conn is not None and depth_conn.topic == colour_conn.topic:
        raise UserError(
            f"{colour_conn.topic} is both the colour and the depth topic: name another with "
            "--color-topic or --depth-topic",
            path=path,
        )
    calibration, note = _calibration(path, reader, conns, colour_conn, depth_conn)
    if depth_conn is not None and (not depth_times or note is not None):
        depth_conn = None
    pairs: list[int | None] = (
        pair_by_time(colour_times, depth_times, tolerance_s)
        if depth_conn is not None
        else [None] * len(colour_times)
    )
    streams = {"colour": colour_conn.topic}
    if depth_conn is not None:
        streams["depth"] = depth_conn.topic
    kind = "ROS 1 bag" if path.suffix.lower() == ".bag" else "ROS 2 bag"
    return _BagRecording(
        path=path,
        kind=kind,
        times=colour_times,
        labels=list(range(len(colour_times))),
        depth_for=pairs,
        streams=streams,
        calibration=calibration,
        notes=[note] if note else [],
        depth_times=depth_times if depth_conn is not None else [],
    )


#: Encodings of depth (or other single-channel measurement) images, never colour.
_DEPTH_ENCODINGS = ("16uc1", "mono16", "z16", "32fc1", "16sc1", "32sc1", "64fc1")


def _check_colour_encoding(path: Path, reader: Any, conns: list[Any], conn: Any) -> None:
    """Refuse (one line) a colour topic whose images are depth: written as colour they
    would be depth maps in the dataset's intensity images."""
    msg = _first(reader, conns, conn.topic)
    if msg is None:
        return
    enc = str(getattr(msg, "encoding", "") or getattr(msg, "format", "")).lower()
    if any(enc.startswith(e) for e in _DEPTH_ENCODINGS) or "compresseddepth" in enc:
        images = sorted(
            {c.topic for c in conns if c.msgtype in (IMAGE, COMPRESSED) and c.topic != conn.topic}
        )
        raise UserError(
            f"{conn.topic} holds depth images ({enc}), not colour: name the colour topic with "
            f"--color-topic (other image topics: {', '.join(images) or 'none'})",
            path=path,
        )


def _first(reader: Any, conns: list[Any], topic: str) -> Any | None:
    """The first message of ``topic`` (None if the bag has none)."""
    mine = [c for c in conns if c.topic == topic]
    if not mine:
        return None
    for conn, _, raw in reader.messages(connections=mine):
        return reader.deserialize(raw, conn.msgtype)
    return None


def _info_topic(conns: list[Any], image_topic: str) -> str | None:
    """The CameraInfo topic of an image topic: in its namespace or a parent's."""
    infos = {c.topic for c in conns if c.msgtype == CAMERA_INFO}
    parts = image_topic.rstrip("/").split("/")
    for k in range(len(parts) - 1, 0, -1):
        ns = "/".join(parts[:k])
        for name in (f"{ns}/camera_info", f"{ns}/info/camera_info"):
            if name in infos:
                return name
    return None


def _camera(path: Path, info: Any, name: str, topic: str) -> Camera | None:
    """The camera a CameraInfo describes (None when its K is all zero: not calibrated)."""

    def field(*names: str) -> Any:
        for n in names:
            if hasattr(info, n):
                return getattr(info, n)
        raise UserError(f"{topic}: CameraInfo without {names[0]}", path=path)

    K = np.asarray(field("K", "k"), np.float64).reshape(3, 3)
    D = np.asarray(field("D", "d"), np.float64).reshape(-1)
    model = str(getattr(info, "distortion_model", "")).strip().lower()
    if model not in _OPENCV_MODELS and np.any(D != 0):
        raise UserError(
            f"{topic}: distortion model {model!r} is not OpenCV's (plumb_bob, "
            "rational_polynomial): rectify the images or calibrate the camera",
            path=path,
        )
    if not K[0, 0] > 0 or not K[1, 1] > 0:
        return None
    if len(D) < 4:
        D = np.concatenate([D, np.zeros(5 - len(D))])
    w, h = int(info.width), int(info.height)
    if model == "inverse brown conrady" and np.any(D != 0):
        D = forward_brown_conrady(K, D[:5], w, h)
    return Camera(name, w, h, K, D)


def _calibration(
    path: Path, reader: Any, conns: list[Any], colour_conn: Any, depth_conn: Any | None
) -> tuple[Calibration | None, str | None]:
    """The cameras, and why depth is left out when it cannot be put on the colour grid."""
    colour_info_topic = _info_topic(conns, colour_conn.topic)
    if colour_info_topic is None:
        return None, None
    colour_info = _first(reader, conns, colour_info_topic)
    if colour_info is None:
        return None, None
    colour = _camera(path, colour_info, "colour", colour_info_topic)
    if colour is None:
        return None, None  # not calibrated: the rig's own intrinsics serve
    origin = f"CameraInfo {colour_info_topic}"
    if depth_conn is None:
        return Calibration(colour, None, origin), None
    depth_info_topic = _info_topic(conns, depth_conn.topic)
    depth_info = _first(reader, conns, depth_info_topic) if depth_info_topic else None
    unit = _depth_unit_mm(reader, conns, depth_conn.topic)
    if depth_info is None or depth_info_topic == colour_info_topic:
        # No calibration of its own: taken as drawn on the colour grid already.
        return Calibration(colour, DepthGeometry(colour, None, unit), origin), None
    depth_cam = _camera(path, depth_info, "depth", depth_info_topic)  # type: ignore[arg-type]
    if depth_cam is None:
        return Calibration(colour, None, origin), (
            f"depth left out: its CameraInfo {depth_info_topic} carries no intrinsics"
        )
    origin += f" and {depth_info_topic}"
    same_frame = _frame_id(colour_info) == _frame_id(depth_info) and _frame_id(colour_info)
    if _is_registered_name(depth_conn.topic) or _same_camera(colour, depth_cam) or same_frame:
        return Calibration(colour, DepthGeometry(depth_cam, None, unit), origin), None
    c_T_d = _realsense_extrinsics(reader, conns, colour_conn.topic, depth_conn.topic)
    if c_T_d is None:
        c_T_d = _tf_extrinsics(reader, conns, _frame_id(colour_info), _frame_id(depth_info))
    if c_T_d is None:
        return Calibration(colour, None, origin), (
            f"depth left out: {depth_conn.topic} is another camera's ({depth_info_topic}) and "
            "the bag holds no transform between the two (RealSense tf/<n>, /tf_static); record "
            "depth aligned to colour"
        )
    return Calibration(colour, DepthGeometry(depth_cam, c_T_d, unit), origin), None


def _frame_id(info: Any) -> str:
    return str(getattr(getattr(info, "header", None), "frame_id", "") or "").lstrip("/")


def _same_camera(a: Camera, b: Camera) -> bool:
    return a.size == b.size and bool(np.allclose(a.K, b.K, rtol=1e-6))


def _stream_ns(topic: str) -> str:
    """A RealSense stream's namespace (``/device_0/sensor_1/Color_0``) of one of its topics."""
    parts = topic.split("/")
    return "/".join(parts[:4]) if len(parts) >= 4 and parts[1].startswith("device_") else ""


def _depth_unit_mm(reader: Any, conns: list[Any], depth_topic: str) -> float:
    """Millimetres per unit of 16-bit depth: RealSense's Depth Units option, else ROS's mm."""
    ns = _stream_ns(depth_topic)
    if ns:
        sensor = "/".join(ns.split("/")[:3])
        # librealsense names the option with a space, or (file version 3 on) an underscore.
        for name in ("Depth_Units", "Depth Units"):
            msg = _first(reader, conns, f"{sensor}/option/{name}/value")
            if msg is not None and float(msg.data) > 0:
                return float(msg.data) * 1000.0
    return 1.0


def _realsense_extrinsics(
    reader: Any, conns: list[Any], colour_topic: str, depth_topic: str
) -> np.ndarray | None:
    """colour_T_depth (mm) from RealSense's ``<stream>/tf/<group>``: librealsense writes
    each stream's extrinsics *from* the device's reference stream of that group *to* the
    stream (metres), so the depth stream, usually the reference, has the identity."""
    c_ns, d_ns = _stream_ns(colour_topic), _stream_ns(depth_topic)
    if not c_ns or not d_ns:
        return None
    groups = [
        {c.topic.rsplit("/", 1)[1] for c in conns if c.topic.startswith(f"{ns}/tf/")}
        for ns in (c_ns, d_ns)
    ]
    shared = sorted(groups[0] & groups[1])
    if not shared:
        return None
    stream_T_ref = []
    for ns in (c_ns, d_ns):
        msg = _first(reader, conns, f"{ns}/tf/{shared[0]}")
        if msg is None:
            return None
        stream_T_ref.append(_transform_msg(msg))
    return stream_T_ref[0] @ np.linalg.inv(stream_T_ref[1])


def _transform_msg(msg: Any) -> np.ndarray:
    """A geometry_msgs/Transform as 4x4 (mm)."""
    q, t = msg.rotation, msg.translation
    R = quaternion_matrix(q.x, q.y, q.z, q.w)
    return transform(R, np.array([t.x, t.y, t.z]) * 1000.0)


def _tf_extrinsics(
    reader: Any, conns: list[Any], colour_frame: str, depth_frame: str
) -> np.ndarray | None:
    """colour_T_depth (mm) from the static transforms between the two camera frames."""
    if not colour_frame or not depth_frame:
        return None
    parent: dict[str, tuple[str, np.ndarray]] = {}
    tf = [c for c in conns if c.topic in ("/tf_static", "tf_static")]
    if not tf:
        return None  # (no connections would mean every message to rosbags)
    for conn, _, raw in reader.messages(connections=tf):
        msg = reader.deserialize(raw, conn.msgtype)
        for ts in msg.transforms:
            child = ts.child_frame_id.lstrip("/")
            parent[child] = (ts.header.frame_id.lstrip("/"), _transform_msg(ts.transform))

    def root_T(frame: str) -> tuple[str, np.ndarray]:
        T = np.eye(4)
        seen = set()
        while frame in parent and frame not in seen:
            seen.add(frame)
            up, p_T_c = parent[frame]
            T = p_T_c @ T
            frame = up
        return frame, T

    r_c, root_T_colour = root_T(colour_frame)
    r_d, root_T_depth = root_T(depth_frame)
    if r_c != r_d:
        return None
    return np.linalg.inv(root_T_colour) @ root_T_depth


class _BagRecording(Recording):
    def decode(self, indices: Sequence[int], *, depth: bool) -> Iterator[Decoded]:
        depth_wanted: dict[int, list[int]] = {}
        if depth and "depth" in self.streams:
            for i in indices:
                d = self.depth_for[i]
                if d is not None:
                    depth_wanted.setdefault(d, []).append(i)
        yield from join_depth(self._events(set(indices), depth_wanted), depth_wanted)

    def _events(
        self, wanted: set[int], depth_wanted: dict[int, list[int]]
    ) -> Iterator[tuple[str, int, Decoded | np.ndarray | str]]:
        colour_topic = self.streams["colour"]
        topics = {colour_topic, self.streams.get("depth")} if depth_wanted else {colour_topic}
        reader = _reader(self.path)
        try:
            conns = [c for c in reader.connections if c.topic in topics]
            ci = di = 0
            for conn, _, raw in reader.messages(connections=conns):
                if conn.topic == colour_topic:
                    if ci in wanted:
                        yield "colour", ci, _decode_colour(reader, conn, raw)
                    ci += 1
                else:
                    if di in depth_wanted:
                        yield "depth", di, _decode_depth(reader, conn, raw, self)
                    di += 1
        finally:
            reader.close()


def _decode_colour(reader: Any, conn: Any, raw: Any) -> Decoded:
    try:
        msg = reader.deserialize(raw, conn.msgtype)
    except Exception:
        return Decoded(-1, None, None, "the message cannot be read (damaged)")
    img, problem = image_of(msg, conn.msgtype)
    return Decoded(-1, img, None, problem)


def _decode_depth(reader: Any, conn: Any, raw: Any, rec: Recording) -> np.ndarray | str:
    try:
        msg = reader.deserialize(raw, conn.msgtype)
    except Exception:
        return "the message cannot be read (damaged)"
    img, problem = image_of(msg, conn.msgtype)
    if problem is not None or img is None:
        return problem or "no image"
    assert rec.calibration is None or rec.calibration.depth is not None
    unit = rec.calibration.depth.unit_mm if rec.calibration and rec.calibration.depth else 1.0
    if img.dtype == np.uint16 and img.ndim == 2:
        mm = img.astype(np.float64) * unit
        mm[img == 0] = np.nan
        return mm
    if img.dtype == np.float32 and img.ndim == 2:
        mm = img.astype(np.float64) * 1000.0  # 32FC1 is metres (REP 118)
        mm[~np.isfinite(mm) | (mm <= 0)] = np.nan
        return mm
    return f"depth encoding {getattr(msg, 'encoding', '?')!r} is not 16UC1, mono16 or 32FC1"


READERS = (
    RecorderReader(
        "ROS bag",
        (".bag", ".mcap", ".db3", "a ROS 2 bag folder"),
        lambda path, _: is_bag(path),
        lambda path, o: open_bag(
            path,
            color_topic=o.color_topic,
            depth_topic=o.depth_topic,
            depth=o.depth,
            tolerance_s=o.tolerance_s,
        ),
        order=10,
    ),
)
