"""Running one job per scene over a dataset, here or on a Ray cluster.

A job is a picklable callable ``job(scene_id) -> dict``; a :class:`~annotator.errors.UserError`
(or any exception) in one scene is recorded as that scene's failure and the batch goes on.
Interrupting (Ctrl-C) stops the batch; what was already written stays (writes are atomic), so
a batch command run again resumes where it stopped.

Two backends, siblings: :mod:`.local` (worker processes of this machine) and
:mod:`.ray_cluster` (one Ray task per scene; the job declares its files, :mod:`.job`). Both
give the same :class:`~.report.BatchReport`, the same progress bar and the same files.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from annotator.runner.job import RAY_WAIT_S, DistributableJob
from annotator.runner.report import BatchReport
from annotator.runner.threads import available_cpus

__all__ = [
    "RAY_WAIT_S",
    "BatchReport",
    "DistributableJob",
    "available_cpus",
    "run_batch",
]


def run_batch(
    job: Callable[[str], dict[str, Any]],
    scene_ids: Sequence[str],
    *,
    workers: int = 1,
    desc: str = "scenes",
    quiet: bool = False,
    ray_address: str | None = None,
    ray_wait: float | None = None,
) -> BatchReport:
    """Run ``job`` on every scene id: in ``workers`` local processes of one thread each
    (:func:`~.local.run_local`), or with ``ray_address`` (``"auto"`` or a cluster's address)
    as tasks on that Ray cluster, ``workers`` then ignored; ``job`` must then declare its
    files (:class:`DistributableJob`), and ``ray_wait`` bounds the wait (s) for a cluster
    that has no CPU for the tasks (default :data:`RAY_WAIT_S`)."""
    # The backends are imported when a batch runs: multiprocessing and Ray cost the start-up
    # of the commands that only read and print.
    if ray_address is not None:
        from annotator.runner.ray_cluster import run_on_ray

        return run_on_ray(
            job, scene_ids, address=ray_address, desc=desc, quiet=quiet, wait_s=ray_wait
        )
    from annotator.runner.local import run_local

    return run_local(job, scene_ids, workers=workers, desc=desc, quiet=quiet)
