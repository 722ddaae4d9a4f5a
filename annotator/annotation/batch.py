"""``annotate`` over a whole dataset: which scenes need work, the per-scene job, and
:func:`annotate_dataset`, what ``annotator annotate`` runs."""

from __future__ import annotations

import functools
import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from annotator.annotation.scene import annotate_scene
from annotator.annotation.sequence.batch import annotate_sequences
from annotator.annotation.settings import AnnotateSettings
from annotator.dataset import Dataset, Scene, as_dataset, cached_dataset, require_meshes
from annotator.dataset.check import BROKEN_LINK
from annotator.dataset.flags import WarningKind
from annotator.dataset.frames import frames_left_out, frames_line
from annotator.dataset.poses import read_pose_file
from annotator.dataset.records import SceneAnnotation
from annotator.dataset.review import now_iso
from annotator.dataset.selection import matches, matching_scenes
from annotator.detection import MarkerDetector
from annotator.errors import UserError
from annotator.io.images import write_png
from annotator.physics.scene import empty_bin
from annotator.runner import BatchReport, run_batch
from annotator.runner.files import description_files, dictionary_files
from annotator.summary import failure_lines
from annotator.values import number, of_type, whole


def description_digest(ds: Dataset) -> str:
    """SHA-256 of what every annotation of the dataset depends on besides its scene's images:
    dataset.yaml, a custom dictionary file, each object.yaml and each mesh file, by content."""
    h = hashlib.sha256()
    files = [ds.root / "dataset.yaml", *dictionary_files(ds)]
    for name in sorted(ds.objects):
        files += [ds.objects[name].folder / "object.yaml", ds.objects[name].mesh_path]
    for path in files:
        h.update(os.path.relpath(path, ds.root).encode() + b"\0")
        h.update(hashlib.sha256(path.read_bytes()).digest())
    return h.hexdigest()


def scene_inputs(ds: Dataset, scene: Scene) -> list[Path]:
    """The scene's own files an annotation depends on: its images and depth map (every
    frame's, for a sequence)."""
    shots = scene.frames() if ds.rig.moving else [scene]
    files = [shot.image_path(c) for shot in shots for c in ds.rig.cameras]
    files += [shot.depth_path for shot in shots if shot.depth_path.exists()]
    return files


def is_up_to_date(ds: Dataset, scene: Scene, digest: str) -> bool:
    """True if the scene's annotation.json is valid, was made from the dataset description
    with ``digest`` (:func:`description_digest`), and is newer than the scene's images (a
    sequence's: of the very frames it has now)."""
    path = scene.annotation_path
    if not path.exists():
        return False
    try:
        _, top = read_pose_file(path)
    except UserError:  # corrupt: annotate again
        return False
    if top.get("description_digest") != digest:
        return False
    if ds.rig.moving:  # a frame added or deleted changes the sequence, whatever the times
        recorded = top.get("frames")
        if not isinstance(recorded, dict) or set(recorded) != {f.name for f in scene.frames()}:
            return False
    mtime = path.stat().st_mtime
    return all(p.exists() and p.stat().st_mtime <= mtime for p in scene_inputs(ds, scene))


