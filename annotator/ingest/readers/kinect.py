"""Azure Kinect recordings (``k4arecorder``'s ``.mkv``; Orbbec Femto cameras in K4A mode
write the same), read with PyAV and no vendor SDK.

The Matroska file holds a ``COLOR`` track (MJPEG, NV12 or YUY2), a ``DEPTH`` track
(``b16g``: 16-bit grey, mm, 0 = none) and ``IR``/``IMU`` tracks left out here, and an
attachment ``calibration.json``. Its ``CalibrationInformation.Cameras[]`` gives each camera
(``Location`` ``CALIBRATION_CameraLocationD0`` for depth, ``..PV0`` for colour):

- ``Intrinsics.ModelParameters``: cx, cy, fx, fy, k1..k6, codx, cody, p2, p1 (p2 before
  p1), the first four as fractions of the sensor's size with (0, 0) at the top-left corner
  of the top-left pixel;
- ``Rt``: ``Rotation`` (9, row-major) and ``Translation`` (metres), from the depth camera
  (whose own Rt is the identity) into the camera;
- ``SensorWidth``/``SensorHeight``: the full sensor (colour 4096x3072; an older 16:9
  calibration, 4096x2304, is first brought to 4:3).

A recording's mode is a scaled and cropped window of the sensor: colour at width W is the
4:3 sensor scaled to W x 3W/4 and cropped to the recorded height, centred (720p: 1280x960
less 120 rows top and bottom); depth NFOV is a window of the 1024x1024 (or 2x2-binned
512x512) sensor starting at (192, 180) (binned: (96, 90)), WFOV the whole. The intrinsics
follow: scaled to the binned size, shifted by the crop, then moved half a pixel to OpenCV's
centred pixels. Colour and depth frames of one capture share their timestamp.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.ingest.readers import OpenOptions, RecorderReader
from annotator.ingest.readers.video import TrackIndex, decode_tracks, index_tracks, quiet_ffmpeg
from annotator.ingest.recording import (
    Calibration,
    Decoded,
    DepthGeometry,
    Recording,
    join_depth,
    pair_by_time,
    transform,
)

CALIBRATION_FILE = "calibration.json"
COLOUR_LOCATION = "CALIBRATION_CameraLocationPV0"
DEPTH_LOCATION = "CALIBRATION_CameraLocationD0"

#: Cameras named by their purpose only (a calibration without Location).
_BY_PURPOSE = {
    "CALIBRATION_CameraPurposeDepth": DEPTH_LOCATION,
    "CALIBRATION_CameraPurposePhotoVideo": COLOUR_LOCATION,
}
#: Depth modes by recorded size: (binned sensor size, crop offset).
_DEPTH_MODES = {
    (320, 288): ((512, 512), (96, 90)),  # NFOV 2x2 binned
    (640, 576): ((1024, 1024), (192, 180)),  # NFOV unbinned
    (512, 512): ((512, 512), (0, 0)),  # WFOV 2x2 binned
    (1024, 1024): ((1024, 1024), (0, 0)),  # WFOV unbinned, passive IR
}


def is_kinect(path: Path) -> bool:
    """Whether ``path`` is a Matroska file carrying a K4A ``calibration.json``."""
    if not (path.is_file() and path.suffix.lower() == ".mkv"):
        return False
    try:
        return _attachment(path) is not None
    except UserError:
        return False


@contextlib.contextmanager
def _container(path: Path) -> Iterator[Any]:
    """The file opened by PyAV (None where FFmpeg cannot open it), closed afterwards."""
    import av

    try:
        with quiet_ffmpeg():
            container = av.open(str(path))
    except (av.error.FFmpegError, OSError):
        yield None
        return
    try:
        yield container
    finally:
        container.close()


def has_depth_track(path: Path) -> bool:
    """Whether a Matroska file has a 16-bit grey or ``DEPTH`` video track (an Azure Kinect
    recording's, whatever else it lacks)."""
    with _container(path) as container:
        return container is not None and _tracks(container)[1] is not None


def _attachment(path: Path) -> bytes | None:
    """The bytes of the file's calibration.json attachment (None if it has none)."""
    with _container(path) as container:
        if container is None:
            return None
        stream: Any
        for stream in container.streams:
            if stream.type != "attachment":
                continue
            name = getattr(stream, "name", None) or stream.metadata.get("filename", "")
            if str(name) == CALIBRATION_FILE:
                # PyAV hands the payload over as .data; FFmpeg keeps it as the extradata.
                data = getattr(stream, "data", None)
                if data is None:
                    data = stream.codec_context.extradata
                return bytes(data) if data is not None else None
    return None


@dataclass(frozen=True)
class SensorCamera:
    """One camera of calibration.json as given: normalised intrinsics on the sensor, and its
    pose from the depth camera (4x4, mm)."""

    params: tuple[float, ...]
    sensor: tuple[int, int]
    cam_T_depth: np.ndarray


def parse_calibration(text: bytes | str, path: Path) -> dict[str, SensorCamera]:
    """calibration.json's cameras by Location (``...D0``, ``...PV0``)."""
    try:
        doc = json.loads(text)
        cams = doc["CalibrationInformation"]["Cameras"]
        out = {}
        for c in cams:
            params = tuple(float(v) for v in c["Intrinsics"]["ModelParameters"])
            if len(params) < 14:
                raise ValueError(f"{len(params)} ModelParameters where 14 are expected")
            rt = c["Rt"]
            T = transform(
                np.asarray(rt["Rotation"], float).reshape(3, 3),
                np.asarray(rt["Translation"], float) * 1000.0,
            )
            where = str(c.get("Location") or _BY_PURPOSE.get(str(c.get("Purpose")), ""))
            out[where] = SensorCamera(params, (int(c["SensorWidth"]), int(c["SensorHeight"])), T)
    except (ValueError, KeyError, TypeError, IndexError) as exc:
        raise UserError(f"its {CALIBRATION_FILE} cannot be read ({exc})", path=path) from None
    return out


def mode_camera(
    cam: SensorCamera, size: tuple[int, int], name: str, *, depth: bool, path: Path
) -> Camera:
    """The camera of a recorded mode of ``size`` (module docstring), OpenCV's convention.

    >>> sc = SensorCamera((0.5, 0.5, 0.5, 0.6, *[0.0] * 10), (4096, 3072), np.eye(4))
    >>> cam = mode_camera(sc, (1280, 720), "c", depth=False, path=Path("x"))
    >>> [round(float(v), 2) for v in (cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2])]
    [640.0, 576.0, 639.5, 359.5]
    """
    cx, cy, fx, fy = cam.params[:4]
    w, h = size
    if depth:
        if cam.sensor != (1024, 1024) or size not in _DEPTH_MODES:
            raise UserError(
                f"depth track of {w}x{h} from a {cam.sensor[0]}x{cam.sensor[1]} sensor is "
                "not an Azure Kinect depth mode",
                path=path,
            )
        (bw, bh), (ox, oy) = _DEPTH_MODES[size]
    else:
        sw, sh = cam.sensor
        if sw * 9 == sh * 16:  # an older 16:9 calibration: first brought to the 4:3 sensor
            cy = (cy * sh + (sw * 3 // 4 - sh) / 2) / (sw * 3 / 4)
            fy = fy * sh / (sw * 3 / 4)
        elif sw * 3 != sh * 4:
            raise UserError(f"colour sensor {sw}x{sh} is neither 4:3 nor 16:9", path=path)
        bw, bh = w, w * 3 // 4
        if h > bh:
            raise UserError(f"colour track of {w}x{h} is not an Azure Kinect mode", path=path)
        ox, oy = 0, (bh - h) // 2
    K = np.array(
        [
            [fx * bw, 0.0, cx * bw - ox - 0.5],
            [0.0, fy * bh, cy * bh - oy - 0.5],
            [0.0, 0.0, 1.0],
        ]
    )
    k1, k2, k3, k4, k5, k6, _codx, _cody, p2, p1 = cam.params[4:14]
    dist = np.array([k1, k2, p1, p2, k3, k4, k5, k6])
    return Camera(name, w, h, K, dist)


@dataclass
class _KinectRecording(Recording):
    colour_track: TrackIndex | None = None
    depth_track: TrackIndex | None = None

    def decode(self, indices: Sequence[int], *, depth: bool) -> Iterator[Decoded]:
        assert self.colour_track is not None
        cs = self.colour_track.stream
        wanted = {cs: set(indices)}
        tracks = {cs: self.colour_track}
        formats = {cs: "bgr24"}
        depth_wanted: dict[int, list[int]] = {}
        if depth and self.depth_track is not None:
            ds = self.depth_track.stream
            for i in indices:
                d = self.depth_for[i]
                if d is not None:
                    depth_wanted.setdefault(d, []).append(i)
            wanted[ds] = set(depth_wanted)
            tracks[ds] = self.depth_track
            formats[ds] = "gray16"

        def events() -> Iterator[tuple[str, int, Decoded | np.ndarray | str]]:
            for sid, k, pixels, problem in decode_tracks(self.path, wanted, tracks, formats):
                if sid == cs:
                    yield "colour", k, Decoded(k, pixels, None, problem)
                elif pixels is None:
                    yield "depth", k, problem or "fails to decode"
                else:
                    mm = pixels.astype(np.float64)
                    mm[pixels == 0] = np.nan
                    yield "depth", k, mm

        yield from join_depth(events(), depth_wanted)


def open_kinect(path: Path, *, depth: bool, tolerance_s: float) -> Recording:
    """The recording's colour frames, their depth partners and both cameras (module
    docstring).

    Raises:
        UserError: no colour track, an unreadable calibration.json.
    """
    import av

    raw = _attachment(path)
    if raw is None:
        raise UserError(
            f"has no {CALIBRATION_FILE} attachment (not an Azure Kinect recording)", path=path
        )
    sensors = parse_calibration(raw, path)
    with quiet_ffmpeg():
        container = av.open(str(path))
    try:
        colour_s, depth_s = _tracks(container)
        if colour_s is None:
            raise UserError("has no COLOR track (recorded with the colour camera off)", path=path)
        colour_size = (colour_s.codec_context.width, colour_s.codec_context.height)
        depth_size = (
            (depth_s.codec_context.width, depth_s.codec_context.height) if depth_s else None
        )
        # Read while the container is open: a closed one's streams are gone.
        colour_index = int(colour_s.index)
        depth_index = int(depth_s.index) if depth_s is not None else None
    finally:
        container.close()
    if COLOUR_LOCATION not in sensors:
        raise UserError(f"its {CALIBRATION_FILE} has no {COLOUR_LOCATION} camera", path=path)
    colour = mode_camera(sensors[COLOUR_LOCATION], colour_size, "colour", depth=False, path=path)
    streams = [colour_index] + ([depth_index] if depth and depth_index is not None else [])
    tracks, ended = index_tracks(path, streams)
    ctrack = tracks[colour_index]
    dtrack = tracks.get(depth_index) if depth_index is not None else None
    geometry = None
    if dtrack is not None and depth_size is not None and DEPTH_LOCATION in sensors:
        d = sensors[DEPTH_LOCATION]
        depth_cam = mode_camera(d, depth_size, "depth", depth=True, path=path)
        c_T_d = sensors[COLOUR_LOCATION].cam_T_depth @ np.linalg.inv(d.cam_T_depth)
        geometry = DepthGeometry(depth_cam, c_T_d, 1.0)
    elif dtrack is not None:
        raise UserError(f"its {CALIBRATION_FILE} has no {DEPTH_LOCATION} camera", path=path)
    times: list[float | None] = list(ctrack.times)
    pairs: list[int | None] = (
        pair_by_time(times, list(dtrack.times), tolerance_s)
        if dtrack is not None
        else [None] * len(times)
    )
    named = {"colour": f"track {colour_index} (COLOR)"}
    if dtrack is not None:
        named["depth"] = f"track {dtrack.stream} (DEPTH)"
    return _KinectRecording(
        path=path,
        kind="Azure Kinect recording",
        times=times,
        labels=list(range(len(times))),
        depth_for=pairs,
        streams=named,
        calibration=Calibration(colour, geometry, f"{CALIBRATION_FILE} attachment"),
        ended_early=ended,
        depth_times=list(dtrack.times) if dtrack is not None else [],
        colour_track=ctrack,
        depth_track=dtrack,
    )


def _tracks(container: Any) -> tuple[Any | None, Any | None]:
    """The COLOR and DEPTH video tracks: by their names, or in a file whose tracks have no
    such names, the first track that is not 16-bit grey and the first that is."""
    video = [s for s in container.streams if s.type == "video"]
    by_name = {str(s.metadata.get("title", "")).upper(): s for s in video}
    if by_name.keys() & {"COLOR", "DEPTH", "IR"}:
        # Named as k4arecorder names them: an IR track is never taken for depth.
        return by_name.get("COLOR"), by_name.get("DEPTH")
    grey16 = [s for s in video if "gray16" in str(s.codec_context.pix_fmt or "")]
    colour = next((s for s in video if s not in grey16), None)
    return colour, (grey16[0] if grey16 else None)


def _bare(path: Path, options: OpenOptions) -> Recording:
    raise UserError(
        f"has a DEPTH track but no {CALIBRATION_FILE} attachment (an Azure Kinect recording "
        "carries one), so its depth cannot be placed: pass --no-depth to ingest its colour "
        "as a plain video",
        path=path,
    )


#: An Azure Kinect recording; and an .mkv with a DEPTH track but no calibration, refused
#: when depth is asked for (read as a plain video, its depth would go without a word).
READERS = (
    RecorderReader(
        "Azure Kinect recording",
        (".mkv with calibration.json",),
        lambda path, _: is_kinect(path),
        lambda path, o: open_kinect(path, depth=o.depth, tolerance_s=o.tolerance_s),
        order=30,
    ),
    RecorderReader(
        "Azure Kinect recording without its calibration",
        (".mkv",),
        lambda path, o: o.depth and path.suffix.lower() == ".mkv" and has_depth_track(path),
        _bare,
        order=35,
    ),
)
