"""Sites measured over a dataset's annotated scenes, the whole ``annotator sites`` run short
of printing and asking (:func:`measure_sites`): the markers read in every scene (one batch job
per scene), the sites solved from them (:func:`~annotator.sites.measure.measure_instances`),
and each object.yaml's new text with its diff, written by :meth:`SitesSummary.write`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from annotator.dataset import Dataset, Scene, as_dataset, require_meshes
from annotator.dataset.model import SCENES_DIR
from annotator.dataset.records import SceneAnnotation
from annotator.dataset.selection import EVERY_SCENE, matching_scenes
from annotator.dataset.validity import unknown_name
from annotator.errors import UserError
from annotator.io.atomic import write_together
from annotator.io.documents import unified_diff
from annotator.runner import BatchReport, run_batch
from annotator.sites.measure import DetectJob, InstanceSites, units, updated_object_yaml
from annotator.sites.rounds import measure_in_rounds
from annotator.sites.solve import SiteSettings
from annotator.summary import failure_lines


@dataclass(frozen=True)
class ObjectUpdate:
    """One object.yaml with its instances' measured sites: its new text and the diff."""

    path: Path
    text: str
    diff: str


@dataclass(frozen=True)
class SitesSurvey:
    """The measurement: the scenes it used, the batch's outcome per scene, the instances
    measured, the gluing spread (mm, degrees; None if no marker was seen), and the
    object.yaml files that change."""

    scenes: list[Scene]
    report: BatchReport
    measured: list[InstanceSites]
    spread: tuple[float, float] | None
    updates: list[ObjectUpdate]
    rounds: int = 1  # measurements made until the sites settled (annotator.sites.rounds)
    moves: tuple[float, ...] = ()  # the largest site move of each round after the first, mm

    @property
    def flagged(self) -> int:
        """Markers flagged, over every instance."""
        return sum(len(m.flags) for m in self.measured)


def annotated_scenes(ds: Dataset, pattern: str) -> list[Scene]:
    """The scenes whose id matches ``pattern`` (fnmatch) and that carry an annotation.json."""
    return [s for s in matching_scenes(ds, pattern, required=False) if s.annotation_path.exists()]


def survey_sites(
    ds: Dataset, scenes: list[Scene], *, max_move_mm: float, workers: int, quiet: bool
) -> SitesSurvey:
    """Read the markers of ``scenes`` (annotated), measure every instance's sites until they
    settle (:func:`annotator.sites.rounds.measure_in_rounds`), and the new text of each
    object.yaml whose sites change."""
    require_meshes(ds)
    report = run_batch(
        DetectJob(str(ds.root)),
        [u.id for u in units(ds, scenes)],  # a sequence's frames, each on its own
        workers=workers,
        desc="sites: markers",
        quiet=quiet,
    )
    detections = {sid: r["markers"] for sid, r in report.done.items()}
    for unit in list(report.failed):  # a frame that failed fails its sequence
        owner = unit.rsplit("/", 1)[0] if ds.rig.moving else unit
        report.failed.setdefault(owner, report.failed.pop(unit))
    usable = []
    for scene in scenes:
        problem = scene.id in report.failed or _unknown_instance(ds, scene)
        if problem:  # its poses cannot be matched to sites: the rest goes on
            if isinstance(problem, str):
                report.failed[scene.id] = problem
            continue
        usable.append(scene)
    found = measure_in_rounds(
        ds,
        usable,
        detections,
        settings=SiteSettings(max_move_mm=max_move_mm),
        workers=workers,
        quiet=quiet,
    )
    for sid, why in found.failed.items():  # its annotation.json served in the later rounds
        report.failed[sid] = f"annotated again with the measured sites: {why}"
    return SitesSurvey(
        scenes,
        report,
        found.measured,
        found.spread,
        object_updates(ds, found.measured),
        found.rounds,
        tuple(found.moves),
    )


