"""``annotate`` over a moving rig's dataset: the steps of :mod:`annotator.annotation.sequence`
as batches, so that every core (or a Ray cluster) works on one long sequence.

1. every frame of every chosen scene is read (:class:`FrameReadJob`, one unit per frame),
   its depth map kept at the samples step 3 reads (decoded once);
2. every scene is solved (:class:`SequenceSolveJob`, one unit per scene);
3. every posed frame is seen (:class:`FrameSeeJob`, one unit per frame);
4. each scene's annotation.json is written here, atomically: a scene any of whose frames
   failed is reported with that frame's one-line error and keeps its old file.

Units of frame jobs are ``<scene>/<frame>``: what the progress bar counts and failures name.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from annotator.annotation.sequence import (
    FrameReading,
    SequenceSolution,
    frame_visibility,
    sequence_annotation,
    solve_sequence,
)
from annotator.annotation.sequence.reading import read_frame, read_frame_sampled
from annotator.annotation.sequence.visibility import visibility_step
from annotator.annotation.settings import AnnotateSettings
from annotator.dataset import Dataset, Scene, cached_dataset
from annotator.dataset.flags import WarningKind
from annotator.dataset.frames import scene_shots
from annotator.dataset.model import FRAMES_DIR, SCENES_DIR
from annotator.dataset.records import InstanceAnnotation
from annotator.dataset.review import now_iso
from annotator.detection import MarkerDetector
from annotator.physics.scene import record_physics
from annotator.runner import BatchReport, run_batch
from annotator.runner.files import description_files

__all__ = ["FrameReadJob", "FrameSeeJob", "SequenceSolveJob", "annotate_sequences"]


def _frame_files(ds: Dataset, unit: str) -> list[str]:
    scene, name = unit.rsplit("/", 1)
    folder = f"{SCENES_DIR}/{scene}/{FRAMES_DIR}/{name}"
    return [f"{folder}/{c.name}.png" for c in ds.rig.cameras] + [f"{folder}/depth.png"]


@functools.cache
def _detector(dictionary: str) -> MarkerDetector:
    return MarkerDetector(dictionary)


@dataclass(frozen=True)
class _Step:
    """What every step's job declares for a Ray cluster: the dataset description shared,
    a frame's images and depth as its unit's inputs, nothing written (the results come
    back as data)."""

    root: str

    def shared_files(self) -> list[str]:
        return description_files(cached_dataset(self.root))

    def scene_files(self, scene_id: str) -> list[str]:
        return _frame_files(cached_dataset(self.root), scene_id)

    def output_files(self, scene_id: str) -> list[str]:
        return []


#: The most the depth maps' samples kept from step 1 for step 3 may take (bytes); past it,
#: step 3 decodes the depth files again rather than hold every frame's in memory.
DEPTH_KEPT_BYTES = 1 << 30


@dataclass(frozen=True)
class FrameReadJob(_Step):
    """Step 1: the markers of one frame (unit ``<scene>/<frame>``), and with ``depth_step``
    its depth map at every ``depth_step``-th pixel of every ``depth_step``-th row, what step
    3 reads (None: none, or not kept)."""

    depth_step: int | None = None

    def __call__(self, scene_id: str) -> dict[str, Any]:
        ds = cached_dataset(self.root)
        detector = _detector(ds.dictionary)
        frame = ds.frame(scene_id)
        if self.depth_step is None:
            return {"reading": read_frame(ds, frame, detector), "depth": None}
        reading, depth = read_frame_sampled(ds, frame, detector, step=self.depth_step)
        return {"reading": reading, "depth": depth}


def _kept_depth_step(ds: Dataset, frames: int, settings: AnnotateSettings) -> int | None:
    """The step at which step 1 keeps ``frames`` frames' depth maps for step 3, None when
    there is no depth or they would take more than :data:`DEPTH_KEPT_BYTES`."""
    if ds.rig.depth is None:
        return None
    step = visibility_step(settings)
    cam = ds.rig.camera(ds.rig.depth.camera)
    samples = -(-cam.height // step) * -(-cam.width // step)
    return step if frames * samples * np.dtype(np.float32).itemsize <= DEPTH_KEPT_BYTES else None


@dataclass(frozen=True)
class SequenceSolveJob(_Step):
    """Step 2: one scene's solve from its frames' readings (carried by the job)."""

    readings: dict[str, list[FrameReading]] = field(default_factory=dict)
    settings: AnnotateSettings = AnnotateSettings()

    def scene_files(self, scene_id: str) -> list[str]:
        return []  # a scene unit, not a frame: everything it needs is in the job

    def __call__(self, scene_id: str) -> dict[str, Any]:
        ds = cached_dataset(self.root)
        return {"solution": solve_sequence(ds, self.readings[scene_id], settings=self.settings)}


@dataclass(frozen=True)
class FrameSeeJob(_Step):
    """Step 3: what one posed frame sees of its scene's instances (unit ``<scene>/<frame>``)."""

    solutions: dict[str, SequenceSolution] = field(default_factory=dict)
    settings: AnnotateSettings = AnnotateSettings()
    #: Per unit, the depth map's samples step 1 kept (a unit missing: its file is read).
    depths: dict[str, np.ndarray] = field(default_factory=dict)

    def __call__(self, scene_id: str) -> dict[str, Any]:
        ds = cached_dataset(self.root)
        scene, name = scene_id.rsplit("/", 1)
        sol = self.solutions[scene]
        T = sol.frames[name].scene_T_rig
        assert T is not None  # only posed frames are units
        seen = frame_visibility(
            ds,
            ds.frame(scene_id),
            sol.instances,
            T,
            settings=self.settings,
            depth_samples=self.depths.get(scene_id),
        )
        return {"seen": seen}


