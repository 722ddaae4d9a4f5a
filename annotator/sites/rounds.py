"""Sites measured until they settle, in one ``annotator sites``.

The first measurement starts from the poses and markers ``annotate`` found with the layout's
sites: markers glued a millimetre or two off were rejected then, and poses resting on few
markers were pulled by them. So the scenes are annotated again, in memory, with the sites
just measured (more markers fit, more are recovered from blur, the poses move), and the
sites measured again from those (with the first round's gluing spread as the prior); until
the RMS move of the site corners between two rounds is under :data:`SETTLED_MM`, or
:data:`MAX_ROUNDS` rounds. Nothing is written meanwhile: the caller writes object.yaml once,
and ``annotate`` then finds the poses of the last round.

The corrections of every round are measured from the object's layout, so a round only
changes the sites through better poses and more markers, never by compounding its own.

Every round, the first too, starts from poses made from the markers alone (the scenes are
annotated again in memory, before the first round with the sites the dataset has): the
solve refines each pose against the depth itself, and ``annotate``'s refinement of poses on
few markers (:mod:`annotator.annotation.refine`), kept or not by a threshold, would make the
sites hop between rounds. So the measurement does not depend on which ``annotate`` made
annotation.json, and measuring again after the ``annotate`` that follows is one more round.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Any

import numpy as np

from annotator.annotation.scene import annotate_scene
from annotator.annotation.sequence import annotate_sequence, frame_annotations
from annotator.annotation.settings import AnnotateSettings
from annotator.dataset import Dataset, Scene, cached_dataset
from annotator.dataset.records import SceneAnnotation
from annotator.detection import MarkerDetector
from annotator.runner import BatchReport, run_batch
from annotator.sites.measure import InstanceSites, measure_instances, units
from annotator.sites.solve import SiteSettings

#: Rounds end once the site corners move by less than this between two rounds (mm, RMS):
#: a tenth of what the measured sites are known to.
SETTLED_MM = 0.01
#: Rounds at most (the first is the measurement from annotate's own poses).
MAX_ROUNDS = 3

#: How the rounds annotate: poses from the markers alone (see the module docstring).
ROUND_SETTINGS = AnnotateSettings(refine_max_markers=0)

#: (object, instance) -> its measured sites, (S, 4, 3) mm.
Sites = dict[tuple[str, str], np.ndarray]


@dataclass(frozen=True)
class Rounds:
    """The outcome of the rounds: the last measurement, the gluing spread it used, how many
    rounds were made, the RMS site move of each round after the first (mm), and the scenes
    that could not be annotated again (their annotation.json was used)."""

    measured: list[InstanceSites]
    spread: tuple[float, float] | None
    rounds: int
    moves: list[float]
    failed: dict[str, str]


def with_sites(ds: Dataset, sites: Sites) -> Dataset:
    """``ds`` in memory with the instances of ``sites`` given those sites (meshes shared)."""
    objects = {}
    for name, obj in ds.objects.items():
        instances = tuple(
            replace(i, sites=sites[(name, i.name)]) if (name, i.name) in sites else i
            for i in obj.instances
        )
        new = replace(obj, instances=instances)
        if "mesh" in obj.__dict__:  # the loaded mesh (a cached property), not loaded again
            new.__dict__["mesh"] = obj.__dict__["mesh"]
        objects[name] = new
    return replace(ds, objects=objects)


def rms_move(before: list[InstanceSites], after: list[InstanceSites]) -> float:
    """The RMS distance (mm) the site corners moved from ``before`` to ``after`` (an
    instance measured in one only counts as a move of infinity)."""
    old = {m.key: m.sites for m in before}
    new = {m.key: m.sites for m in after}
    if set(old) != set(new):
        return float("inf")
    moves = [np.sum((new[k] - old[k]) ** 2, axis=-1).ravel() for k in new]
    return float(np.sqrt(np.mean(np.concatenate(moves)))) if moves else 0.0


@dataclass(frozen=True)
class ReannotateJob:
    """Annotate one scene with measured sites, in memory (a batch job: picklable)."""

    root: str
    sites: tuple[tuple[str, str, bytes, tuple[int, ...]], ...]  # (object, instance, data, shape)

    @classmethod
    def of(cls, root: str, measured: list[InstanceSites]) -> ReannotateJob:
        return cls(
            root,
            tuple(
                (
                    m.object,
                    m.instance,
                    np.ascontiguousarray(m.sites, float).tobytes(),
                    m.sites.shape,
                )
                for m in measured
            ),
        )

    def prepare(self) -> None:
        """Once per worker: open3d imported, the dataset with these sites made (meshes,
        marker table), as an annotate worker does."""
        import annotator.occlusion  # noqa: F401  (imports open3d: seconds)

        _with_sites(self.root, self.sites).marker_table  # noqa: B018  (cached property)

    def __call__(self, scene_id: str) -> dict[str, Any]:
        """``{"annotation": SceneAnnotation}``; a sequence's: ``{"frames": {"<scene>/<frame>":
        SceneAnnotation}}``, each posed frame as a fixed rig's annotation."""
        ds = _with_sites(self.root, self.sites)
        detector = _detector(ds.dictionary)
        scene = ds.scene(scene_id)
        if ds.rig.moving:
            ann = annotate_sequence(ds, scene, detector, settings=ROUND_SETTINGS)
            frames = frame_annotations(ann)
            return {"frames": {f"{scene_id}/{name}": a for name, a in frames.items()}}
        result = annotate_scene(ds, scene, detector, settings=ROUND_SETTINGS)
        return {"annotation": result.annotation}