@dataclass(frozen=True)
class AnnotateJob:
    """The per-scene job (picklable, for worker processes: each loads the dataset once)."""

    root: str
    digest: str  # description_digest() of the dataset, recorded in every annotation.json
    settings: AnnotateSettings = AnnotateSettings()

    @classmethod
    def for_dataset(cls, ds: Dataset, settings: AnnotateSettings | None = None) -> AnnotateJob:
        """The job for every scene of ``ds`` (computes the dataset's description digest)."""
        return cls(str(ds.root), description_digest(ds), settings or AnnotateSettings())

    def prepare(self) -> None:
        """Do once what every scene needs (see :mod:`annotator.runner`): import open3d, load
        the dataset, meshes and marker table, tabulate every camera's pixel rays."""
        import annotator.occlusion  # noqa: F401  (imports open3d: seconds)

        ds, _ = _context(self.root)
        ds.marker_table  # noqa: B018  (cached property)
        for obj in ds.objects.values():
            obj.mesh.moments  # noqa: B018
        for cam in ds.rig.cameras:
            cam.pixel_rays(self.settings.visibility_step)
        empty_bin(ds)  # the physics check's support, fitted once for every worker

    # What a scene's work reads and writes, for runs on a cluster without the dataset's disk
    # (annotator.runner.job): paths relative to ``root``.

    def shared_files(self) -> list[str]:
        """The dataset description (dataset.yaml, objects, background depth)."""
        return description_files(cached_dataset(self.root))

    def scene_files(self, scene_id: str) -> list[str]:
        """The scene's images and depth map."""
        scene = Scene.relative(scene_id)
        paths = [scene.image_path(c) for c in cached_dataset(self.root).rig.cameras]
        return [p.as_posix() for p in [*paths, scene.depth_path]]

    def output_files(self, scene_id: str) -> list[str]:
        """The mask (or its deletion) and annotation.json, in the order they are written."""
        scene = Scene.relative(scene_id)
        return [scene.unexplained_path.as_posix(), scene.annotation_path.as_posix()]

    def __call__(self, scene_id: str) -> dict[str, Any]:
        ds, detector = _context(self.root)
        scene = ds.scene(scene_id)
        result = annotate_scene(ds, scene, detector, settings=self.settings)
        ann = result.annotation
        if not ann.instances and any(w.kind == WarningKind.NO_MARKERS for w in ann.warnings):
            raise UserError("no marker of any known instance detected", path=scene.path)
        ann.created_at = now_iso()
        ann.description_digest = self.digest
        mask_path = scene.unexplained_path
        if ann.unexplained_mask is not None and result.unexplained is not None:
            write_png(mask_path, result.unexplained)
        ann.write(scene.annotation_path)
        if ann.unexplained_mask is None:
            mask_path.unlink(missing_ok=True)  # an earlier run's mask no longer holds
        return {
            "instances": len(ann.instances),
            "flagged": sum(1 for i in ann.instances if i.flags),
            "warned": bool(ann.warnings),
        }


def _context(root: str) -> tuple[Dataset, MarkerDetector]:
    ds = cached_dataset(root)
    return ds, _detector(ds.dictionary)


@functools.cache
def _detector(dictionary: str) -> MarkerDetector:
    return MarkerDetector(dictionary)


@dataclass
class AnnotateSummary:
    """What :func:`annotate_dataset` did; :meth:`to_json` is ``annotator annotate --json``.

    Attributes:
        scenes: Scenes matching the pattern.
        report: Per-scene outcomes (done: their counts; failed: one line each).
        skipped: Scenes whose annotation was up to date.

    >>> from annotator.runner import BatchReport
    >>> done = {"000000": {"instances": 8, "flagged": 1, "warned": 0}}
    >>> failed = {"000001": "no depth.png"}
    >>> s = AnnotateSummary(scenes=2, report=BatchReport(done, failed), skipped=0)
    >>> s.counts()["instances_posed"], s.exit_status()
    (8, 1)
    >>> s.warnings()
    ['failed: scene 000001: no depth.png']
    """

    scenes: int
    report: BatchReport
    skipped: int
    #: A sequence annotated now -> its frames not posed and why (:func:`frames_left_out`).
    frames_left_out: dict[str, dict[str, str]] = field(default_factory=dict)
    #: A sequence annotated now -> its notes (parts moved, frames of another arrangement,
    #: markers glued off their layout: run ``annotator sites``).
    notes: dict[str, list[str]] = field(default_factory=dict)
    #: The annotation.json files written now, in scene order.
    written: list[Path] = field(default_factory=list)

    def counts(self) -> dict[str, int]:
        done = self.report.done.values()
        out = {
            "scenes": self.scenes,
            "done": len(self.report.done),
            "skipped": self.skipped,
            "failed": len(self.report.failed),
            "instances_posed": sum(r["instances"] for r in done),
            "instances_flagged": sum(r["flagged"] for r in done),
            "scenes_warned": sum(r["warned"] for r in done),
        }
        if any("frames" in r for r in done):  # sequences: frames are counted too
            out["frames"] = sum(r.get("frames", 0) for r in done)
            out["frames_posed"] = sum(r.get("frames_posed", 0) for r in done)
        return out

    def warnings(self) -> list[str]:
        """The frames of each sequence left out, its notes (what to do next, what moved),
        then the failed scenes."""
        lines = [
            f"scene {sid}: {frames_line(left, self.report.done[sid].get('frames'))}"
            for sid, left in sorted(self.frames_left_out.items())
        ]
        lines += [f"scene {sid}: {n}" for sid, said in sorted(self.notes.items()) for n in said]
        return lines + failure_lines(self.report.failed)

    def written_paths(self) -> list[Path]:
        return list(self.written)

    def text(self) -> str:
        n = self.counts()
        frames = f"{n['frames_posed']} of {n['frames']} frames posed; " if "frames" in n else ""
        return (
            f"annotate: {n['done']} scenes done, {n['skipped']} up to date (skipped), "
            f"{n['failed']} failed; {frames}{n['instances_posed']} instances posed, "
            f"{n['instances_flagged']} flagged; {n['scenes_warned']} scenes with warnings "
            "(parts without a pose, blur, exposure: `annotator check --annotations`)"
        )

    def to_json(self) -> dict[str, Any]:
        n = self.counts()
        moving = {"frames_left_out": self.frames_left_out, "notes": self.notes}
        frames: dict[str, Any] = {k: n.pop(k) for k in ("frames", "frames_posed") if k in n}
        return {
            **n,
            "failures": dict(sorted(self.report.failed.items())),
            **({**frames, **moving} if frames else {}),
        }

    def exit_status(self) -> int:
        return 1 if self.report.failed else 0


