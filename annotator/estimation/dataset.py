"""The baseline estimator over a whole dataset: :func:`estimate_dataset`, what
``annotator estimate`` runs (the per-scene work is :class:`~annotator.estimation.job.EstimateJob`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from annotator.dataset import Dataset, load_dataset, require_meshes
from annotator.dataset.selection import EVERY_SCENE, matching_scenes
from annotator.errors import UserError
from annotator.estimation.estimator import PPFSettings
from annotator.estimation.job import EstimateJob
from annotator.estimation.results import ResultRow, coco_path, coco_results, write_results
from annotator.io.atomic import write_json
from annotator.io.output_folder import check_output_files
from annotator.runner import BatchReport, run_batch
from annotator.summary import failure_lines


@dataclass
class EstimateSummary:
    """What :func:`estimate_dataset` wrote; :meth:`to_json` is ``annotator estimate --json``.

    Attributes:
        method: The variant's name (``PPF``, ``PPF sym``, ``PPF PP``, ``PPF sym PP``).
        out: The results file written.
        coco: The same hypotheses as COCO results (boxes and masks), beside it.
        scenes: Scenes matching the pattern.
        report: Per-scene outcomes (done: their rows and time; failed: one line each).
        rows: Every result written, scene by scene.

    >>> from pathlib import Path
    >>> from annotator.runner import BatchReport
    >>> report = BatchReport({"000000": {"seconds": [2.0]}})
    >>> s = EstimateSummary("PPF", Path("ppf.csv"), Path("ppf.json"), 1, report, rows=[])
    >>> s.counts()
    {'scenes': 1, 'done': 1, 'failed': 0, 'results': 0}
    >>> [str(p) for p in s.written_paths()]
    ['ppf.csv', 'ppf.json']
    """

    method: str
    out: Path
    coco: Path
    scenes: int
    report: BatchReport
    rows: list[ResultRow]

    @property
    def seconds_per_scene(self) -> float:
        """The mean time of a scene on one worker, s."""
        seconds = [self.report.done[sid]["seconds"][0] for sid in self.report.done]
        return round(sum(seconds) / max(len(seconds), 1), 3)

    def counts(self) -> dict[str, int]:
        return {
            "scenes": self.scenes,
            "done": len(self.report.done),
            "failed": len(self.report.failed),
            "results": len(self.rows),
        }

    def warnings(self) -> list[str]:
        return failure_lines(self.report.failed)

    def written_paths(self) -> list[Path]:
        return [self.out, self.coco]

    def to_json(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "out": str(self.out),
            "coco": str(self.coco),
            **self.counts(),
            "seconds_per_scene": self.seconds_per_scene,
            "failures": dict(sorted(self.report.failed.items())),
        }

    def exit_status(self) -> int:
        return 1 if self.report.failed else 0

    def text(self) -> str:
        return (
            f"estimate ({self.method}): {len(self.rows)} results for {len(self.report.done)} "
            f"scenes written to {self.out} (COCO boxes and masks: {self.coco}), "
            f"{len(self.report.failed)} failed; "
            f"{self.seconds_per_scene} s per scene (one worker)"
        )


def estimate_dataset(
    ds: Dataset | str | Path,
    out: str | Path,
    *,
    settings: PPFSettings | None = None,
    scenes: str = EVERY_SCENE,
    workers: int = 1,
    quiet: bool = True,
    ray_address: str | None = None,
    ray_wait: float | None = None,
    overwrite: bool = False,
) -> EstimateSummary:
    """Estimate the pose of every part in every scene of ``ds`` matching ``scenes`` from its
    depth map alone, and write the hypotheses to ``out`` as one BOP results CSV (what
    ``annotator evaluate DATASET --results OUT`` scores) and, beside it (``OUT.json``), as
    COCO results: each hypothesis's silhouette box and mask in the undistorted reference
    camera (what ``--coco-results`` scores).

    >>> import tempfile
    >>> from pathlib import Path
    >>> from annotator import SynthSettings, synthesize_scenes
    >>> root = Path(tempfile.mkdtemp())  # a small rendered scene of three bricks
    >>> settings = SynthSettings(parts=("brick",), scenes=1, instances=(3, 3), size=(320, 256))
    >>> _ = synthesize_scenes(root / "synth", settings)
    >>> s = estimate_dataset(root / "synth", root / "ppf.csv")
    >>> s.to_json()["done"], (root / "ppf.csv").is_file(), (root / "ppf.json").is_file()
    (1, True, True)

    Args:
        settings: The estimator's variant (:class:`~annotator.estimation.PPFSettings`;
            default: plain PPF, mean shift in SE(3), no post-processing).
        workers, quiet, ray_address, ray_wait: As :func:`annotator.runner.run_batch`.
        overwrite: Replace ``out`` and ``OUT.json`` if they exist (refused otherwise).

    Raises:
        UserError: ``out`` may not be written (or exists, without ``overwrite``), the rig has no depth camera or is a moving
            one, no scene matches, or a mesh is unreadable.
    """
    settings = settings or PPFSettings()
    out = Path(out)
    if out.is_dir():
        raise UserError("is a folder; give a file name for the results CSV", path=out)
    if not out.parent.is_dir():
        raise UserError("the folder to write the results in does not exist", path=out)
    check_output_files(
        [("OUT", out), ("OUT's COCO", coco_path(out))],
        datasets=[ds.root if isinstance(ds, Dataset) else ds],
        overwrite=overwrite,
    )
    ds = ds if isinstance(ds, Dataset) else load_dataset(ds)
    if ds.rig.depth is None:
        raise UserError(
            "the rig has no depth camera (rig.depth): the estimator works on depth maps",
            path=ds.root / "dataset.yaml",
        )
    if ds.rig.moving:
        raise UserError(
            "the rig is a moving one (rig.moving): the baseline estimator works on a fixed "
            "rig's scenes, one shot each, not on sequences",
            path=ds.root / "dataset.yaml",
        )
    chosen = matching_scenes(ds, scenes)
    require_meshes(ds)
    ds.background_depth  # noqa: B018  (an unreadable background is a dataset error: now)
    report = run_batch(
        EstimateJob(str(ds.root), (settings,)),
        [s.id for s in chosen],
        workers=workers,
        desc=f"estimate ({settings.label})",
        quiet=quiet,
        ray_address=ray_address,
        ray_wait=ray_wait,
    )
    rows = [row for sid in sorted(report.done) for row in report.done[sid]["rows"][0]]
    write_results(out, rows)
    _write_coco(ds, rows, coco_path(out))
    return EstimateSummary(settings.label, out, coco_path(out), len(chosen), report, rows)


def _write_coco(ds: Dataset, rows: list[ResultRow], path: Path) -> None:
    """The hypotheses as COCO results, in the reference camera without distortion."""
    from annotator.export.undistort import pinhole_rig

    cam = pinhole_rig(ds.rig).cameras[0]
    meshes = [ds.objects[name].mesh for name in ds.objects]
    write_json(path, coco_results(rows, meshes, cam.K, cam.width, cam.height))
