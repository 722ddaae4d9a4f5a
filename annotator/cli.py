"""The ``annotator`` command: one subcommand per pipeline stage.

Each subcommand lives in ``annotator/commands/<name>.py`` and defines ``HELP`` (one line),
``add_arguments(parser)`` and ``run(args) -> int`` (the exit status). Modules are imported
only when their subcommand runs, so ``annotator --help`` stays fast.

Exit status: 0 success; 1 the command ran but found problems (failed scenes, check
problems); 2 a usage error or bad input (one line on stderr, no traceback); 130 interrupted.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from annotator.errors import UserError

#: (subcommand, module, one-line help), in pipeline order.
COMMANDS: tuple[tuple[str, str, str], ...] = (
    ("check", "annotator.commands.check", "validate a dataset and list every problem"),
    (
        "markers",
        "annotator.commands.markers",
        "place marker sites on a part and export printable sheets",
    ),
    (
        "synth",
        "annotator.commands.synth",
        "generate synthetic bin-picking scenes with exact ground truth",
    ),
    (
        "annotate",
        "annotator.commands.annotate",
        "propose a pose for every instance from its markers",
    ),
    ("review", "annotator.commands.review", "accept or reject annotated scenes in the browser"),
    ("occlusion", "annotator.commands.occlusion", "compute per-instance masks and occlusion rates"),
    ("export", "annotator.commands.export", "export accepted scenes to BOP or the Sileane format"),
    (
        "evaluate",
        "annotator.commands.evaluate",
        "score pose estimation results (symmetry-aware AP)",
    ),
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="annotator",
        description="Ground-truth 6D poses for bin-picking scenes, and symmetry-aware evaluation.",
    )
    from importlib.metadata import PackageNotFoundError, version

    try:
        ver = version("bin-annotator")
    except PackageNotFoundError:
        ver = "unknown"
    parser.add_argument("--version", action="version", version=f"annotator {ver}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module, help_text in COMMANDS:
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        # Arguments are added lazily in main() for the chosen command only.
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    # Find the subcommand first so that only its module is imported.
    chosen = next((a for a in argv if not a.startswith("-")), None)
    for name, module, _help_text in COMMANDS:
        if name == chosen:
            sub = parser._subparsers._group_actions[0].choices[name]  # type: ignore[union-attr]
            mod = importlib.import_module(module)
            mod.add_arguments(sub)
            break
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    mod = importlib.import_module(args._module)
    try:
        return int(mod.run(args) or 0)
    except UserError as exc:
        print(f"annotator: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("annotator: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
