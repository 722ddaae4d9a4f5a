"""What a stage returns: one shape for every ``*Summary`` a dataset-level function gives back.

Each stage (annotate, occlusion, export, synth, estimate, calibrate, sites, ingest, markers,
evaluate, the physics check) returns a record of what it did. Whatever else it holds, it
answers the same six questions, so that a command prints any of them the same way
(:func:`annotator.commands.finish`) and a script reads any of them the same way:

- :meth:`StageSummary.counts`: how many of each thing (scenes done, failed, instances...);
- :meth:`StageSummary.warnings`: lines for the terminal's error stream (failed scenes, what
  was left out and why, what to do next);
- :meth:`StageSummary.written_paths`: the files and folders the stage wrote;
- :meth:`StageSummary.text`: what the command prints on standard output;
- :meth:`StageSummary.to_json`: what ``--json`` prints (plain JSON values);
- :meth:`StageSummary.exit_status`: the command's exit status (1: something failed).

>>> from dataclasses import dataclass
>>> @dataclass
... class Done:
...     scenes: int
...     def counts(self): return {"scenes": self.scenes}
...     def warnings(self): return []
...     def written_paths(self): return []
...     def text(self): return f"done: {self.scenes} scenes"
...     def to_json(self): return self.counts()
...     def exit_status(self): return 0
>>> isinstance(Done(3), StageSummary)
True
>>> failure_lines({"b": "no depth", "a": "no markers"})
['failed: scene a: no markers', 'failed: scene b: no depth']
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

__all__ = ["FolderBatch", "StageSummary", "failure_lines"]


@runtime_checkable
class StageSummary(Protocol):
    """What every stage's summary answers (module docstring). ``isinstance`` checks that the
    methods are there, not their types: mypy checks those where a summary is used as one."""

    def counts(self) -> dict[str, int]:
        """How many of each thing the stage did, by name."""
        ...

    def warnings(self) -> list[str]:
        """The lines for the terminal's error stream, each whole (``failed: scene 3: ...``)."""
        ...

    def written_paths(self) -> list[Path]:
        """The files and folders written (empty when the stage wrote nothing)."""
        ...

    def text(self) -> str:
        """What the command prints on standard output (one line, or a report)."""
        ...

    def to_json(self) -> dict[str, Any]:
        """What ``--json`` prints: plain JSON values."""
        ...

    def exit_status(self) -> int:
        """The command's exit status: 0, or 1 when a scene failed or a write was declined."""
        ...


def failure_lines(failed: Mapping[str, str]) -> list[str]:
    """One warning line per failed scene, in scene order (as every batch stage says it)."""
    return [f"failed: scene {sid}: {why}" for sid, why in sorted(failed.items())]


class FolderBatch:
    """The warnings, written paths and exit status of a batch stage that writes one folder
    ``out`` and keeps a report whose ``failed`` maps a scene to why it failed (synth, its
    sequences, twins): a summary that is that names both as attributes."""

    out: Path
    report: Any

    def warnings(self) -> list[str]:
        return failure_lines(self.report.failed)

    def written_paths(self) -> list[Path]:
        return [self.out]

    def exit_status(self) -> int:
        return 1 if self.report.failed else 0
