"""Ingesting one recorded sequence into a moving rig's dataset (``annotator ingest``).

Two passes over the source: the first decodes every candidate frame (every ``every``-th),
drops the damaged ones, checks the size against the rig camera's and measures sharpness
(:mod:`.selection`); the second decodes the frames kept again and writes them with their
depth (registered to the colour camera when the recorder did not, :mod:`.registration`),
then ``frames.json``. Nothing is written before the first pass has found the input good,
and the scene folder appears whole or not at all.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from annotator.dataset import Dataset, load_dataset
from annotator.dataset.model import SCENES_DIR
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.ingest.recording import Recording, isolated_spikes, nearest_gaps
from annotator.ingest.registration import register_depth
from annotator.ingest.rig import (
    DEFAULT_DICTIONARY,
    check_rig_matches,
    rig_from_calibration,
    write_new_dataset,
)
from annotator.ingest.selection import BLUR_THRESHOLD, candidates, select, sharpness
from annotator.ingest.sources import PAIR_TOLERANCE_S, open_recording
from annotator.ingest.write import (
    FRAMES_FILE,
    WRITTEN_BY,
    check_depth_range,
    check_replaceable,
    check_scene_id,
    check_size,
    frame_name,
    frames_folder,
    sweep_abandoned,
    write_frame,
)
from annotator.io.atomic import atomic_folder, write_json
from annotator.runner.report import progress_bar

__all__ = ["IngestSummary", "ingest_recording"]


@dataclass(frozen=True)
class IngestSummary:
    """What :func:`ingest_recording` did (``--json`` prints :meth:`to_json`).

    Attributes:
        scene: The scene folder written.
        source: The recording, video or image folder read.
        kind: ``ROS 1 bag``, ``Azure Kinect recording``, ``video``, ``image folder``...
        camera: The rig camera the images are of.
        source_frames: Colour frames in the source.
        candidates: Frames looked at (every ``every``-th).
        written: Frames written.
        blurred: Source labels of the candidates dropped as too blurred.
        dropped: The candidates dropped as unusable: ``{"frame": label, "why": ...}``
            (damaged, decoded partly, no depth partner).
        ended_early: Why the source stops before its end (None if it does not).
        notes: What else the reader said (a depth stream left out, and why).
        depth: Whether depth maps were written.
        streams: The streams read (``colour``, ``depth``: topics or tracks).
        intrinsics: Where the camera's intrinsics came from (``dataset.yaml``, or the file's
            CameraInfo / calibration.json / metadata when the rig was written from it).
        file_calibration: Where the file's own calibration was read (checked against the
            rig's; None when the file carries none).
        depth_registered: Whether depth was redrawn from its own camera onto the colour
            camera's grid.
        rig_written: Whether dataset.yaml was written from the source (``--rig-from-source``).
        every: The stride.
        blur_threshold: The sharpness threshold (times the running median).

    >>> s = IngestSummary("scenes/000000", "shots", "image folder", "left", source_frames=10,
    ...                   candidates=10, written=8, blurred=[3, 7])
    >>> s.counts()
    {'source_frames': 10, 'candidates': 10, 'written': 8, 'blurred': 2, 'dropped': 0}
    >>> s.exit_status()
    0
    """

    scene: str
    source: str
    kind: str
    camera: str
    source_frames: int
    candidates: int
    written: int
    blurred: list[str | int] = field(default_factory=list)
    dropped: list[dict[str, Any]] = field(default_factory=list)
    ended_early: str | None = None
    notes: list[str] = field(default_factory=list)
    depth: bool = False
    streams: dict[str, str] = field(default_factory=dict)
    intrinsics: str = "dataset.yaml"
    file_calibration: str | None = None
    depth_registered: bool = False
    rig_written: bool = False
    every: int = 1
    blur_threshold: float = BLUR_THRESHOLD

    def counts(self) -> dict[str, int]:
        return {
            "source_frames": self.source_frames,
            "candidates": self.candidates,
            "written": self.written,
            "blurred": len(self.blurred),
            "dropped": len(self.dropped),
        }

    def warnings(self) -> list[str]:
        return []  # what was dropped and why is in the text: it is what ingest reports

    def written_paths(self) -> list[Path]:
        return [Path(self.scene)]

    def exit_status(self) -> int:
        return 0

    def to_json(self) -> dict[str, Any]:
        """The summary as plain JSON values."""
        return asdict(self)

    def text(self) -> str:
        stride = "every frame" if self.every == 1 else f"one frame in {self.every}"
        depth = "no" if not self.depth else "yes"
        if self.depth_registered:
            depth += ", registered to colour"
        text = (
            f"ingest: {self.written} frames of {self.source} ({self.kind}, {self.source_frames} "
            f"frames, {stride}) written to {self.scene}; {len(self.blurred)} dropped as blurred "
            f"(sharpness below {self.blur_threshold:g} x the running median); depth: {depth}"
        )
        if self.dropped:
            shown = ", ".join(f"{_frame(d['frame'])} ({d['why']})" for d in self.dropped[:5])
            more = f" and {len(self.dropped) - 5} more" if len(self.dropped) > 5 else ""
            text += f"; {len(self.dropped)} dropped as unusable: {shown}{more}"
        if self.ended_early:
            text += f"; {self.ended_early}"
        for note in self.notes:
            text += f"; {note}"
        if self.rig_written:
            text += f"; dataset.yaml written from the file's {self.intrinsics}"
        return text


def _frame(label: str | int) -> str:
    """A source frame as the summary names it: its file, or ``frame <index>``."""
    return f"frame {label}" if isinstance(label, int) else label


@dataclass(frozen=True)
class IngestSettings:
    """How a recording is ingested (``annotator ingest``'s options of the same names).

    Attributes:
        camera: The rig camera the images are of (the name of the camera of a new rig).
        stream: The colour stream to take from a folder of several (``left``...; default:
            the one named like the camera).
        every: Take every ``every``-th frame of the source.
        blur_threshold: Drop a candidate whose sharpness is below this times the running
            median of its neighbours' (0 keeps every candidate).
        depth: Write the source's depth (when it has any) as ``depth.png``.
        depth_scale: Millimetres per unit of the source's 16-bit depth (default: what the
            file says; 1 for an image folder, as RealSense writes them).
        tolerance_s: How far apart in time a colour frame and its depth partner may be.
        fps: The frame rate of an image folder whose names are frame indices (their times).
        color_topic: A bag's colour topic (when it cannot be told).
        depth_topic: A bag's depth topic (when it cannot be told).
        rig_from_source: Create the dataset (when it does not exist) with the rig the
            file's calibration describes.
        dictionary: The ArUco dictionary of a dataset created by ``rig_from_source``.
        overwrite: Replace the scene if ingest wrote it.

    >>> s = IngestSettings(camera="left", every=5)
    >>> s.every, s.depth
    (5, True)
    """

    camera: str | None = None
    stream: str | None = None
    every: int = 1
    blur_threshold: float = BLUR_THRESHOLD
    depth: bool = True
    depth_scale: float | None = None
    tolerance_s: float = PAIR_TOLERANCE_S
    fps: float | None = None
    color_topic: str | None = None
    depth_topic: str | None = None
    rig_from_source: bool = False
    dictionary: str = DEFAULT_DICTIONARY
    overwrite: bool = False

    def check(self) -> None:
        """Refuse (one line naming the option) a value no ingest can take."""
        if self.every < 1:
            raise UserError(f"--every must be at least 1, got {self.every}")
        if not self.blur_threshold >= 0:
            raise UserError(f"--blur-threshold must be at least 0, got {self.blur_threshold}")
        if self.depth_scale is not None and not self.depth_scale > 0:
            raise UserError(f"--depth-scale must be above 0, got {self.depth_scale}")


def ingest_recording(
    dataset: str | Path | Dataset,
    source: str | Path,
    scene_id: str,
    settings: IngestSettings | None = None,
    *,
    quiet: bool = True,
) -> IngestSummary:
    """Write the sequence recorded in ``source`` (a recorder's file, a video or a folder of
    colour and depth images, :mod:`annotator.ingest.sources`) as scene ``scene_id`` of a
    moving rig's dataset (the dataset's folder, or a new one with
    ``settings.rig_from_source``), as ``settings`` says; ``quiet``: no progress bars.

    >>> import shutil, tempfile
    >>> from pathlib import Path
    >>> from annotator import SynthSettings, synthesize_sequences
    >>> ds = Path(tempfile.mkdtemp()) / "seq"  # a moving rig's dataset, one camera
    >>> settings = SynthSettings(parts=("brick",), scenes=1, instances=(2, 2), size=(160, 128),
    ...                          frames=3, cameras=1)
    >>> _ = synthesize_sequences(ds, settings)
    >>> rec = Path(tempfile.mkdtemp())  # a folder of frames, as image_saver writes them
    >>> for k, f in enumerate(sorted((ds / "scenes" / "000000" / "frames").iterdir())):
    ...     _ = shutil.copy(f / "left.png", rec / f"frame{k:04d}.png")
    >>> s = ingest_recording(ds, rec, "000001", IngestSettings(depth=False))
    >>> s.to_json()["kind"], s.to_json()["written"]
    ('image folder', 3)

    Raises:
        UserError: one line naming the file, for any bad input (module :mod:`.sources`,
            sizes that are not the camera's, a dataset that is not a moving rig's...).
    """
    s = settings or IngestSettings()
    check_scene_id(scene_id)
    s.check()
    src = open_recording(
        source,
        stream=s.camera if s.stream is None else s.stream,
        depth=s.depth,
        tolerance_s=s.tolerance_s,
        fps=s.fps,
        color_topic=s.color_topic,
        depth_topic=s.depth_topic,
        depth_unit_mm=s.depth_scale,
    )
    made = _new_folders(dataset) if s.rig_from_source else []
    ds, rig_written = _dataset(dataset, src, s.camera, s.depth, s.rig_from_source, s.dictionary)
    try:
        return _ingest(ds, src, Path(source), scene_id, s, rig_written, quiet)
    except BaseException:
        if rig_written:  # the dataset this call made goes with the scene it failed to write
            _unmake(ds.root, made)
        raise


@dataclass
class _Chosen:
    """The frames to write, and what was said of the others."""

    kept: list[int]
    sharpness: dict[int, float]
    blurred: list[str | int]
    dropped: list[dict[str, Any]]
    notes: list[str]
    with_depth: bool


def _ingest(
    ds: Dataset,
    src: Recording,
    source: Path,
    scene_id: str,
    s: IngestSettings,
    rig_written: bool,
    quiet: bool,
) -> IngestSummary:
    """The ingest once the dataset is there (:func:`ingest_recording`)."""
    cam, folder = _target(ds, src, source, scene_id, s, rig_written)
    chosen = _choose(ds, src, cam, s, quiet)
    scale = _depth_factor(src, s.depth_scale)
    option = _depth_option(src, s.depth_scale)
    sweep_abandoned(ds.root / SCENES_DIR)
    recheck = partial(check_replaceable, overwrite=s.overwrite)
    with atomic_folder(folder, still_replaceable=recheck) as tmp:
        written = _write_frames(
            ds, src, chosen.kept, cam, tmp, (chosen.with_depth, scale, option), quiet,
            chosen.dropped,
        )  # fmt: skip
        if not written:
            raise UserError("no frame is left to write (none could be decoded)", path=src.path)
        spikes = sum(e.get("depth_spikes_removed", 0) for _, e in written)
        if spikes:
            chosen.notes.append(
                f"{spikes} depth pixels unlike all four of their neighbours made holes (damaged "
                "bytes, or the sensor's speckle); frames.json says how many in each frame"
            )
        intrinsics = src.calibration.origin if rig_written and src.calibration else "dataset.yaml"
        doc = _frames_doc(src, source, cam, s, chosen, written, intrinsics)
        write_json(tmp / FRAMES_FILE, doc)
    return IngestSummary(
        scene=str(folder),
        source=str(source),
        kind=src.kind,
        camera=cam.name,
        source_frames=len(src.times),
        candidates=len(candidates(len(src.times), s.every)),
        written=len(written),
        blurred=chosen.blurred,
        dropped=chosen.dropped,
        ended_early=src.ended_early,
        notes=list(src.notes) + chosen.notes,
        depth=chosen.with_depth,
        streams=dict(src.streams),
        intrinsics=intrinsics,
        file_calibration=src.calibration.origin if src.calibration else None,
        depth_registered=chosen.with_depth and _registers(src),
        rig_written=rig_written,
        every=s.every,
        blur_threshold=s.blur_threshold,
    )


def _target(
    ds: Dataset, src: Recording, source: Path, scene_id: str, s: IngestSettings, rig_written: bool
) -> tuple[Camera, Path]:
    """The rig camera and the scene folder, checked: a moving rig's, the recording's camera,
    a scene ingest may write, a source outside it."""
    if not ds.rig.moving:
        raise UserError(
            "the rig is not a moving one: ingest writes sequences into a dataset whose "
            "dataset.yaml says rig: {moving: true} (FORMAT.md, sequences)",
            path=ds.root / "dataset.yaml",
        )
    cam = _camera(ds, s.camera)
    if src.calibration is not None and not rig_written:
        check_rig_matches(cam, src.calibration, ds.root / "dataset.yaml", src.path)
    folder = ds.root / SCENES_DIR / scene_id
    check_replaceable(folder, overwrite=s.overwrite)
    real = Path(source).resolve()
    if real == folder.resolve() or folder.resolve() in real.parents:
        raise UserError(
            "lies in the scene it would be written to; move it out of the dataset first",
            path=source,
        )
    return cam, folder


def _choose(ds: Dataset, src: Recording, cam: Camera, s: IngestSettings, quiet: bool) -> _Chosen:
    """The frames to write: every ``every``-th, in time (repeats dropped), with a depth
    partner when depth is written, sharp enough (pass 1 reads them)."""
    if s.depth and "depth" in src.streams and all(d is None for d in src.depth_for):
        raise UserError(_unpaired(src, s.tolerance_s), path=src.path)
    with_depth = s.depth and any(d is not None for d in src.depth_for)
    if with_depth:
        _check_depth_camera(ds, cam)
    dropped: list[dict[str, Any]] = [{"frame": lbl, "why": why} for lbl, why in src.dropped]
    chosen, repeats, notes = _in_time(src, candidates(len(src.times), s.every))
    dropped += repeats
    if with_depth:
        tol = f"{s.tolerance_s * 1000:g} ms"
        lonely = [i for i in chosen if src.depth_for[i] is None]
        dropped += [{"frame": src.labels[i], "why": f"no depth frame within {tol}"} for i in lonely]
        chosen = [i for i in chosen if src.depth_for[i] is not None]
    good, values = _measure(src, chosen, cam, quiet, dropped)
    selection = select(good, values, threshold=s.blur_threshold)
    kept = list(selection.kept)
    if not kept:
        why = "all dropped as blurred" if good else "none could be decoded"
        raise UserError(f"no frame is left to write ({why})", path=src.path)
    sharpness = {i: round(selection.of(i), 3) for i in kept}
    blurred = [src.labels[i] for i in selection.blurred]
    return _Chosen(kept, sharpness, blurred, dropped, notes, with_depth)


def _frames_doc(
    src: Recording,
    source: Path,
    cam: Camera,
    s: IngestSettings,
    chosen: _Chosen,
    written: list[tuple[int, dict[str, Any]]],
    intrinsics: str,
) -> dict[str, Any]:
    """frames.json (FORMAT.md, sequences): where each frame came from, its time and
    sharpness, and what was left out."""
    t0 = next((t for t in src.times if t is not None), None)
    entries: dict[str, dict[str, Any]] = {}
    for k, (i, entry) in enumerate(written):
        entry["sharpness"] = chosen.sharpness[i]
        t = src.times[i]
        entry["time_s"] = None if t is None or t0 is None else round(t - t0, 6)
        entries[frame_name(k)] = entry
    return {
        "written_by": WRITTEN_BY,
        "source": str(Path(source).resolve()),
        "kind": src.kind,
        "camera": cam.name,
        "streams": src.streams,
        "intrinsics": intrinsics,
        "every": s.every,
        "blur_threshold": s.blur_threshold,
        "time_origin_s": t0,
        "blurred": chosen.blurred,
        "dropped": chosen.dropped,
        "ended_early": src.ended_early,
        "notes": src.notes + chosen.notes,
        "frames": entries,
    }


def _unpaired(src: Recording, tolerance_s: float) -> str:
    """Why no colour frame has a depth partner, with how far apart the streams are and the
    tolerance that would pair them: a whole stream is never dropped without a word."""
    gaps = nearest_gaps(src.times, src.depth_times)
    tol = f"{tolerance_s * 1000:g} ms"
    if not gaps:
        return (
            f"no colour frame has a depth frame within {tol} (the depth stream "
            f"{src.streams.get('depth')} has no usable time): pass --no-depth to ingest colour only"
        )
    median = float(np.median(gaps)) * 1000
    need = int(np.ceil(median * 1.1))
    return (
        f"no colour frame has a depth frame within {tol}: the streams are {median:.0f} ms apart "
        f"(median nearest gap); --tolerance-ms {need} would pair them, or pass --no-depth to "
        "ingest colour only"
    )


def _in_time(
    src: Recording, chosen: list[int]
) -> tuple[list[int], list[dict[str, Any]], list[str]]:
    """The chosen frames less those whose time repeats the frame before's (a recorder
    writing a frame twice), those dropped, and a note when the times go back."""
    kept: list[int] = []
    repeats: list[dict[str, Any]] = []
    back: list[str] = []
    last: tuple[int, float] | None = None
    for i in chosen:
        t = src.times[i]
        if t is not None and last is not None and t == last[1]:
            why = f"the same time as {_frame(src.labels[last[0]])} (a repeated frame)"
            repeats.append({"frame": src.labels[i], "why": why})
            continue
        if t is not None and last is not None and t < last[1]:
            back.append(f"{_frame(src.labels[i])} ({t - last[1]:+.3f} s)")
        if t is not None:
            last = (i, t)
        kept.append(i)
    notes = []
    if back:
        more = f" and {len(back) - 3} more" if len(back) > 3 else ""
        notes.append(
            f"the frames' times go back at {', '.join(back[:3])}{more}: kept in the file's "
            "order, times as the file gives them"
        )
    return kept, repeats, notes


def _new_folders(dataset: str | Path | Dataset) -> list[Path]:
    """The folders that creating ``dataset`` would make, outermost first."""
    if isinstance(dataset, Dataset):
        return []
    missing = []
    p = Path(dataset).absolute()
    while not p.exists() and p != p.parent:
        missing.append(p)
        p = p.parent
    return missing[::-1]


def _unmake(root: Path, made: list[Path]) -> None:
    """Remove the dataset.yaml this ingest wrote, and the folders it made if left empty."""
    (root / "dataset.yaml").unlink(missing_ok=True)
    scenes = root / SCENES_DIR
    for folder in [scenes, *reversed(made)]:
        with contextlib.suppress(OSError):
            folder.rmdir()  # only when empty


def _dataset(
    dataset: str | Path | Dataset,
    src: Recording,
    camera: str | None,
    depth: bool,
    rig_from_source: bool,
    dictionary: str,
) -> tuple[Dataset, bool]:
    """The dataset, created from the source's calibration when asked and not there yet."""
    if isinstance(dataset, Dataset):
        return dataset, False
    root = Path(dataset)
    if not rig_from_source or (root / "dataset.yaml").exists():
        return load_dataset(root), False
    if src.calibration is None:
        raise UserError(
            f"--rig-from-source: a {src.kind} carries no calibration; write dataset.yaml "
            "yourself (FORMAT.md) or ingest a recorder's file (.bag, Azure Kinect .mkv, .r3d)",
            path=src.path,
        )
    if root.exists() and not root.is_dir():
        raise UserError("exists and is not a folder", path=root)
    rig = rig_from_calibration(src.calibration, camera or "cam", depth=depth)
    write_new_dataset(root, rig, dictionary, src.path)
    return load_dataset(root), True


