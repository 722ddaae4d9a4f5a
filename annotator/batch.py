"""Running one job per scene over a dataset: worker processes, progress bar, failure report.

A job is a picklable callable ``job(scene_id) -> dict``; a :class:`~annotator.errors.UserError`
(or any exception) in one scene is recorded as that scene's failure and the batch goes on.
Interrupting (Ctrl-C) stops the batch; what was already written stays (writes are atomic), so
a batch command run again resumes where it stopped.
"""

from __future__ import annotations

import sys
import traceback
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
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
    """Run ``job`` on every scene id, in ``workers`` processes, with a progress bar on stderr."""
    report = BatchReport()
    bar = tqdm(
        total=len(scene_ids),
        desc=desc,
        unit="scene",
        disable=quiet or not sys.stderr.isatty(),
        file=sys.stderr,
    )
    try:
        if workers <= 1 or len(scene_ids) <= 1:
            for sid in scene_ids:
                _record(report, *_run_one(job, sid))
                bar.update()
        else:
            with ProcessPoolExecutor(max_workers=workers) as pool:
                futures = [pool.submit(_run_one, job, sid) for sid in scene_ids]
                for fut in as_completed(futures):
                    _record(report, *fut.result())
                    bar.update()
    finally:
        bar.close()
    return report


def _record(
    report: BatchReport, sid: str, result: dict[str, Any] | None, error: str | None
) -> None:
    if error is not None:
        report.failed[sid] = error
    else:
        report.done[sid] = result or {}
