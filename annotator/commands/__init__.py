"""One module per ``annotator`` subcommand: argument parsing and terminal output only.

The work itself lives in the pipeline packages; a command module wires options to library
calls and prints results (``--json`` where scripts consume the output).
"""

from __future__ import annotations

import argparse

from annotator.batch import available_cpus


def add_workers_option(parser: argparse.ArgumentParser) -> None:
    """``--workers N``: processes of one core each; default: every available core."""
    cores = available_cpus()
    parser.add_argument(
        "--workers",
        type=_positive_int,
        default=cores,
        metavar="N",
        help=f"worker processes, one core each (default: the {cores} available cores)",
    )


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a whole number of at least 1, not {text!r}")
    return value
