"""Reading and writing image files (PNG intensity images and uint16 depth maps).

Intensity images may be 8- or 16-bit, grey or colour; they are returned as stored.
Depth maps are uint16 PNGs; ``scale`` converts units to millimetres and 0 means
"no measurement", returned as NaN.
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np

from annotator.errors import UserError
from annotator.io.atomic import write_bytes


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as stored (8/16-bit, grey or colour). Raises UserError if unreadable."""
    path = Path(path)
    if not path.is_file():
        raise UserError(_not_a_file(path, "image"), path=path)
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise UserError(f"cannot read ({exc.strerror or exc})", path=path) from None
    with native_stderr_hidden():
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise UserError("unreadable or corrupt image", path=path)
    return img


def _not_a_file(path: Path, what: str) -> str:
    """Why ``path`` is not a readable file: missing, a folder, or a link leading nowhere."""
    if path.is_dir():
        return f"is a folder, not an {what} file"
    if path.is_symlink():
        return f"is a symbolic link that leads nowhere (dangling or a loop), not an {what} file"
    return f"{what} file is missing"


_STDERR = threading.Lock()


@contextmanager
def native_stderr_hidden() -> Iterator[None]:
    """Silence what native code writes to file descriptor 2 meanwhile.

    libpng, OpenCV and FFmpeg (under ``cv2.VideoCapture``) print their own lines ("libpng error: ...", "[ WARN:0] ...") on a
    corrupt file before returning the failure that we report as one clear line. (Output of
    other threads in these few milliseconds is lost too; batch workers decode in their own
    processes.)
    """
    with _STDERR:
        sys.stderr.flush()
        saved = os.dup(2)
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, 2)
        os.close(null)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def to_gray8(img: np.ndarray) -> np.ndarray:
    """Convert an 8/16-bit grey or colour image to 8-bit grey (16-bit is scaled by 1/257)."""
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    if img.dtype == np.uint16:
        img = (img.astype(np.float32) / 257.0 + 0.5).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    return img


def write_png(path: str | Path, img: np.ndarray) -> None:
    """Encode ``img`` as PNG and write it atomically."""
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    write_bytes(path, buf.tobytes())


#: The uint16 that depth maps hold where the sensor got nothing back, as 0 (FORMAT.md).
NO_RETURN = 65535


def read_depth(path: str | Path, scale: float) -> np.ndarray:
    """Read a uint16 depth PNG as float32 millimetres, NaN where there is no measurement:
    0, and 65535 (the largest value, which sensors write where nothing came back)."""
    raw = read_image(path)
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise UserError(
            f"depth map must be single-channel uint16, got {raw.dtype} {raw.shape}", path=path
        )
    depth = raw.astype(np.float32) * np.float32(scale)
    depth[(raw == 0) | (raw == NO_RETURN)] = np.nan
    return depth


def encode_depth(depth_mm: np.ndarray, scale: float) -> np.ndarray:
    """Convert float millimetres (NaN/inf/<=0 = no measurement) to uint16 units of ``scale`` mm."""
    units = np.round(np.nan_to_num(depth_mm, nan=0.0, posinf=0.0, neginf=0.0) / scale)
    units[(units < 1) | (units >= NO_RETURN)] = 0
    return units.astype(np.uint16)
