"""Writing an ingested sequence: each frame's images as the dataset stores them, and
``frames.json`` (FORMAT.md, sequences), into a scene folder that is put in place whole.

Colour images are written as PNG, colour kept (an alpha channel dropped), 8 or 16 bits as
they came; grey stays grey. Depth comes in millimetres (NaN = no measurement) and is
written at the rig's ``rig.depth.scale``. Frames are named ``000000``, ``000001``... in the
order kept.

The scene folder is built in a temporary sibling and renamed into place at the end
(:func:`annotator.io.atomic.atomic_folder`): an interrupted ingest leaves nothing behind
(the next run removes its remains), and a scene already there is replaced only when asked
and only if ingest wrote it (its frames.json says so) and no reviewer has decided on it. A
killed ingest's temporary folder is swept by the next ingest into the same dataset
(:func:`sweep_abandoned`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from annotator.dataset.model import FRAMES_DIR, DepthSpec
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.io.atomic import remove_if_abandoned
from annotator.io.documents import read_json
from annotator.io.images import NO_RETURN, encode_depth, write_png

#: The file ingest writes beside a sequence's frames.
FRAMES_FILE = "frames.json"
WRITTEN_BY = "annotator ingest"
#: The longest scene id (bytes): the folder's temporary sibling ``.<id>.<random>`` must fit
#: a file name's 255 bytes too.
MAX_SCENE_BYTES = 200


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
    if len(scene_id.encode()) > MAX_SCENE_BYTES:
        raise UserError(
            f"--scene is {len(scene_id.encode())} bytes long; a scene id may have at most "
            f"{MAX_SCENE_BYTES} (a folder name, and its temporary sibling's, must fit the "
            "file system's 255)"
        )


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


def check_depth_range(
    depth_mm: np.ndarray, spec: DepthSpec, unit_mm: float, option: str, where: Path | str
) -> None:
    """Refuse depth that the rig's ``rig.depth.scale`` cannot store: all of a frame's
    measurements below one unit, or most of them beyond 65534 units (a wrong unit, such as
    ``--depth-scale 1000`` for millimetres), in one line naming ``option`` and the range of
    the source's values (in its own units, ``unit_mm`` mm each)."""
    valid = depth_mm[np.isfinite(depth_mm) & (depth_mm > 0)]
    if not valid.size:
        return
    units = np.round(valid / spec.scale)  # as encode_depth rounds them
    low = units < 1
    high = units >= NO_RETURN
    if low.all() or high.mean() > 0.5:
        lo, hi = float(valid.min()), float(valid.max())
        raw_lo, raw_hi = lo / unit_mm, hi / unit_mm
        raise UserError(
            f"{option}: the depth values seen, {raw_lo:g}..{raw_hi:g}, become {lo:g}..{hi:g} "
            f"mm, which rig.depth.scale {spec.scale:g} mm cannot store ({spec.scale:g}.."
            f"{spec.scale * (NO_RETURN - 1):g} mm): give the millimetres per unit of the "
            "source's depth",
            path=where,
        )


def sweep_abandoned(scenes: Path) -> list[Path]:
    """Remove the temporary scene folders (``.<scene>.<random>/``, marked as ours) that a
    killed ingest left in ``scenes/``, whatever scene they were for; a folder that a running
    ingest holds (its lock is taken) is left alone. The ones removed are returned."""
    removed: list[Path] = []
    try:
        entries = sorted(p for p in scenes.iterdir() if p.name.startswith("."))
    except OSError:
        return removed
    for cand in entries:
        if not cand.is_dir() or cand.is_symlink():
            continue
        scene = cand.name[1:].rsplit(".", 1)[0]
        if scene and remove_if_abandoned(cand, restore=scenes / scene):
            removed.append(cand)
    return removed


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