def _unknown_instance(ds: Dataset, scene: Scene) -> str | None:
    """Why the scene's annotation.json cannot be used (it names an instance the dataset does
    not have, or it is unreadable), or None."""
    try:
        instances = SceneAnnotation.read(scene.annotation_path).instances
    except UserError as exc:
        return str(exc)
    for inst in instances:
        why = unknown_name(ds, inst.object, inst.instance)
        if why is not None:
            return f"{scene.annotation_path}: {why}; annotate the scene again"
    return None


def object_updates(ds: Dataset, measured: list[InstanceSites]) -> list[ObjectUpdate]:
    """The object.yaml files that the ``measured`` sites change, in the order their objects
    were first measured."""
    by_object: dict[str, list[InstanceSites]] = {}
    for m in measured:
        by_object.setdefault(m.object, []).append(m)
    updates = []
    for name, ms in by_object.items():
        path = ds.objects[name].folder / "object.yaml"
        old, new = updated_object_yaml(path, ms)
        if old != new:
            updates.append(
                ObjectUpdate(path, new, unified_diff(old, new, path, label="measured sites"))
            )
    return updates


def instance_lines(m: InstanceSites) -> list[str]:
    """One instance's table as ``annotator sites`` prints it: its corner RMS before and after,
    then each site seen (or flagged) with its correction and 1-sigma."""
    sol = m.solution
    head = (
        f"{m.key}: {len(sol.poses)} scenes, {sol.used} marker views used"
        f"{f' ({sol.left_out} left out)' if sol.left_out else ''}, corner RMS "
        f"{sol.rms_before:.2f} -> {sol.rms_after:.2f} px"
        + (f"; not observable: {', '.join(sol.unobservable)}" if sol.unobservable else "")
    )
    out = [head, "  site    id  scenes   du mm (1-sigma)   dv mm (1-sigma)   turn deg (1-sigma)"]
    for k, mid in enumerate(m.marker_ids):
        if sol.seen[k] == 0 and k not in m.flags:
            continue
        du, dv, dt = sol.corrections[k]
        su, sv, st = sol.std[k]
        cells = (
            f"  {k:4d}  {mid:4d}  {sol.seen[k]:6d}   {du:+6.2f} ({su:4.2f})     "
            f"{dv:+6.2f} ({sv:4.2f})     {np.degrees(dt):+6.2f} ({np.degrees(st):4.2f})"
        )
        out.append(cells + (f"   ! {m.flags[k]}" if k in m.flags else ""))
    return out


