"""One module per ``annotator`` subcommand: argument parsing and terminal output only.

The work itself lives in the pipeline packages; a command module wires options to one library
call and prints what it returns, a :class:`~annotator.summary.StageSummary`, through
:func:`finish` (``--json`` where scripts consume the output).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path

from annotator import values
from annotator.runner import RAY_WAIT_S, available_cpus
from annotator.summary import StageSummary


def add_workers_option(parser: argparse.ArgumentParser) -> None:
    """``--workers N``: processes of one core each; default: every available core."""
    cores = available_cpus()
    parser.add_argument(
        "--workers",
        type=whole(low=1),
        default=cores,
        metavar="N",
        help=f"worker processes, one core each (default: the {cores} available cores)",
    )


def add_ray_option(parser: argparse.ArgumentParser) -> None:
    """``--ray ADDRESS``: one Ray task per scene on that cluster (``auto``: the running one)."""
    parser.add_argument(
        "--ray",
        metavar="ADDRESS",
        default=None,
        help="run every scene as a task on the Ray cluster whose head is at ADDRESS "
        "(host:port), or 'auto' for the one this machine belongs to (RAY_ADDRESS or the "
        "latest `ray start`); files travel as bytes, no shared file system is needed; "
        "--workers is then ignored (needs `pip install 'bin-annotator[ray]'`)",
    )
    parser.add_argument(
        "--ray-wait",
        metavar="SECONDS",
        type=_seconds,
        default=RAY_WAIT_S,
        help="with --ray: how long to wait for a CPU when the cluster has none for its tasks "
        "(its worker nodes died or none joined) before stopping with the unfinished scenes "
        f"listed (default {RAY_WAIT_S:g})",
    )


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number of seconds: {text!r}") from None
    if not (value >= 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a finite number of seconds >= 0: {text!r}")
    return value


def whole(*, low: int = 0, high: int | None = None) -> Callable[[str], int]:
    """An argparse type: a whole number within [``low``, ``high``] (one line otherwise;
    :func:`annotator.values.whole`, which the API calls too)."""

    def parse(text: str) -> int:
        try:
            return values.whole(text, name="value", low=low, high=high)
        except values.BadValue as exc:
            raise argparse.ArgumentTypeError(exc.reason) from None

    return parse


def number(
    *, low: float | None = None, high: float | None = None, above: bool = False
) -> Callable[[str], float]:
    """An argparse type: a finite number within [``low``, ``high``] (``above``: strictly
    greater than ``low``); NaN and infinities are refused in one line
    (:func:`annotator.values.number`, which the API calls too)."""

    def parse(text: str) -> float:
        try:
            return values.number(text, name="value", low=low, high=high, above=above)
        except values.BadValue as exc:
            raise argparse.ArgumentTypeError(exc.reason) from None

    return parse


def number_pair(form: str, example: str) -> Callable[[str], tuple[float, float]]:
    """An argparse type: two finite numbers, at least 0, written ``A,B`` (``form`` names
    them, ``MM,DEG``; ``example`` shows one, for the error line)."""
    finite = number(low=0)

    def parse(text: str) -> tuple[float, float]:
        parts = text.split(",")
        if len(parts) != 2:
            raise argparse.ArgumentTypeError(f"must be {form} (e.g. {example}), not {text!r}")
        return finite(parts[0]), finite(parts[1])

    return parse


def confirm(path: Path) -> bool:
    """Ask on the terminal whether to write ``path``; anything but y/yes is no."""
    print(f"write {path}? [y/N] ", end="", file=sys.stderr, flush=True)
    try:
        answer = sys.stdin.readline().strip().lower()
    except (EOFError, KeyboardInterrupt):
        return False
    return answer in ("y", "yes")


def show(summary: StageSummary) -> None:
    """Print a stage's summary for a person: its warnings on stderr, then its text."""
    for line in summary.warnings():
        print(line, file=sys.stderr)
    print(summary.text())


def finish(summary: StageSummary, *, as_json: bool) -> int:
    """End a command the one way every stage ends: its summary as JSON (``--json``), or its
    warnings and text (:func:`show`); the exit status the summary gives."""
    if as_json:
        print(json.dumps(summary.to_json(), indent=1))
    else:
        show(summary)
    return summary.exit_status()
