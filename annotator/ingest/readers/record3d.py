"""Record3D's ``.r3d`` exports (iPhone / iPad LiDAR): a zip archive.

``metadata`` (JSON) gives the colour size ``w`` x ``h``, the depth size ``dw`` x ``dh``,
``K`` (9 floats, column-major, for the colour size), ``fps`` and, in newer exports,
``frameTimestamps`` (s). ``rgbd/<i>.jpg`` is frame i's colour image and ``rgbd/<i>.depth``
its depth: ``dw * dh`` float32 metres compressed with LZFSE (0 or NaN = none);
``rgbd/<i>.conf``, when there, ARKit's confidence of it (LZFSE, a byte a pixel: 0 low, 1
medium, 2 high), and depth of low confidence is left out. The depth
map is ARKit's, of the same camera as the colour image at a lower resolution: its
intrinsics are the colour ones scaled to its size, and it is redrawn on the colour grid.

LZFSE needs the ``lzfse`` package (a wheel, no compiler); without it ``.r3d`` files are
refused in one line saying so.
"""

from __future__ import annotations

import json
import re
import zipfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.ingest.readers import RecorderReader
from annotator.ingest.recording import (
    Calibration,
    Decoded,
    DepthGeometry,
    Recording,
    check_calibration,
)
from annotator.io.images import native_stderr_hidden

_FRAME = re.compile(r"^rgbd/(\d+)\.(jpg|jpeg|png)$", re.I)


def is_record3d(path: Path) -> bool:
    """Whether ``path`` is a Record3D export (``.r3d``)."""
    return path.is_file() and path.suffix.lower() == ".r3d"


def lzfse_module(path: Path) -> Any:
    """The LZFSE decoder (a UserError naming the file and the package when it is not
    installed)."""
    try:
        import lzfse
    except ImportError:
        raise UserError(
            "its depth is LZFSE-compressed and the `lzfse` package is not installed "
            "(pip install lzfse), or give --no-depth",
            path=path,
        ) from None
    return lzfse


