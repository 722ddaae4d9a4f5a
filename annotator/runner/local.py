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

"""

from __future__ import annotations

import multiprocessing
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any

from annotator.errors import UserError
from annotator.runner import threads
from annotator.runner.report import BatchReport, describe_failure, progress_bar, record
from annotator.runner.threads import one_thread_meanwhile


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
            initializer=_worker_start,
            initargs=(os.getpid(), context is None),
        )
        _POOLS.add(pool)
    bar = progress_bar(len(scene_ids), desc, quiet)
    try:
        with one_thread_meanwhile():
            if pool is None:
                for sid in scene_ids:
                    record(report, *_run_one(job, sid))
                    bar.update()
            else:
                try:
                    futures = [pool.submit(_run_one, job, sid) for sid in scene_ids]
                    for fut in as_completed(futures):
                        record(report, *fut.result())
                        bar.update()
                except BaseException:
                    _stop_workers(pool)
                    raise
                finally:
                    _POOLS.discard(pool)
                pool.shutdown(wait=True)
    finally:
        bar.close()
    return report


_POOLS: set[ProcessPoolExecutor] = set()


def kill_workers() -> None:
    """Kill every worker process of this process's running batches (last-resort exit path)."""
    for pool in list(_POOLS):
        for proc in list((getattr(pool, "_processes", None) or {}).values()):
            proc.kill()


def _worker_start(parent: int, one_thread: bool) -> None:
    """Runs first in every worker: die with the parent, and (spawned workers) one thread."""
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
