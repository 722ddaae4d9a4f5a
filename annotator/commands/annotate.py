"""`annotator annotate` (not built yet)."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset")


def run(args: argparse.Namespace) -> int:
    raise SystemExit("annotator annotate: not built yet")