@dataclass
class _Run:
    """Where each scene stands: its frames, and the first failure of any of its steps."""

    frames: dict[str, list[str]]
    failed: dict[str, str] = field(default_factory=dict)

    def units(self) -> list[str]:
        return [
            f"{s}/{f}" for s, names in self.frames.items() if s not in self.failed for f in names
        ]

    def absorb(self, report: BatchReport) -> None:
        for unit, message in sorted(report.failed.items()):
            scene, _, frame = unit.rpartition("/")
            scene = scene or unit
            self.failed.setdefault(scene, f"frame {frame}: {message}" if frame else message)


def annotate_sequences(
    ds: Dataset,
    scenes: list[Scene],
    *,
    digest: str,
    workers: int = 1,
    settings: AnnotateSettings = AnnotateSettings(),
    quiet: bool = True,
    ray_address: str | None = None,
    ray_wait: float | None = None,
) -> BatchReport:
    """Annotate the sequences ``scenes`` (steps 1-4 of the module's docstring); each done
    scene's result has the counts ``annotate --json`` sums."""
    run = _Run({s.id: [f.name for f in s.frames()] for s in scenes})
    for s in scenes:
        if not run.frames[s.id]:
            run.failed[s.id] = (
                f"{s.path}: a moving rig's scene holds its images in {FRAMES_DIR}/<frame>/: none found"
            )
    batch = functools.partial(
        run_batch, workers=workers, quiet=quiet, ray_address=ray_address, ray_wait=ray_wait
    )
    units = run.units()
    read = FrameReadJob(str(ds.root), _kept_depth_step(ds, len(units), settings))
    report = batch(read, units, desc="read frames")
    run.absorb(report)
    depths = {unit: r.pop("depth") for unit, r in report.done.items()}
    readings = {
        s: [report.done[f"{s}/{f}"]["reading"] for f in names]
        for s, names in run.frames.items()
        if s not in run.failed
    }
    solved = batch(SequenceSolveJob(str(ds.root), readings, settings), list(readings), desc="solve")
    run.absorb(solved)
    solutions = {s: r["solution"] for s, r in solved.done.items() if s not in run.failed}
    posed = [
        f"{s}/{f}"
        for s, sol in solutions.items()
        for f in run.frames[s]
        if sol.frames[f].scene_T_rig is not None
    ]
    kept = {u: depths[u] for u in posed if depths.get(u) is not None}
    see = FrameSeeJob(str(ds.root), solutions, settings, kept)
    seen_report = batch(see, posed, desc="see frames")
    run.absorb(seen_report)
    out = BatchReport(failed=dict(run.failed))
    for sid, sol in sorted(solutions.items()):
        if sid in run.failed:
            continue
        seen = {
            f: seen_report.done[f"{sid}/{f}"]["seen"]
            for f in run.frames[sid]
            if f"{sid}/{f}" in seen_report.done
        }
        ann = sequence_annotation(sol, readings[sid], seen, settings=settings)
        scene = ds.scene(sid)
        if not ann.instances:
            out.failed[sid] = f"{scene.path}: no marker of any known instance detected in any frame"
            continue
        shots = scene_shots(ds, scene, ann.frames)
        if shots:  # the pile as its first posed frame's depth sees its support
            record_physics(ds, shots[0], ann.instances)
        ann.created_at = now_iso()
        ann.description_digest = digest
        ann.write(scene.annotation_path)
        scene.unexplained_path.unlink(missing_ok=True)  # a fixed rig's mask does not apply
        out.done[sid] = _counts(ann.instances, bool(ann.warnings), sol)
    return out


def _counts(
    instances: list[InstanceAnnotation], warned: bool, sol: SequenceSolution
) -> dict[str, Any]:
    frames = list(sol.frames.values())
    return {
        "instances": len(instances),
        "flagged": sum(1 for i in instances if i.flags),
        "warned": warned or any(w.kind == WarningKind.NO_MARKERS for w in sol.warnings),
        "frames": len(frames),
        "frames_posed": sum(1 for f in frames if f.scene_T_rig is not None),
    }
