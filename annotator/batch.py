"""Running one job per scene over a dataset: worker processes, progress bar, failure report.

A job is a picklable callable ``job(scene_id) -> dict``; a :class:`~annotator.errors.UserError`
(or any exception) in one scene is recorded as that scene's failure and the batch goes on.
Interrupting (Ctrl-C) stops the batch; what was already written stays (writes are atomic), so
a batch command run again resumes where it stopped.

Parallelism comes from the workers: each runs OpenCV and the ray caster on one thread, so that
N workers are N times as fast (threads inside one process scale much worse).

Worker start-up: importing open3d, loading a dataset and tabulating the cameras' pixel rays
take seconds, which every worker would pay again. A job may have a ``prepare()`` method that
does this work; with several workers on Linux it is called once in the parent and the workers
are forked from it, so that they start ready. (Forked workers must not call
``cv2.setNumThreads``: it waits forever for the parent's OpenCV threads, which a child does
not have. The parent sets one thread before forking instead, and restores its setting after.)
"""

from __future__ import annotations

import multiprocessing
import os
import sys
import traceback
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

from tqdm import tqdm

from annotator.errors import UserError


@dataclass
class BatchReport:
    """Per-scene outcomes: results of the scenes done and one-line errors of the failed ones."""

    done: dict[str, dict[str, Any]] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)

    def print_failures(self) -> None:
        """One line per failed scene on stderr, in scene order."""
        for sid, err in sorted(self.failed.items()):
            print(f"failed: scene {sid}: {err}", file=sys.stderr)


def _run_one(
    job: Callable[[str], dict[str, Any]], scene_id: str
) -> tuple[str, dict[str, Any] | None, str | None]:
    try:
        return scene_id, job(scene_id), None
    except UserError as exc:
        return scene_id, None, str(exc)
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # one bad scene must not stop the batch; report it in one line
        last = traceback.extract_tb(exc.__traceback__)[-1]
        return scene_id, None, f"{type(exc).__name__}: {exc} (at {last.filename}:{last.lineno})"


def run_batch(
    job: Callable[[str], dict[str, Any]],
    scene_ids: Sequence[str],
    *,
    workers: int = 1,
    desc: str = "scenes",
    quiet: bool = False,
) -> BatchReport:
    """Run ``job`` on every scene id, in ``workers`` processes of one thread each (OpenCV and
    ray casting), with a progress bar on stderr."""
    report = BatchReport()
    pool = None
    if workers > 1 and len(scene_ids) > 1:
        context = _fork_context()
        prepare = getattr(job, "prepare", None)
        if context is not None and prepare is not None:
            prepare()
        # Created before the progress bar: a process with threads (tqdm's monitor) should not
        # fork. Forked workers inherit the thread settings; spawned ones set their own.
        pool = ProcessPoolExecutor(
            max_workers=workers,
            mp_context=context,
            initializer=None if context is not None else _one_thread,
        )
    bar = tqdm(
        total=len(scene_ids),
        desc=desc,
        unit="scene",
        disable=quiet or not sys.stderr.isatty(),
        file=sys.stderr,
    )
    try:
        with _one_thread_meanwhile():
            if pool is None:
                for sid in scene_ids:
                    _record(report, *_run_one(job, sid))
                    bar.update()
            else:
                with pool:
                    futures = [pool.submit(_run_one, job, sid) for sid in scene_ids]
                    for fut in as_completed(futures):
                        _record(report, *fut.result())
                        bar.update()
    finally:
        bar.close()
    return report


def available_cpus() -> int:
    """Cores this process may run on (the default number of workers)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _fork_context() -> multiprocessing.context.BaseContext | None:
    """Fork on Linux (workers inherit the prepared parent); the platform's default elsewhere
    (fork is unsafe on macOS)."""
    if sys.platform.startswith("linux"):
        return multiprocessing.get_context("fork")
    return None


def _one_thread() -> None:
    import cv2

    from annotator.rendering.raycast import set_threads

    cv2.setNumThreads(1)
    set_threads(1)


@contextmanager
def _one_thread_meanwhile() -> Iterator[None]:
    import cv2

    from annotator.rendering import raycast

    before = cv2.getNumThreads(), raycast.get_threads()
    _one_thread()
    try:
        yield
    finally:
        cv2.setNumThreads(before[0])
        raycast.set_threads(before[1])


def _record(
    report: BatchReport, sid: str, result: dict[str, Any] | None, error: str | None
) -> None:
    if error is not None:
        report.failed[sid] = error
    else:
        report.done[sid] = result or {}
