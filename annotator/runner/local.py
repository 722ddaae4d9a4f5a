"""The local runner: one job per scene in worker processes of this machine.

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

Forked workers also inherit the job itself: a scene's task sends only its id. A job may carry
every scene's inputs (a sequence's solution, each frame's depth), and pickling it again for
each of hundreds of scenes costs the parent more than the workers' work on some of them.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from annotator.errors import UserError
from annotator.runner import heap, threads
from annotator.runner.report import BatchReport, describe_failure, progress_bar, record
from annotator.runner.threads import one_thread_meanwhile

#: In a worker: where it says which scene it starts (the parent learns which scenes a dead
#: worker was running).
_STARTED: Any = None

#: The failure of a scene whose worker process died under it, twice.
WORKER_DIED = (
    "its worker process died while working on it (killed by the system: out of memory?); "
    "try it again with fewer --workers"
)


#: The jobs of this process's running batches, by key: what forked workers inherit
#: (:func:`_run_inherited`).
_INHERITED: dict[int, Callable[[str], dict[str, Any]]] = {}


def _run_inherited(key: int, scene_id: str) -> tuple[str, dict[str, Any] | None, str | None]:
    """:func:`_run_one` of the job the worker inherited from its parent when forked."""
    return _run_one(_INHERITED[key], scene_id)


def _run_one(
    job: Callable[[str], dict[str, Any]], scene_id: str
) -> tuple[str, dict[str, Any] | None, str | None]:
    if _STARTED is not None:
        _STARTED.put(scene_id)
    try:
        return scene_id, job(scene_id), None
    except UserError as exc:
        return scene_id, None, str(exc)
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # one bad scene must not stop the batch; report it in one line
        return scene_id, None, describe_failure(exc)


def run_local(
    job: Callable[[str], dict[str, Any]],
    scene_ids: Sequence[str],
    *,
    workers: int = 1,
    desc: str = "scenes",
    quiet: bool = False,
) -> BatchReport:
    """Run ``job`` on every scene id, in ``workers`` processes of one thread each (OpenCV and
    ray casting), with a progress bar on stderr.

    A worker process that dies (the system's out-of-memory killer, say) takes only its scene
    down: the scenes the workers were running then are tried again, each alone in a new
    worker, and the one whose worker dies again is reported failed (:data:`WORKER_DIED`);
    the others go on as before."""
    report = BatchReport()
    heap.keep_freed_memory()  # here, and in the workers forked from here
    if workers <= 1 or len(scene_ids) <= 1:
        bar = progress_bar(len(scene_ids), desc, quiet)
        try:
            with one_thread_meanwhile():
                for sid in scene_ids:
                    record(report, *_run_one(job, sid))
                    bar.update()
        finally:
            bar.close()
        return report
    context = _fork_context()
    prepare = getattr(job, "prepare", None)
    if context is not None and prepare is not None:
        prepare()
    if context is not None:
        heap.release_free_memory()  # the workers' first pages fresh, not copied from ours
    # Before any worker is forked (the pools start theirs on the first task).
    key = id(job)
    if context is not None:
        _INHERITED[key] = job
    # The first pool is made before the progress bar: a process with threads (tqdm's
    # monitor) should not fork.
    first = _Pool(context, workers)
    bar = progress_bar(len(scene_ids), desc, quiet)
    try:
        with one_thread_meanwhile():
            left, running = first.run(job, scene_ids, report, bar)
            while left:
                for sid in sorted(running):  # each alone: the one that kills again is it
                    alone, _ = _Pool(context, 1).run(job, [sid], report, bar)
                    if alone:
                        record(report, sid, None, WORKER_DIED)
                        bar.update()
                rest = [sid for sid in left if sid not in running]
                left, running = (
                    _Pool(context, workers).run(job, rest, report, bar) if rest else ([], set())
                )
    finally:
        bar.close()
        _INHERITED.pop(key, None)
    return report


class _Pool:
    """Worker processes for one round of scenes (a round ends early if a worker dies)."""

    def __init__(self, context: multiprocessing.context.BaseContext | None, workers: int) -> None:
        ctx = context or multiprocessing.get_context()
        #: Forked workers: they have the parent's jobs (:data:`_INHERITED`).
        self.inherits = ctx.get_start_method() == "fork"
        self.started = ctx.SimpleQueue()
        # Forked workers inherit the thread settings; spawned ones set their own.
        self.pool = ProcessPoolExecutor(
            max_workers=workers,
            mp_context=context,
            initializer=_worker_start,
            initargs=(os.getpid(), context is None, self.started),
        )
        _POOLS.add(self.pool)

    def run(
        self,
        job: Callable[[str], dict[str, Any]],
        scene_ids: Sequence[str],
        report: BatchReport,
        bar: Any,
    ) -> tuple[list[str], set[str]]:
        """Run the scenes; if a worker died, the scenes not finished and, of them, those
        that had started (the dead worker's among them)."""
        done: set[str] = set()
        started: set[str] = set()
        broken = False
        try:
            key = id(job)
            if self.inherits and _INHERITED.get(key) is job:
                futures = [self.pool.submit(_run_inherited, key, sid) for sid in scene_ids]
            else:
                futures = [self.pool.submit(_run_one, job, sid) for sid in scene_ids]
            for fut in as_completed(futures):
                try:
                    result = fut.result()
                except BrokenProcessPool:
                    broken = True
                    break
                record(report, *result)
                done.add(result[0])
                bar.update()
        except BaseException:
            _stop_workers(self.pool)
            raise
        finally:
            _POOLS.discard(self.pool)
        if broken:
            _stop_workers(self.pool)
        else:
            self.pool.shutdown(wait=True)
        while not self.started.empty():
            started.add(self.started.get())
        self.started.close()
        left = [sid for sid in scene_ids if sid not in done]
        return left, started & set(left)


_POOLS: set[ProcessPoolExecutor] = set()


def kill_workers() -> None:
    """Kill every worker process of this process's running batches (last-resort exit path)."""
    for pool in list(_POOLS):
        for proc in list((getattr(pool, "_processes", None) or {}).values()):
            proc.kill()


def _worker_start(parent: int, one_thread: bool, started: Any) -> None:
    """Runs first in every worker: die with the parent, and (spawned workers) one thread."""
    global _STARTED
    _STARTED = started
    if sys.platform.startswith("linux"):
        import ctypes
        import signal

        PR_SET_PDEATHSIG = 1
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    if os.getppid() != parent:  # the parent died before the line above took effect
        os._exit(1)
    # Elsewhere (and as a second guard), a watcher notices the parent's death within a second.
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True).start()
    if one_thread:
        threads.one_thread()
        heap.keep_freed_memory()


def _exit_with_parent(parent: int) -> None:
    while True:
        time.sleep(0.5)
        if os.getppid() != parent:
            os._exit(1)


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """After an interruption (Ctrl-C, SIGTERM) or a crash: kill the workers at once.

    ``shutdown`` alone would wait for the running scenes and then start the queued ones.
    """
    # The executor keeps no public handle on its processes (Python < 3.14), and forgets them
    # on shutdown: take them first.
    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        if proc.is_alive():
            proc.kill()
    for proc in procs:
        proc.join(timeout=2.0)
    pool.shutdown(wait=True)


def _fork_context() -> multiprocessing.context.BaseContext | None:
    """Fork on Linux (workers inherit the prepared parent); the platform's default elsewhere
    (fork is unsafe on macOS)."""
    if sys.platform.startswith("linux"):
        return multiprocessing.get_context("fork")
    return None
