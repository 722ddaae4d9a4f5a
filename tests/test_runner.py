"""The local batch runner when a worker process dies under a scene (issue 44: the system's
out-of-memory killer): that scene is reported failed in one line, every other scene is
done, and nothing raises."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from annotator.runner.local import WORKER_DIED, run_local

pytestmark = pytest.mark.slow  # real worker processes, one of them killed


class _KillsItsWorker:
    """A job that kills its own process on scene ``victim`` (as the OOM killer would)."""

    def __init__(self, victim: str, log: Path) -> None:
        self.victim, self.log = victim, log

    def __call__(self, sid: str) -> dict:
        if sid == self.victim:
            os.kill(os.getpid(), signal.SIGKILL)
        with open(self.log, "a") as f:
            f.write(sid + "\n")
        return {"scene": sid}


@pytest.mark.parametrize("victim", ["000000", "000004", "000009"])
def test_a_worker_killed_under_a_scene_fails_that_scene_alone(tmp_path: Path, victim) -> None:
    ids = [f"{i:06d}" for i in range(10)]
    report = run_local(_KillsItsWorker(victim, tmp_path / "log"), ids, workers=2, quiet=True)
    assert report.failed == {victim: WORKER_DIED}
    assert sorted(report.done) == [sid for sid in ids if sid != victim]
    assert all(report.done[sid] == {"scene": sid} for sid in report.done)


def test_a_batch_keeps_freed_memory_in_the_heap() -> None:
    """On glibc (Linux), a batch's processes fix the allocator's thresholds, so that a
    frame's image-sized temporaries are not mapped afresh each time."""
    import sys

    from annotator.runner.heap import keep_freed_memory, release_free_memory

    assert keep_freed_memory() is sys.platform.startswith("linux")
    assert release_free_memory() is sys.platform.startswith("linux")
