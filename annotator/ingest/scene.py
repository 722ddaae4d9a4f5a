"""Ingesting one recorded sequence into a moving rig's dataset (``annotator ingest``).

Two passes over the source: the first reads every candidate frame (every ``every``-th),
checks its size against the rig camera's and measures its sharpness (:mod:`.selection`);
the second reads the frames kept again and writes them with their depth (:mod:`.write`),
then ``frames.json``. Nothing is written before the first pass has found the input good,
and the scene folder appears whole or not at all.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from annotator.dataset import Dataset, load_dataset
from annotator.dataset.model import SCENES_DIR
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.ingest.selection import BLUR_THRESHOLD, candidates, select, sharpness
from annotator.ingest.sources import PAIR_TOLERANCE_S, Source, SourceFrame, open_source
from annotator.ingest.write import (
    FRAMES_FILE,
    WRITTEN_BY,
    check_replaceable,
    check_scene_id,
    check_size,
    frame_name,
    frames_folder,
    read_source_depth,
    write_frame,
)
from annotator.io.atomic import atomic_folder, write_json
from annotator.runner.report import progress_bar

__all__ = ["IngestSummary", "ingest_scene"]


@dataclass(frozen=True)
class IngestSummary:
    """What :func:`ingest_scene` did (``--json`` prints :meth:`to_json`).

    Attributes:
        scene: The scene folder written.
        source: The video or image folder read.
        kind: ``video`` or ``image folder``.
        camera: The rig camera the images are of.
        source_frames: Frames in the source.
        candidates: Frames looked at (every ``every``-th).
        written: Frames written.
        blurred: Source labels of the candidates dropped as too blurred.
        depth: Whether depth maps were written.
        every: The stride.
        blur_threshold: The sharpness threshold (times the running median).
    """

    scene: str
    source: str
    kind: str
    camera: str
    source_frames: int
    candidates: int
    written: int
    blurred: list[str | int] = field(default_factory=list)
    depth: bool = False
    every: int = 1
    blur_threshold: float = BLUR_THRESHOLD

    def to_json(self) -> dict[str, Any]:
        """The summary as plain JSON values."""
        return asdict(self)

    def line(self) -> str:
        """The one line the command prints."""
        stride = "every frame" if self.every == 1 else f"one frame in {self.every}"
        return (
            f"ingest: {self.written} frames of {self.source} ({self.kind}, {self.source_frames} "
            f"frames, {stride}) written to {self.scene}; {len(self.blurred)} dropped as blurred "
            f"(sharpness below {self.blur_threshold:g} x the running median); depth: "
            f"{'yes' if self.depth else 'no'}"
        )


def ingest_scene(
    dataset: str | Path | Dataset,
    source: str | Path,
    scene_id: str,
    *,
    camera: str | None = None,
    stream: str | None = None,
    every: int = 1,
    blur_threshold: float = BLUR_THRESHOLD,
    depth: bool = True,
    depth_scale: float = 1.0,
    tolerance_s: float = PAIR_TOLERANCE_S,
    fps: float | None = None,
    overwrite: bool = False,
    quiet: bool = True,
) -> IngestSummary:
    """Write the sequence recorded in ``source`` (a video or a folder of colour and depth
    images, :mod:`annotator.ingest.sources`) as scene ``scene_id`` of a moving rig's dataset.

    Args:
        dataset: The dataset (its dataset.yaml says ``rig.moving: true``).
        source: The video file or image folder.
        scene_id: The scene to write (``scenes/<scene_id>/``).
        camera: The rig camera the images are of (needed when the rig has several).
        stream: The colour stream to take from a folder of several (``left``...; default:
            the one named like the camera).
        every: Take every ``every``-th frame of the source.
        blur_threshold: Drop a candidate whose sharpness is below this times the running
            median of its neighbours' (0 keeps every candidate).
        depth: Write the source's depth images (when it has any) as ``depth.png``.
        depth_scale: Millimetres per unit of the source's depth images (RealSense: 1).
        tolerance_s: How far apart in time a colour image and its depth partner may be.
        fps: The frame rate of an image folder whose names are frame indices (their times).
        overwrite: Replace the scene if ingest wrote it.
        quiet: No progress bars.

    Raises:
        UserError: one line naming the file, for any bad input (module :mod:`.sources`,
            sizes that are not the camera's, a dataset that is not a moving rig's...).
    """
    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    check_scene_id(scene_id)
    if every < 1:
        raise UserError(f"--every must be at least 1, got {every}")
    if not blur_threshold >= 0:
        raise UserError(f"--blur-threshold must be at least 0, got {blur_threshold}")
    if not ds.rig.moving:
        raise UserError(
            "the rig is not a moving one: ingest writes sequences into a dataset whose "
            "dataset.yaml says rig: {moving: true} (FORMAT.md, sequences)",
            path=ds.root / "dataset.yaml",
        )
    cam = _camera(ds, camera)
    folder = ds.root / SCENES_DIR / scene_id
    check_replaceable(folder, overwrite=overwrite)
    real = Path(source).resolve()
    if real == folder.resolve() or folder.resolve() in real.parents:
        raise UserError(
            "lies in the scene it would be written to; move it out of the dataset first",
            path=source,
        )
    src = open_source(
        source,
        stream=cam.name if stream is None else stream,
        depth=depth,
        tolerance_s=tolerance_s,
        fps=fps,
    )
    with_depth = depth and src.has_depth
    if with_depth:
        _check_depth_camera(ds, cam)
    chosen = [src.frames[i] for i in candidates(len(src.frames), every)]
    values = _measure(src, chosen, cam, quiet)
    selection = select([f.index for f in chosen], values, threshold=blur_threshold)
    kept = [src.frames[i] for i in selection.kept]
    if not kept:
        raise UserError("no frame is left to write (all dropped as blurred)", path=src.path)
    t0 = next((f.time_s for f in src.frames if f.time_s is not None), None)
    with atomic_folder(folder) as tmp:
        entries = _write_frames(ds, src, kept, cam, tmp, with_depth, depth_scale, quiet)
        for entry, f in zip(entries.values(), kept):
            entry["sharpness"] = round(selection.of(f.index), 3)
            entry["time_s"] = None if f.time_s is None or t0 is None else round(f.time_s - t0, 6)
        doc: dict[str, Any] = {
            "written_by": WRITTEN_BY,
            "source": str(Path(source).resolve()),
            "kind": src.describe(),
            "camera": cam.name,
            "every": every,
            "blur_threshold": blur_threshold,
            "time_origin_s": t0,
            "blurred": [src.frames[i].label for i in selection.blurred],
            "frames": entries,
        }
        write_json(tmp / FRAMES_FILE, doc)
    return IngestSummary(
        scene=str(folder),
        source=str(source),
        kind=src.describe(),
        camera=cam.name,
        source_frames=len(src.frames),
        candidates=len(chosen),
        written=len(kept),
        blurred=[src.frames[i].label for i in selection.blurred],
        depth=with_depth,
        every=every,
        blur_threshold=blur_threshold,
    )


def _camera(ds: Dataset, name: str | None) -> Camera:
    """The rig camera the images are of."""
    names = [c.name for c in ds.rig.cameras]
    if name is not None:
        if name not in names:
            raise UserError(
                f"--camera {name!r} is not a camera of the rig ({', '.join(names)})",
                path=ds.root / "dataset.yaml",
            )
        return ds.rig.camera(name)
    if len(names) > 1:
        raise UserError(
            f"the rig has several cameras ({', '.join(names)}): say which one the images are "
            "of with --camera",
            path=ds.root / "dataset.yaml",
        )
    return ds.rig.cameras[0]


def _check_depth_camera(ds: Dataset, cam: Camera) -> None:
    spec = ds.rig.depth
    if spec is None:
        raise UserError(
            "the source has depth images but the rig has no depth camera: add rig.depth "
            "(camera, scale) or give --no-depth",
            path=ds.root / "dataset.yaml",
        )
    if spec.camera != cam.name:
        raise UserError(
            f"the source's depth images are camera {cam.name}'s, but rig.depth.camera is "
            f"{spec.camera}: give --no-depth or correct rig.depth",
            path=ds.root / "dataset.yaml",
        )


def _where(src: Source, f: SourceFrame) -> Path | str:
    """How messages name a frame: its file, or the video and the frame."""
    if f.colour is not None:
        return f.colour
    return f"{src.path} (frame {f.index})"


def _measure(src: Source, frames: list[SourceFrame], cam: Camera, quiet: bool) -> list[float]:
    """Pass 1: every candidate's size checked; their sharpness."""
    values = []
    first: tuple[tuple[int, int], str] | None = None
    bar = progress_bar(len(frames), "ingest (reading)", quiet, unit="frame")
    try:
        for f, img in src.read(frames):
            check_size(img, cam, _where(src, f), first)
            if first is None:
                first = ((img.shape[1], img.shape[0]), str(f.label))
            values.append(sharpness(img))
            bar.update()
    finally:
        bar.close()
    return values


def _write_frames(
    ds: Dataset,
    src: Source,
    kept: list[SourceFrame],
    cam: Camera,
    scene: Path,
    with_depth: bool,
    depth_scale: float,
    quiet: bool,
) -> dict[str, dict[str, Any]]:
    """Pass 2: each kept frame's folder; their frames.json entries."""
    entries: dict[str, dict[str, Any]] = {}
    bar = progress_bar(len(kept), "ingest (writing)", quiet, unit="frame")
    try:
        for k, (f, img) in enumerate(src.read(kept)):
            depth_mm = None
            entry: dict[str, Any] = {"source": f.label}
            if with_depth:
                assert f.depth is not None  # every colour image has its partner
                depth_mm = read_source_depth(f.depth, cam, depth_scale)
                entry["depth_source"] = f.depth.relative_to(src.path).as_posix()
            write_frame(frames_folder(scene, k), cam, img, depth_mm, ds.rig.depth)
            entries[frame_name(k)] = entry
            bar.update()
    finally:
        bar.close()
    return entries
