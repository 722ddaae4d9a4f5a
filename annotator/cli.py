"""The ``annotator`` command: one subcommand per pipeline stage.

Each subcommand lives in ``annotator/commands/<name>.py`` and defines ``HELP`` (one line),
``add_arguments(parser)`` and ``run(args) -> int`` (the exit status). Modules are imported
only when their subcommand runs, so ``annotator --help`` stays fast.

Exit status: 0 success; 1 the command ran but found problems (failed scenes, check
problems); 2 a usage error or bad input (one line on stderr, no traceback); 130 interrupted
(Ctrl-C); 143 terminated (SIGTERM).
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import threading
import time
import warnings
from collections.abc import Sequence
from typing import NoReturn

from annotator.errors import Notice, Terminated, UserError
from annotator.io.writer_lock import dataset_writer

# One BLAS thread: the matrices here are small, and threads only add overhead (annotate is
# faster with one, `benchmarks/bench_annotate.py`); batch commands get their parallelism from
# worker processes. Set before numpy is first imported; a user's own
# setting wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

#: (subcommand, module, one-line help), in pipeline order.
COMMANDS: tuple[tuple[str, str, str], ...] = (
    ("check", "annotator.commands.check", "validate a dataset and list every problem"),
    (
        "calibrate",
        "annotator.commands.calibrate",
        "calibrate the rig from ChArUco board shots into dataset.yaml",
    ),
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
        "ingest",
        "annotator.commands.ingest",
        "a recorded sequence (video or RealSense/ROS images) into a moving rig's dataset",
    ),
    (
        "annotate",
        "annotator.commands.annotate",
        "propose a pose for every instance from its markers",
    ),
    (
        "sites",
        "annotator.commands.sites",
        "measure where each instance's markers really are (glued by hand) into object.yaml",
    ),
    ("review", "annotator.commands.review", "accept or reject annotated scenes in the browser"),
    ("occlusion", "annotator.commands.occlusion", "compute per-instance masks and occlusion rates"),
    (
        "estimate",
        "annotator.commands.estimate",
        "a baseline pose estimator (PPF) on the depth maps, results as BOP CSV",
    ),
    ("export", "annotator.commands.export", "export accepted scenes to BOP or the Sileane format"),
    (
        "evaluate",
        "annotator.commands.evaluate",
        "score pose estimation results (symmetry-aware AP)",
    ),
    (
        "twin-report",
        "annotator.commands.twin_report",
        "compare real depth with the depth simulated on the scenes' synthetic twins",
    ),
)


class _UsageError(Exception):
    """A mistake on the command line (the message names the option)."""


class _Parser(argparse.ArgumentParser):
    """argparse, with its errors as one line (no usage block) and exit status 2 returned by
    :func:`main` rather than raised as SystemExit."""

    def error(self, message: str) -> NoReturn:
        raise _UsageError(f"{self.prog}: error: {message} (see `{self.prog} --help`)")


class _Version(argparse.Action):
    """``--version``, looked up only when asked for: importlib.metadata is slow to import,
    and every command would pay for it."""

    def __init__(self, option_strings: Sequence[str], dest: str, help: str | None = None) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=help)

    def __call__(self, parser: argparse.ArgumentParser, *_: object) -> NoReturn:
        from importlib.metadata import PackageNotFoundError, version

        try:
            ver = version("bin-annotator")
        except PackageNotFoundError:
            ver = "unknown"
        print(f"annotator {ver}")
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="annotator",
        description="Ground-truth 6D poses for bin-picking scenes, and symmetry-aware evaluation.",
    )
    parser.add_argument("--version", action=_Version, help="show the version and exit")
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
            commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
            sub = commands.choices[name]
            mod = importlib.import_module(module)
            mod.add_arguments(sub)
            if getattr(mod, "WRITES", None):
                sub.add_argument(
                    "--wait",
                    action="store_true",
                    help="if another command is writing into the dataset, wait for it to "
                    "finish (default: refuse at once, naming it)",
                )
            break
    try:
        args = parser.parse_args(argv)
    except _UsageError as exc:
        print(exc, file=sys.stderr)
        return 2
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    mod = importlib.import_module(args._module)
    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate) if in_main else None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", Notice)
            warnings.showwarning = _show_notice
            return _run(mod, args)
    except BaseException as exc:
        # A SIGTERM may surface as another exception (a library turning it into an
        # ImportError, say): once asked to stop, stopping is the outcome.
        if isinstance(exc, Terminated) or _TERMINATING.is_set():
            print("annotator: terminated", file=sys.stderr)
            return 143
        if isinstance(exc, UserError):
            print(f"annotator: error: {exc}", file=sys.stderr)
            return 2
        if isinstance(exc, KeyboardInterrupt):
            print("annotator: interrupted", file=sys.stderr)
            return 130
        raise
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous)


def _run(mod: object, args: argparse.Namespace) -> int:
    """The command, holding its dataset's writer lock if it writes into one (its module's
    ``WRITES`` names the argument that gives the dataset: :mod:`annotator.io.writer_lock`)."""
    where = getattr(mod, "WRITES", None)
    root = getattr(args, where, None) if where else None
    if root is None:
        return int(mod.run(args) or 0)  # type: ignore[attr-defined]
    with dataset_writer(root, command=f"annotator {args.command}", wait=args.wait):
        return int(mod.run(args) or 0)  # type: ignore[attr-defined]


def _show_notice(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    file: object = None,
    line: str | None = None,
) -> None:
    if issubclass(category, Notice):
        print(f"annotator: warning: {message}", file=sys.stderr)
    else:  # as Python shows it
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


def _terminate(signum: int, frame: object) -> None:
    # Raised in the main thread wherever it is, so that the same clean-up as for Ctrl-C runs
    # (batch workers are stopped, temporary folders removed). Some libraries swallow every
    # exception around their imports: if the process is still there a few seconds later, it
    # stops its workers and leaves at once (a temporary folder left behind is removed by the
    # next run).
    if not _TERMINATING.is_set():
        _TERMINATING.set()
        threading.Thread(target=_exit_soon, daemon=True).start()
    raise Terminated()


_TERMINATING = threading.Event()


def _exit_soon(delay: float = 5.0) -> None:
    time.sleep(delay)
    batch = sys.modules.get("annotator.runner.local")
    if batch is not None:
        batch.kill_workers()
    print("annotator: terminated", file=sys.stderr, flush=True)
    os._exit(143)


if __name__ == "__main__":
    sys.exit(main())
