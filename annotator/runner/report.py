"""What a batch gives back: per-scene outcomes, the one line a failure is reported with,
and the progress bar (the same for the local and the Ray runner)."""

from __future__ import annotations

import sys
import traceback
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from tqdm import tqdm


@dataclass
class BatchReport:
    """Per-scene outcomes: results of the scenes done and one-line errors of the failed ones."""

    done: dict[str, dict[str, Any]] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)

    def print_failures(self) -> None:
        """One line per failed scene on stderr, in scene order."""
        for sid, err in sorted(self.failed.items()):
            print(f"failed: scene {sid}: {err}", file=sys.stderr)


def describe_failure(exc: BaseException) -> str:
    """The one line a failed scene's unexpected exception is reported with: its type, message
    and the line of code that raised it."""
    tb = traceback.extract_tb(exc.__traceback__)
    where = f" (at {tb[-1].filename}:{tb[-1].lineno})" if tb else ""
    return f"{type(exc).__name__}: {exc}{where}"


def progress_bar(total: int, desc: str, quiet: bool, *, unit: str = "scene") -> tqdm:
    """The batch progress bar: scenes (``unit``s) finished (done or failed), on stderr when
    it is a terminal."""
    # Imported here: tqdm costs every command's start-up, and only batches draw a bar.
    from tqdm import tqdm

    return tqdm(
        total=total,
        desc=desc,
        unit=unit,
        disable=quiet or not sys.stderr.isatty(),
        file=sys.stderr,
    )


def record(report: BatchReport, sid: str, result: dict[str, Any] | None, error: str | None) -> None:
    if error is not None:
        report.failed[sid] = error
    else:
        report.done[sid] = result or {}
