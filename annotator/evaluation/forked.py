"""Share of a list of work items done in forked processes beside this one.

BOP's scores spend their time in numpy and in open3d's ray casting, which holds the GIL:
threads do not help, processes do. A forked child starts at once with everything this
process has read (images, meshes, their ray-casting scenes), so it pays for itself on work
of a second or more. Each process takes every n-th item; each one's result comes back
whole, and the caller merges them: the numbers do not depend on who computed what.

Everything runs on one thread per process meanwhile (OpenCV, the ray caster, BLAS), set in
this process before forking, as :mod:`annotator.runner.local` does: a child must not change
OpenCV's threads itself. A child that fails or dies leaves its share to this process, which
computes it (and raises what it raises).

Fork exists on Linux only (and is unsafe on macOS): elsewhere everything runs here.
"""

from __future__ import annotations

import multiprocessing
import sys
import warnings
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

from annotator.runner.threads import available_cpus, one_thread_meanwhile

T = TypeVar("T")
R = TypeVar("R")


def process_count(wanted: int | None = None) -> int:
    """Processes to share work between: ``wanted`` (default: every core this process may
    run on); 1 where processes are not forked, and in a daemonic process (a pool's worker),
    which may not have children."""
    if not sys.platform.startswith("linux") or multiprocessing.current_process().daemon:
        return 1
    return max(1, available_cpus() if wanted is None else int(wanted))


def in_processes(
    work: Callable[[Sequence[T], Callable[[], Any] | None], R],
    items: Sequence[T],
    processes: int,
    progress: Callable[[], Any] | None = None,
) -> list[R]:
    """``work(share, progress)`` on ``processes`` shares of ``items`` (every n-th item),
    the first here and the others in forked children; their results in the shares' order.
    ``progress`` is called per item of this process's share, and per item of a child's once
    it is back."""
    n = min(max(1, processes), len(items)) if items else 1
    if n == 1 or process_count(n) == 1:
        return [work(items, progress)]
    shares = [items[k::n] for k in range(n)]
    ctx = multiprocessing.get_context("fork")
    children = []
    with one_thread_meanwhile(), warnings.catch_warnings():
        # Python 3.12+ warns of forking a process with threads: the children use no lock
        # of another thread (no Python threads run here; open3d's pool is not waited on).
        warnings.filterwarnings("ignore", message=".*fork.*", category=DeprecationWarning)
        for share in shares[1:]:
            reader, writer = ctx.Pipe(duplex=False)
            child = ctx.Process(target=_child, args=(work, share, writer), daemon=True)
            child.start()
            writer.close()
            children.append((child, reader))
        try:
            results = [work(shares[0], progress)]
            for (child, reader), share in zip(children, shares[1:]):
                results.append(_result(child, reader, work, share))
                if progress:
                    for _ in share:
                        progress()
        finally:
            for child, reader in children:
                reader.close()
                if child.is_alive():
                    child.kill()
                child.join()
    return results


def _child(work: Callable[[Sequence[T], None], R], share: Sequence[T], writer: Any) -> None:
    try:
        writer.send(("ok", work(share, None)))
    except BaseException as exc:  # the parent computes this share again and raises
        writer.send(("failed", repr(exc)))
    finally:
        writer.close()


def _result(
    child: Any,
    reader: Any,
    work: Callable[[Sequence[T], Callable[[], Any] | None], R],
    share: Sequence[T],
) -> R:
    try:
        status, value = reader.recv()
    except (EOFError, OSError):  # the child died
        status, value = "failed", None
    if status == "ok":
        return value
    return work(share, None)
