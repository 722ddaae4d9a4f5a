"""ROS image messages as pixels: ``sensor_msgs/Image`` in the encodings cameras publish
(and librealsense records: ``mono16`` depth, ``8UC1``/``16UC1`` infrared, ``yuv422`` for
UYVY, ``YUYV``) and ``sensor_msgs/CompressedImage`` (JPEG, PNG), with what makes one unusable
said rather than decoded half: a message cut short, a JPEG without its end marker.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from annotator.io.images import native_stderr_hidden

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"


def image_of(msg: Any, msgtype: str) -> tuple[np.ndarray | None, str | None]:
    """A sensor_msgs Image or CompressedImage as BGR / grey / uint16 / float32, or why not."""
    if msgtype == COMPRESSED:
        data = np.asarray(msg.data, np.uint8)
        if data.size == 0:
            return None, "an empty compressed image"
        fmt = str(getattr(msg, "format", "")).lower()
        if "compresseddepth" in fmt:
            return _compressed_depth(data, fmt)
        if ("jpeg" in fmt or data[:2].tobytes() == b"\xff\xd8") and not _jpeg_complete(data):
            return None, "a truncated JPEG (decoded partly)"
        with native_stderr_hidden():
            img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        if img is None:
            return None, "the compressed image fails to decode"
        return img, None
    enc = str(msg.encoding).lower()
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, np.uint8)
    if h <= 0 or w <= 0 or step <= 0:
        return None, "an image of no size"
    if data.size < h * step:
        return None, f"holds {data.size} bytes where {h * step} are expected (cut short)"
    rows = data[: h * step].reshape(h, step)
    big = bool(getattr(msg, "is_bigendian", 0))
    if enc in ("rgb8", "bgr8", "rgba8", "bgra8", "8uc3", "8uc4"):
        ch = 4 if enc in ("rgba8", "bgra8", "8uc4") else 3
        img = rows[:, : w * ch].reshape(h, w, ch)
        if enc == "rgb8":
            return cv2.cvtColor(img, cv2.COLOR_RGB2BGR), None
        if enc == "rgba8":
            return cv2.cvtColor(img, cv2.COLOR_RGBA2BGR), None
        if ch == 4:
            return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR), None
        return np.ascontiguousarray(img), None
    if enc in ("mono8", "8uc1"):
        return np.ascontiguousarray(rows[:, :w]), None
    if enc in ("mono16", "16uc1", "z16"):
        img16 = rows[:, : w * 2].copy().view(">u2" if big else "<u2").reshape(h, w)
        return img16.astype(np.uint16), None
    if enc == "32fc1":
        f32 = rows[:, : w * 4].copy().view(">f4" if big else "<f4").reshape(h, w)
        return f32.astype(np.float32), None
    if enc in ("yuv422", "uyvy"):
        return cv2.cvtColor(rows[:, : w * 2].reshape(h, w, 2), cv2.COLOR_YUV2BGR_UYVY), None
    if enc in ("yuyv", "yuv422_yuy2"):
        return cv2.cvtColor(rows[:, : w * 2].reshape(h, w, 2), cv2.COLOR_YUV2BGR_YUYV), None
    bayer = {
        "bayer_rggb8": cv2.COLOR_BayerBG2BGR,
        "bayer_bggr8": cv2.COLOR_BayerRG2BGR,
        "bayer_gbrg8": cv2.COLOR_BayerGR2BGR,
        "bayer_grbg8": cv2.COLOR_BayerGB2BGR,
    }
    if enc in bayer:
        # OpenCV names Bayer patterns by the second row's first two pixels.
        return cv2.cvtColor(np.ascontiguousarray(rows[:, :w]), bayer[enc]), None
    return None, f"image encoding {msg.encoding!r} is not one ingest reads"


def _jpeg_complete(data: np.ndarray) -> bool:
    """Whether a JPEG's bytes end with its end-of-image marker (trailing padding allowed)."""
    tail = data[-64:].tobytes().rstrip(b"\x00")
    return tail.endswith(b"\xff\xd9")


def _compressed_depth(data: np.ndarray, fmt: str) -> tuple[np.ndarray | None, str | None]:
    """image_transport's ``compressedDepth``: a 12-byte header (the format, then two floats
    quantising 32-bit depth) and a PNG. 16UC1 is the depth as it was; 32FC1 is stored as
    quantised inverse depth, ``depth = a / (v - b)`` metres for v > 0."""
    if data.size <= 12:
        return None, "a compressedDepth image without its PNG"
    with native_stderr_hidden():
        img = cv2.imdecode(data[12:], cv2.IMREAD_UNCHANGED)
    if img is None or img.dtype != np.uint16 or img.ndim != 2:
        return None, "the compressedDepth image fails to decode as a 16-bit PNG"
    if fmt.startswith("32fc1"):
        a, b = np.frombuffer(data[4:12].tobytes(), "<f4")
        out = np.full(img.shape, np.nan, np.float32)
        ok = img > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            out[ok] = a / (img[ok].astype(np.float32) - b)
        return out, None
    return img, None
