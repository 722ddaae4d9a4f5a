"""Scenes rendered twice, with and without markers (``synth --no-markers``, same seed), and
their BOP exports: what ``export --remove-markers`` is checked against."""

from __future__ import annotations

from pathlib import Path

from annotator.cli import main

#: The exports' options: every scene, the true poses.
EXPORT = ["--format", "bop", "--poses", "gt", "--include-pending", "--quiet"]


def render_twins(base: Path, synth: list[str]) -> Path:
    """``synth`` (its options) rendered to ``base/marked`` and, bare, to ``base/bare``."""
    for name, extra in (("marked", []), ("bare", ["--no-markers"])):
        if main(["synth", str(base / name), *synth, *extra]) != 0:
            raise RuntimeError(f"synth to {base / name} failed")
    return base


def export_twins(base: Path) -> Path:
    """``base/marked`` and ``base/bare`` (two synth datasets) exported to ``base/plain``,
    ``base/bare_bop`` and, with ``--remove-markers``, ``base/removed``; returns ``base``."""
    for src, dst, extra in (
        ("marked", "plain", []),
        ("bare", "bare_bop", []),
        ("marked", "removed", ["--remove-markers"]),
    ):
        if main(["export", str(base / src), str(base / dst), *EXPORT, *extra]) != 0:
            raise RuntimeError(f"export of {base / src} failed")
    return base