@lru_cache(maxsize=2)
def _with_sites(root: str, sites: tuple[tuple[str, str, bytes, tuple[int, ...]], ...]) -> Dataset:
    # A worker annotates every scene of a round with one dataset.
    table = {(o, i): np.frombuffer(d, float).reshape(s) for o, i, d, s in sites}
    return with_sites(cached_dataset(root), table)


@lru_cache(maxsize=4)
def _detector(dictionary: str) -> MarkerDetector:
    return MarkerDetector(dictionary)


def measure_in_rounds(
    ds: Dataset,
    scenes: list[Scene],
    detections: dict[str, list[tuple[int, int, np.ndarray]]],
    *,
    settings: SiteSettings,
    workers: int,
    quiet: bool,
) -> Rounds:
    """Measure the sites of ``scenes`` until they settle (see the module docstring)."""
    failed: dict[str, str] = {}

    def annotated(measured: list[InstanceSites], desc: str) -> dict[str, SceneAnnotation]:
        nonlocal failed
        report: BatchReport = run_batch(
            ReannotateJob.of(str(ds.root), measured),
            [s.id for s in scenes],
            workers=workers,
            desc=desc,
            quiet=quiet,
        )
        failed = dict(report.failed)  # these scenes' annotation.json is used instead
        out: dict[str, SceneAnnotation] = {}
        for sid, r in report.done.items():
            out.update(r["frames"] if "frames" in r else {sid: r["annotation"]})
        return out

    annotations = annotated([], "sites: markers")
    shots = units(ds, scenes)  # a sequence's sites are measured on its frames
    measured, spread = measure_instances(
        ds, shots, detections, settings=settings, annotations=annotations
    )
    moves: list[float] = []
    rounds = 1
    while rounds < MAX_ROUNDS and measured:
        annotations = annotated(measured, f"sites: round {rounds + 1}")
        again, _ = measure_instances(
            ds, shots, detections, settings=settings, annotations=annotations, spread=spread
        )
        rounds += 1
        moves.append(rms_move(measured, again))
        measured = again
        if moves[-1] < SETTLED_MM:
            break
    return Rounds(measured, spread, rounds, moves, failed)
