"""One thread for OpenCV, the ray caster and numpy's BLAS in a worker: the workers are the parallelism
(threads inside one process scale much worse).

OpenCV and the ray caster (open3d) are imported when a batch starts, not when this module is:
the commands that only read and print import the runner too, and open3d costs a second.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager


def available_cpus() -> int:
    """Cores this process may run on (the default number of workers)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def one_thread() -> None:
    """OpenCV, the ray caster and numpy's BLAS on one thread, in this process."""
    import cv2
    from threadpoolctl import threadpool_limits

    from annotator.rendering import raycast

    cv2.setNumThreads(1)
    raycast.set_threads(1)
    threadpool_limits(1, user_api="blas")


@contextmanager
def one_thread_meanwhile() -> Iterator[None]:
    """:func:`one_thread` for the duration of the block, then the settings as they were."""
    import cv2
    from threadpoolctl import threadpool_limits

    from annotator.rendering import raycast

    before = cv2.getNumThreads(), raycast.get_threads()
    blas = threadpool_limits(1, user_api="blas")
    one_thread()
    try:
        yield
    finally:
        cv2.setNumThreads(before[0])
        raycast.set_threads(before[1])
        blas.restore_original_limits()
