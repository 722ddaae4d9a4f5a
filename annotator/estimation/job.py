"""One scene of ``annotator estimate`` (and of the benchmark) as a batch job
(:func:`annotator.runner.run_batch`): picklable, prepared once before the workers fork."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from annotator.dataset import cached_dataset
from annotator.estimation.estimator import PPFSettings, estimate_scene, train_all
from annotator.estimation.results import result_rows
from annotator.runner.files import description_files


@dataclass(frozen=True)
class EstimateJob:
    """Estimate every variant on one scene of the dataset at ``root``.

    The result of a scene is ``{"rows": [[ResultRow, ...] per variant], "seconds": [...]}``.
    """

    root: str
    variants: tuple[PPFSettings, ...]

    def prepare(self) -> None:
        """Load the dataset, train every part and tabulate the depth camera's rays, once in
        the parent: forked workers start with all of it."""
        ds = cached_dataset(self.root)
        train_all(ds, self.variants)
        cam = ds.rig.depth_camera
        if cam is not None:
            cam.pixel_rays()
            cam.pixel_rays(2)
        ds.background_depth  # noqa: B018  (cached property: read once, before forking)

    # What a scene's work reads (for runs on a Ray cluster without the dataset's disk, see
    # annotator.runner.job): the results travel back in the job's return value, no file is written.

    def shared_files(self) -> list[str]:
        """The dataset description (dataset.yaml, objects, background depth)."""
        return description_files(cached_dataset(self.root))

    def scene_files(self, scene_id: str) -> list[str]:
        """The scene's depth map."""
        return [f"scenes/{scene_id}/depth.png"]

    def output_files(self, scene_id: str) -> list[str]:
        """None: the results come back as the scene's result."""
        return []

    def __call__(self, scene_id: str) -> dict[str, Any]:
        ds = cached_dataset(self.root)
        estimates = estimate_scene(ds, scene_id, self.variants)
        objects = list(ds.objects)
        return {
            "rows": [result_rows(scene_id, e.hypotheses, objects, e.seconds) for e in estimates],
            "seconds": [e.seconds for e in estimates],
        }
