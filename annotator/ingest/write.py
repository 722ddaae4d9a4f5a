"""Writing an ingested sequence: each frame's images as the dataset stores them, and
``frames.json`` (FORMAT.md, sequences), into a scene folder that is put in place whole.

Colour images are written as PNG, colour kept (an alpha channel dropped), 8 or 16 bits as
they came; grey stays grey. Depth images (uint16, ``depth_scale`` mm per unit, 0 = no
measurement) are converted to the rig's ``rig.depth.scale``. Frames are named ``000000``,
``000001``... in the order kept.

The scene folder is built in a temporary sibling and renamed into place at the end
(:func:`annotator.io.atomic.atomic_folder`): an interrupted ingest leaves nothing behind
(the next run removes its remains), and a scene already there is replaced only when asked
and only if ingest wrote it (its frames.json says so) and no reviewer has decided on it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from annotator.dataset.model import FRAMES_DIR, DepthSpec
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.io.documents import read_json
from annotator.io.images import encode_depth, read_image, write_png

#: The file ingest writes beside a sequence's frames.
FRAMES_FILE = "frames.json"
WRITTEN_BY = "annotator ingest"


def frame_name(k: int) -> str:
    """The folder of the ``k``-th frame written: ``000000``, ``000001``..."""
    return f"{k:06d}"


def check_scene_id(scene_id: str) -> None:
    """A scene id ingest may write: a plain folder name (no ``/``, not hidden, not ``..``)."""
    if (
        not scene_id
        or scene_id.startswith(".")
        or any(c in scene_id for c in "/\\\0")
        or scene_id.strip() != scene_id
    ):
        raise UserError(f"--scene must be a plain folder name, not {scene_id!r}")


def check_replaceable(folder: Path, *, overwrite: bool) -> None:
    """Raise a one-line UserError unless ingest may write the scene ``folder``: it does not
    exist (or is empty), or ``overwrite`` and ingest wrote it and it holds no review.json."""
    if not folder.exists() and not folder.is_symlink():
        return
    if not folder.is_dir():
        raise UserError("exists and is not a folder", path=folder)
    if not any(folder.iterdir()):
        return
    if not overwrite:
        raise UserError(
            "the scene exists (use --overwrite to replace a scene that ingest wrote)",
            path=folder,
        )
    mark = folder / FRAMES_FILE
    doc = read_json(mark) if mark.is_file() else None
    if not isinstance(doc, dict) or doc.get("written_by") != WRITTEN_BY:
        raise UserError(
            f"--overwrite replaces only a scene that `{WRITTEN_BY}` wrote (its {FRAMES_FILE} "
            "says so); remove it yourself or choose another --scene",
            path=folder,
        )
    review = folder / "review.json"
    if review.exists():
        raise UserError(
            "holds a reviewer's decisions: remove it yourself before ingesting the scene again",
            path=review,
        )


def stored_colour(img: np.ndarray) -> np.ndarray:
    """The image as the dataset stores it: grey or BGR (an alpha channel dropped), 8 or 16
    bits as it came (other types clipped to 8 bits)."""
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    elif img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.dtype not in (np.uint8, np.uint16):
        img = np.clip(img, 0, 255).astype(np.uint8)
    return img


def check_size(
    img: np.ndarray, camera: Camera, where: Path | str, first: Any, *, hint: str = ""
) -> None:
    """Refuse an image whose size is not the rig camera's (ingest does not resize) in one
    line naming it (``where``: the file, or ``video, frame i``); ``first`` (the first
    frame's ``(size, where)``, or None) tells frames of different sizes apart."""
    h, w = img.shape[:2]
    if (w, h) == camera.size:
        return
    cw, ch = camera.size
    if first is not None and first[0] != (w, h):
        (fw, fh), was = first
        raise UserError(
            f"frames of different sizes: this one is {w}x{h}, {was} is {fw}x{fh} (camera "
            f"{camera.name} is {cw}x{ch})",
            path=where,
        )
    raise UserError(
        f"image is {w}x{h} but camera {camera.name} in dataset.yaml is {cw}x{ch}: ingest "
        f"does not resize ({hint or 'record at the calibrated resolution'})",
        path=where,
    )


def read_source_depth(path: Path, camera: Camera, scale_mm: float) -> np.ndarray:
    """A source depth image in mm (NaN = no measurement): uint16, single channel, of the
    camera's size, ``scale_mm`` mm per unit."""
    raw = read_image(path)
    if raw.ndim == 3 and raw.shape[2] == 1:
        raw = raw[..., 0]
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise UserError(
            f"depth image must be single-channel uint16, got {raw.dtype} {raw.shape}", path=path
        )
    check_size(raw, camera, path, None, hint="record depth aligned to the colour images")
    mm = raw.astype(np.float64) * scale_mm
    mm[raw == 0] = np.nan
    return mm


def write_frame(
    folder: Path,
    camera: Camera,
    colour: np.ndarray,
    depth_mm: np.ndarray | None,
    depth_spec: DepthSpec | None,
) -> None:
    """One frame's folder: ``<camera>.png`` and, with depth, ``depth.png`` at the rig's
    depth scale."""
    write_png(folder / f"{camera.name}.png", stored_colour(colour))
    if depth_mm is not None:
        assert depth_spec is not None  # checked before anything is read
        write_png(folder / "depth.png", encode_depth(depth_mm, depth_spec.scale))


def frames_folder(scene: Path, k: int) -> Path:
    """``<scene>/frames/<frame k>/``."""
    return scene / FRAMES_DIR / frame_name(k)