def scaled(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """``K`` for the same view resampled by ``sx`` x ``sy`` (pixel centres kept).

    >>> scaled(np.array([[100.0, 0, 49.5], [0, 100.0, 29.5], [0, 0, 1]]), 0.5, 0.5)[:2].tolist()
    [[50.0, 0.0, 24.5], [0.0, 50.0, 14.5]]
    """
    out = np.array(K, np.float64)
    out[0, 0] *= sx
    out[1, 1] *= sy
    out[0, 2] = (out[0, 2] + 0.5) * sx - 0.5
    out[1, 2] = (out[1, 2] + 0.5) * sy - 0.5
    return out


@dataclass
class _Record3D(Recording):
    names: list[str] = field(default_factory=list)  # each frame's rgbd/<i>.jpg
    depth_size: tuple[int, int] = (0, 0)

    def decode(self, indices: Sequence[int], *, depth: bool) -> Iterator[Decoded]:
        decoder = lzfse_module(self.path) if depth and "depth" in self.streams else None
        with zipfile.ZipFile(self.path) as archive:
            for i in indices:
                yield self._frame(archive, i, decoder)

    def _frame(self, archive: zipfile.ZipFile, i: int, decoder: Any | None) -> Decoded:
        name = self.names[i]
        try:
            data = archive.read(name)
        except (zipfile.BadZipFile, OSError, EOFError) as exc:
            return Decoded(i, None, None, f"{name} is damaged ({exc})")
        if data[:2] == b"\xff\xd8" and not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
            return Decoded(i, None, None, f"{name} is a truncated JPEG (decoded partly)")
        with native_stderr_hidden():
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            return Decoded(i, None, None, f"{name} fails to decode")
        if decoder is None:
            return Decoded(i, img)
        depth_name = name.rsplit(".", 1)[0] + ".depth"
        try:
            raw = decoder.decompress(archive.read(depth_name))
        except KeyError:
            return Decoded(i, None, None, f"{depth_name} is missing")
        except Exception as exc:  # zip CRC errors and LZFSE's own
            return Decoded(i, None, None, f"{depth_name} is damaged ({exc})")
        dw, dh = self.depth_size
        if len(raw) != dw * dh * 4:
            return Decoded(
                i, None, None, f"{depth_name} holds {len(raw)} bytes, {dw * dh * 4} expected"
            )
        mm = np.frombuffer(raw, "<f4").reshape(dh, dw).astype(np.float64) * 1000.0
        mm[~np.isfinite(mm) | (mm <= 0)] = np.nan
        low = self._low_confidence(archive, name.rsplit(".", 1)[0] + ".conf", decoder)
        if low is not None:
            mm[low] = np.nan
        return Decoded(i, img, mm)

    def _low_confidence(
        self, archive: zipfile.ZipFile, name: str, decoder: Any
    ) -> np.ndarray | None:
        """Where ARKit marks its depth of low confidence (``rgbd/<i>.conf``, LZFSE, one byte
        a pixel: 0 low, 1 medium, 2 high), or None without a usable confidence map."""
        try:
            raw = decoder.decompress(archive.read(name))
        except Exception:  # none (older exports), or damaged: the depth stands alone
            return None
        dw, dh = self.depth_size
        if len(raw) != dw * dh:
            return None
        return np.frombuffer(raw, np.uint8).reshape(dh, dw) == 0


def open_record3d(path: Path, *, depth: bool) -> Recording:
    """The export's frames, their depth and the camera (module docstring).

    Raises:
        UserError: not a zip archive, no metadata or no frames, depth wanted without the
            ``lzfse`` package.
    """
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
            meta = json.loads(archive.read("metadata"))
    except (zipfile.BadZipFile, OSError, EOFError) as exc:
        raise UserError(f"not a readable Record3D export ({exc})", path=path) from None
    except KeyError:
        raise UserError("not a Record3D export (no metadata in the archive)", path=path) from None
    except ValueError as exc:
        raise UserError(f"its metadata is not JSON ({exc})", path=path) from None
    frames = sorted(
        ((int(m.group(1)), n) for n in names if (m := _FRAME.match(n))), key=lambda f: f[0]
    )
    if not frames:
        raise UserError("holds no rgbd/<i>.jpg frame", path=path)
    try:
        w, h = int(meta["w"]), int(meta["h"])
        K = np.asarray(meta["K"], np.float64).reshape(3, 3).T  # column-major
        dw, dh = int(meta.get("dw", 0)), int(meta.get("dh", 0))
        fps = float(meta.get("fps", 0) or 0)
        stamps = meta.get("frameTimestamps") or []
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"its metadata lacks the camera ({exc})", path=path) from None
    stamps = _stamps(stamps, path)
    colour = Camera("colour", w, h, K, np.zeros(5))
    check_calibration(Calibration(colour, None, "metadata K"), path)  # before it is scaled
    has_depth = depth and dw > 0 and dh > 0 and any(n.endswith(".depth") for n in names)
    geometry = None
    if has_depth:
        lzfse_module(path)
        depth_cam = Camera("depth", dw, dh, scaled(K, dw / w, dh / h), np.zeros(5))
        geometry = DepthGeometry(depth_cam, np.eye(4), 1.0)
    times: list[float | None] = []
    for k, _ in frames:
        if k < len(stamps):
            times.append(stamps[k])
        else:
            times.append(k / fps if fps > 0 else None)
    return _Record3D(
        path=path,
        kind="Record3D export",
        times=times,
        labels=[n for _, n in frames],
        depth_for=[i if has_depth else None for i in range(len(frames))],
        streams={"colour": "rgbd/*.jpg", **({"depth": "rgbd/*.depth"} if has_depth else {})},
        calibration=Calibration(colour, geometry, "metadata K"),
        names=[n for _, n in frames],
        depth_size=(dw, dh),
    )


def _stamps(stamps: object, path: Path) -> list[float]:
    """The metadata's ``frameTimestamps``: a list of finite numbers (seconds), or a one-line
    refusal naming what is there instead."""
    if not isinstance(stamps, list):
        raise UserError(
            f"its metadata's frameTimestamps is a {type(stamps).__name__}, not a list of times",
            path=path,
        )
    out: list[float] = []
    for k, t in enumerate(stamps):
        if isinstance(t, bool) or not isinstance(t, int | float) or not np.isfinite(t):
            raise UserError(
                f"its metadata's frameTimestamps[{k}] is {t!r}, not a time in seconds", path=path
            )
        out.append(float(t))
    return out


READERS = (
    RecorderReader(
        "Record3D export",
        (".r3d",),
        lambda path, _: is_record3d(path),
        lambda path, o: open_record3d(path, depth=o.depth),
        order=20,
    ),
)
