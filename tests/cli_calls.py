"""Running the command line in-process in tests: its exit status and output, and the one
line a bad input must give."""

from __future__ import annotations

import pytest

from annotator.cli import main


def run_cli(args: list[str], capsys: pytest.CaptureFixture) -> tuple[int, str, str]:
    """``annotator ARGS``: exit status, stdout, stderr."""
    code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(args: list[str], capsys: pytest.CaptureFixture) -> str:
    """``annotator ARGS`` must fail with exit status 2 and one ``annotator: error:`` line."""
    code, _, err = run_cli(args, capsys)
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("annotator: error: "), err
    return lines[0]