@dataclass
class SitesSummary:
    """What :func:`measure_sites` measured (:attr:`survey`) and which object.yaml files
    :meth:`write` wrote; :meth:`to_json` is ``annotator sites --json``.

    >>> from pathlib import Path
    >>> from annotator.runner import BatchReport
    >>> from annotator.sites.survey import SitesSurvey
    >>> survey = SitesSurvey(scenes=[], report=BatchReport(), measured=[], spread=None, updates=[])
    >>> s = SitesSummary(survey, Path("ds"))
    >>> s.text()
    'sites: 0 instances measured from 0 scenes, 0 markers flagged; nothing written'
    >>> s.exit_status()
    0
    """

    survey: SitesSurvey
    root: Path
    #: The object.yaml files written, and whether the user declined any.
    written: list[str] = field(default_factory=list)
    declined: bool = False
    #: Whether :meth:`write` was called (not: ``--dry-run``).
    offered: bool = False

    def write(self, *, confirm: Callable[[Path], bool] | None = None) -> None:
        """Write every object.yaml whose sites change, all together
        (:func:`annotator.io.atomic.write_together`): those ``confirm`` says yes to, asked
        about each first (every question before any file is written), or all of them."""
        self.offered = True
        chosen = {}
        for update in self.survey.updates:
            if confirm is None or confirm(update.path):
                chosen[update.path] = update.text
                self.written.append(str(update.path))
            else:
                self.declined = True
        if self.survey.updates:
            write_together(self.root, chosen)

    def preview(self) -> str:
        """What is shown before asking to write: every instance's table, then the diffs."""
        lines = [line for m in self.survey.measured for line in instance_lines(m)]
        lines += [u.diff.removesuffix("\n") for u in self.survey.updates]
        return "\n".join(lines)

    def counts(self) -> dict[str, int]:
        survey = self.survey
        return {
            "scenes": len(survey.scenes),
            "instances": len(survey.measured),
            "flagged_markers": survey.flagged,
            "written": len(self.written),
            "failed": len(survey.report.failed),
        }

    def warnings(self) -> list[str]:
        return failure_lines(self.survey.report.failed)

    def written_paths(self) -> list[Path]:
        return [Path(p) for p in self.written]

    def exit_status(self) -> int:
        return 1 if self.survey.report.failed or self.declined else 0

    def text(self) -> str:
        survey, spread = self.survey, self.survey.spread
        told = (
            ""
            if spread is None
            else f" (gluing moved them by {spread[0]:.2f} mm and {spread[1]:.1f} deg, 1-sigma)"
        )
        settled = (
            f"; {survey.rounds} rounds (the last moved the sites by {survey.moves[-1]:.3f} mm RMS)"
            if survey.moves
            else ""
        )
        unit = "frames" if any("/" in u for u in survey.report.done) else "scenes"
        if self.written:
            outcome = (
                f"wrote {len(self.written)} object.yaml; run `annotator annotate {self.root}` again"
            )
        else:
            dry = not self.offered and survey.updates
            outcome = "nothing written" + (" (--dry-run)" if dry else "")
        return (
            f"sites: {len(survey.measured)} instances measured from {len(survey.report.done)} "
            f"{unit}{told}{settled}, {survey.flagged} markers flagged; {outcome}"
        )

    def to_json(self) -> dict[str, Any]:
        survey, spread = self.survey, self.survey.spread
        return {
            "scenes": len(survey.scenes),
            "glue_spread": None
            if spread is None
            else {"mm": round(spread[0], 4), "deg": round(spread[1], 3)},
            "instances": [m.to_json() for m in survey.measured],
            "rounds": survey.rounds,
            "round_moves_mm": [round(m, 4) for m in survey.moves],
            "flagged_markers": survey.flagged,
            "written": self.written,
            "failures": dict(sorted(survey.report.failed.items())),
        }


def measure_sites(
    ds: Dataset | str | Path,
    *,
    scenes: str = EVERY_SCENE,
    max_move_mm: float = 2.0,
    write: bool = False,
    workers: int = 1,
    quiet: bool = True,
) -> SitesSummary:
    """Measure where every instance's markers really are (markers glued by hand) from the
    annotated scenes of ``ds`` matching ``scenes``: the markers found again in every camera,
    each instance's sites solved until they settle, markers farther than ``max_move_mm``
    from the layout's flagged. With ``write``, the object.yaml files whose sites change are
    written (``annotator annotate`` then uses the measured sites); without, nothing is:
    :meth:`SitesSummary.write` does it later, and each update's diff is in
    ``summary.survey.updates``.

    >>> import shutil, tempfile
    >>> from pathlib import Path
    >>> root = shutil.copytree("sample_scenes", Path(tempfile.mkdtemp()) / "ds")
    >>> survey = measure_sites(root, scenes="000000")  # write=True: into object.yaml
    >>> [i["instance"] for i in survey.to_json()["instances"]][:3]
    ['bracket/01', 'bracket/02', 'bracket/03']

    Raises:
        UserError: no scene matches, none is annotated, or a mesh is unreadable.
    """
    ds = as_dataset(ds, name="ds")
    chosen = annotated_scenes(ds, scenes)
    matching_scenes(ds, scenes)  # none matches: say so
    if not chosen:
        raise UserError(
            "no scene has an annotation.json: run `annotator annotate "
            f"{ds.root}` first (sites are measured from annotated scenes)",
            path=ds.root / SCENES_DIR,
        )
    survey = survey_sites(ds, chosen, max_move_mm=max_move_mm, workers=workers, quiet=quiet)
    summary = SitesSummary(survey, ds.root)
    if write:
        summary.write()
    return summary