def annotate_dataset(
    ds: Dataset | str | Path,
    *,
    scenes: str = "*",
    force: bool = False,
    workers: int = 1,
    settings: AnnotateSettings | None = None,
    quiet: bool = True,
    ray_address: str | None = None,
    ray_wait: float | None = None,
) -> AnnotateSummary:
    """Annotate every scene of ``ds`` whose id matches ``scenes`` (fnmatch) and whose
    annotation.json is not up to date (all of them with ``force``), in ``workers`` processes
    or on a Ray cluster (``ray_address``); a scene that fails is reported, the others go on.

        >>> import shutil, tempfile
    >>> from pathlib import Path
    >>> root = shutil.copytree("sample_scenes", Path(tempfile.mkdtemp()) / "ds")
    >>> summary = annotate_dataset(root, scenes="000000", force=True)
    >>> summary.scenes, sorted(summary.report.done), summary.report.failed
    (1, ['000000'], {})

    Raises:
        UserError: no scene matches, or a mesh is unreadable.
    """
    # What `annotator annotate` refuses, refused here in the same words.
    ds = as_dataset(ds, name="ds")
    of_type(scenes, str, name="scenes", what="an fnmatch pattern (str)")
    workers = whole(workers, name="workers", low=1)
    if ray_wait is not None:
        ray_wait = number(ray_wait, name="ray_wait", low=0)
    if settings is not None:
        of_type(settings, AnnotateSettings, name="settings", what="annotator.AnnotateSettings")
    chosen = matching_scenes(ds, scenes)
    require_meshes(ds)
    job = AnnotateJob.for_dataset(ds, settings)
    todo = [s.id for s in chosen if force or not is_up_to_date(ds, s, job.digest)]
    if ds.rig.moving:
        report = annotate_sequences(
            ds,
            [ds.scene(s) for s in todo],
            digest=job.digest,
            workers=workers,
            settings=job.settings,
            quiet=quiet,
            ray_address=ray_address,
            ray_wait=ray_wait,
        )
    else:
        report = run_batch(
            job,
            todo,
            workers=workers,
            desc="annotate",
            quiet=quiet,
            ray_address=ray_address,
            ray_wait=ray_wait,
        )
    for link in ds.broken_scene_links():
        if matches(link.name, scenes):
            report.failed[link.name] = f"{link}: {BROKEN_LINK}"
    left, notes = {}, {}
    for sid in sorted(report.done) if ds.rig.moving else []:
        path = ds.scene(sid).annotation_path
        ann = SceneAnnotation.read(path)
        frames = frames_left_out(ann.frames)
        if frames:
            left[sid] = frames
        said = [w.message for w in ann.warnings if w.kind == WarningKind.NOTE]
        if said:
            notes[sid] = said
    written = [ds.scene(sid).annotation_path for sid in sorted(report.done)]
    return AnnotateSummary(len(chosen), report, len(chosen) - len(todo), left, notes, written)
