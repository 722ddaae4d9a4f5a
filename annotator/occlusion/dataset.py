"""Occlusion over a whole dataset: :func:`compute_occlusion`, what ``annotator occlusion``
runs (the per-scene work is :class:`~annotator.occlusion.job.VisibilityJob`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from annotator.dataset import Dataset, as_dataset
from annotator.dataset.selection import EVERY_SCENE, matching_scenes
from annotator.occlusion import DEPTH_TOLERANCE_MM
from annotator.occlusion.job import VISIBILITY_FILE, VisibilityJob, is_fresh
from annotator.runner import BatchReport, run_batch
from annotator.summary import failure_lines


@dataclass
class OcclusionSummary:
    """What :func:`compute_occlusion` did; :meth:`to_json` is ``annotator occlusion --json``.

    Attributes:
        report: Per-scene outcomes (done, and failed: one line each).
        skipped: Scenes whose visibility.json was up to date.

    >>> from annotator.runner import BatchReport
    >>> s = OcclusionSummary(BatchReport({"000000": {}}), skipped=3)
    >>> s.text()
    'occlusion: 1 scenes done, 3 up to date, 0 failed'
    >>> s.to_json()
    {'done': 1, 'skipped': 3, 'failed': 0, 'failures': {}}
    """

    report: BatchReport
    skipped: int
    #: The visibility.json files written now, in scene order.
    written: list[Path] = field(default_factory=list)

    def counts(self) -> dict[str, int]:
        return {
            "done": len(self.report.done),
            "skipped": self.skipped,
            "failed": len(self.report.failed),
        }

    def warnings(self) -> list[str]:
        return failure_lines(self.report.failed)

    def written_paths(self) -> list[Path]:
        return list(self.written)

    def to_json(self) -> dict[str, Any]:
        return {**self.counts(), "failures": self.report.failed}

    def text(self) -> str:
        return (
            f"occlusion: {len(self.report.done)} scenes done, {self.skipped} up to date, "
            f"{len(self.report.failed)} failed"
        )

    def exit_status(self) -> int:
        return 1 if self.report.failed else 0


def compute_occlusion(
    ds: Dataset | str | Path,
    *,
    poses: str = "annotation",
    scenes: str = EVERY_SCENE,
    depth_tolerance: float = DEPTH_TOLERANCE_MM,
    force: bool = False,
    workers: int = 1,
    quiet: bool = True,
    ray_address: str | None = None,
    ray_wait: float | None = None,
) -> OcclusionSummary:
    """Write ``visibility.json`` (every instance's mask pixel counts, boxes and occlusion
    rates per camera) into every scene of ``ds`` matching ``scenes``, from its
    ``annotation`` or ``gt`` poses, the depth test within ``depth_tolerance`` mm.

    A scene whose visibility.json was made from the same poses and tolerance after they and
    the depth last changed is skipped, unless ``force``. The scenes run in ``workers``
    processes or on a Ray cluster (``ray_address``); a scene that fails is reported, the
    others go on.

    >>> import shutil, tempfile
    >>> from pathlib import Path
    >>> root = shutil.copytree("sample_scenes", Path(tempfile.mkdtemp()) / "ds")
    >>> compute_occlusion(root, scenes="000000").to_json()
    {'done': 1, 'skipped': 0, 'failed': 0, 'failures': {}}
    >>> (root / "scenes" / "000000" / "visibility.json").is_file()
    True

    Raises:
        UserError: no scene matches ``scenes``.
    """
    ds = as_dataset(ds, name="ds")
    chosen = matching_scenes(ds, scenes)
    todo = [s.id for s in chosen if force or not is_fresh(ds, s, poses, depth_tolerance)]
    report = run_batch(
        VisibilityJob(str(ds.root), poses, depth_tolerance),
        todo,
        workers=workers,
        desc="occlusion",
        quiet=quiet,
        ray_address=ray_address,
        ray_wait=ray_wait,
    )
    written = [ds.scene(sid).path / VISIBILITY_FILE for sid in sorted(report.done)]
    return OcclusionSummary(report, len(chosen) - len(todo), written)
