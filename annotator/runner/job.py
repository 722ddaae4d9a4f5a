"""What a job that can run on a Ray cluster declares (``--ray ADDRESS`` on the batch commands).

Nothing here assumes a shared file system. The driver (the machine that runs the command
and holds the dataset) reads every file a scene needs and sends it as bytes through Ray's
object store; a task runs the unchanged per-scene job on a private replica of those files
in a temporary folder of its node, and sends back the files the job wrote, as bytes; the
driver writes them with the same atomic writes as a local batch. The dataset description
(dataset.yaml, every object.yaml and mesh, the background depth map) is put into the object
store once and unpacked once per worker process.

A job that can run this way is a picklable dataclass with a ``root`` field (the dataset
folder; a task runs a copy whose ``root`` is its replica) that declares its files, relative
to ``root`` (see :class:`DistributableJob`). A job that writes into another folder than it
reads (``synth --twin``) has an ``out`` field too: its outputs are then relative to ``out``,
and a task runs with ``out`` an empty folder of its own. Scene folders are
``scenes/<scene_id>`` (docs/FORMAT.md).

See :mod:`annotator.runner.files` (files as bytes) and :mod:`annotator.runner.ray_cluster`
(joining the cluster, tasks, retries, cancellation). Ray itself is imported only when
``--ray`` is given: it is an optional extra, ``pip install 'bin-annotator[ray]'``.
"""

from __future__ import annotations

from typing import Any, Protocol

#: How long (s) a run waits by default for a cluster that has no CPU for its tasks (its
#: only worker node died, or none joined) before it stops and lists the unfinished scenes.
RAY_WAIT_S = 60.0


class DistributableJob(Protocol):
    """A per-scene job that can run where the dataset is not (see the module docstring)."""

    root: str

    def shared_files(self) -> list[str]:
        """Files every scene needs (the dataset description), read once by the driver."""
        ...

    def scene_files(self, scene_id: str) -> list[str]:
        """The scene's input files; those that do not exist are left out (the job then
        reports them missing, as it does locally)."""
        ...

    def output_files(self, scene_id: str) -> list[str]:
        """What the job writes (under ``out`` if the job has that field, else under
        ``root``), in writing order: a file that the job did not leave behind
        is deleted on the driver's side (after the writes); a path ending in ``/`` stands for
        every file under that folder."""
        ...

    def __call__(self, scene_id: str) -> dict[str, Any]:
        """Process one scene under ``root`` (reads its inputs, writes its outputs)."""
        ...