def _camera(ds: Dataset, name: str | None) -> Camera:
    """The rig camera the images are of: the rig's only one (a frame needs an image of
    every rig camera, and a recording gives one camera's)."""
    names = [c.name for c in ds.rig.cameras]
    if name is not None and name not in names:
        raise UserError(
            f"--camera {name!r} is not a camera of the rig ({', '.join(names)})",
            path=ds.root / "dataset.yaml",
        )
    if len(names) > 1:
        raise UserError(
            f"the rig has several cameras ({', '.join(names)}) and every frame of a sequence "
            "needs an image of each, but ingest reads one camera's recording: ingest into a "
            f"dataset whose rig is {'that camera' if name else 'the recording camera'} alone",
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


def _depth_factor(src: Recording, depth_scale: float | None) -> float:
    """What the recording's depth (mm by its own unit) is multiplied by: the unit given
    with --depth-scale over the file's own (folders take --depth-scale when reading)."""
    cal = src.calibration
    if depth_scale is None or cal is None or cal.depth is None:
        return 1.0
    return depth_scale / cal.depth.unit_mm


def _where(src: Recording, i: int) -> Path | str:
    """How messages name a frame: its file, or the recording and the frame."""
    label = src.labels[i]
    if src.kind == "image folder":
        return src.path / str(label)
    return f"{src.path} (frame {label})"


def _measure(
    src: Recording, chosen: Sequence[int], cam: Camera, quiet: bool, dropped: list[dict[str, Any]]
) -> tuple[list[int], list[float]]:
    """Pass 1: every candidate decoded (the damaged ones dropped), its size checked; the
    good ones and their sharpness."""
    good: list[int] = []
    values: list[float] = []
    first: tuple[tuple[int, int], str] | None = None
    bar = progress_bar(len(chosen), "ingest (reading)", quiet, unit="frame")
    try:
        for d in src.decode(chosen, depth=False):
            bar.update()
            if d.problem is not None or d.colour is None:
                dropped.append({"frame": src.labels[d.index], "why": d.problem or "no image"})
                continue
            img = d.colour
            check_size(img, cam, _where(src, d.index), first)
            if first is None:
                first = ((img.shape[1], img.shape[0]), str(src.labels[d.index]))
            good.append(d.index)
            values.append(sharpness(img))
    finally:
        bar.close()
    return good, values


def _write_frames(
    ds: Dataset,
    src: Recording,
    kept: list[int],
    cam: Camera,
    scene: Path,
    depth: tuple[bool, float, str],
    quiet: bool,
    dropped: list[dict[str, Any]],
) -> list[tuple[int, dict[str, Any]]]:
    """Pass 2: each kept frame's folder; their frames.json entries. ``depth``: whether to
    write it, the factor its millimetres take, the option that set its unit."""
    with_depth, scale, option = depth
    written: list[tuple[int, dict[str, Any]]] = []
    bar = progress_bar(len(kept), "ingest (writing)", quiet, unit="frame")
    try:
        for d in src.decode(kept, depth=with_depth):
            bar.update()
            if d.problem is not None or d.colour is None:
                dropped.append({"frame": src.labels[d.index], "why": d.problem or "no image"})
                continue
            entry: dict[str, Any] = {"source": src.labels[d.index]}
            depth_mm = None
            if with_depth:
                assert d.depth_mm is not None and ds.rig.depth is not None
                spikes = isolated_spikes(d.depth_mm)
                if spikes.any():  # holes rather than depth of no surface
                    d.depth_mm[spikes] = np.nan
                    entry["depth_spikes_removed"] = int(spikes.sum())
                depth_mm = _on_colour_grid(src, d.depth_mm * scale, cam, d.index)
                unit = src.depth_unit() * scale
                check_depth_range(depth_mm, ds.rig.depth, unit, option, src.depth_where(d.index))
                entry["depth_source"] = src.depth_label(d.index)
            write_frame(frames_folder(scene, len(written)), cam, d.colour, depth_mm, ds.rig.depth)
            written.append((d.index, entry))
    finally:
        bar.close()
    return written


def _registers(src: Recording) -> bool:
    """Whether the recording's depth is another camera's, redrawn on the colour grid."""
    cal = src.calibration
    return cal is not None and cal.depth is not None and not cal.depth.registered


def _depth_option(src: Recording, depth_scale: float | None) -> str:
    """What set the depth unit, as error messages name it."""
    if depth_scale is not None:
        return f"--depth-scale {depth_scale:g}"
    if src.calibration is not None and src.calibration.depth is not None:
        return f"the file's depth unit ({src.calibration.depth.unit_mm:g} mm; see --depth-scale)"
    return "--depth-scale 1 (the default)"


def _on_colour_grid(src: Recording, depth_mm: np.ndarray, cam: Camera, i: int) -> np.ndarray:
    """The frame's depth on the rig camera's grid: registered when it is another camera's."""
    cal = src.calibration
    if _registers(src):
        assert cal is not None and cal.depth is not None and cal.depth.colour_T_depth is not None
        return register_depth(depth_mm, cal.depth.camera, cam, cal.depth.colour_T_depth)
    h, w = depth_mm.shape
    if (w, h) != cam.size:
        raise UserError(
            f"depth is {w}x{h} but camera {cam.name} is {cam.width}x{cam.height}: record "
            "depth aligned to the colour images",
            path=src.depth_where(i),
        )
    return depth_mm
