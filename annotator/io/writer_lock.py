"""One writer per dataset: a command that writes into a dataset holds its writer lock.

The lock is an exclusive ``flock`` on the dataset's folder itself (the kernel drops it when
the process ends, however it ends, so a killed writer never leaves the dataset locked).
While it holds the lock, the writer describes itself in ``DATASET/.annotator-writer.json``
(command, process id, host, start time), so that a second writer is refused with a message
naming the holder, or waits for it when asked (``--wait``). Readers (``check``, ``export``,
``evaluate``, the review server) take no lock: every file is replaced atomically, so they
see either the old file or the new one.

The lock is per process and re-entrant: a command's library function may take it again
inside the command's own hold.
"""

from __future__ import annotations

import datetime
import json
import os
import socket
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from annotator.errors import UserError
from annotator.io.atomic import write_json

__all__ = ["HOLDER_FILE", "DatasetBusy", "dataset_writer", "holder_of"]

#: Where the writer holding a dataset's lock describes itself.
HOLDER_FILE = ".annotator-writer.json"

_held: dict[Path, int] = {}
_guard = threading.Lock()


class DatasetBusy(UserError):
    """Another command is writing into the dataset (the message names it)."""


def holder_of(root: str | Path) -> str:
    """Who holds ``root``'s writer lock, as a message names it (``another command`` when it
    has not described itself yet)."""
    try:
        doc = json.loads((Path(root) / HOLDER_FILE).read_text(encoding="utf-8"))
        return f"`{doc['command']}` (pid {doc['pid']} on {doc['host']}, since {doc['since']})"
    except (OSError, ValueError, KeyError, TypeError):
        return "another command"


@contextmanager
def dataset_writer(root: str | Path, *, command: str, wait: bool = False) -> Iterator[Path]:
    """Hold ``root``'s writer lock while the block runs (the folder is created if missing).

    Args:
        root: The dataset's folder.
        command: Who writes (``annotator ingest``), as a refused writer is told.
        wait: Wait for the holder to finish instead of refusing.

    Raises:
        DatasetBusy: another process holds the lock and ``wait`` is False.

    >>> import tempfile
    >>> root = tempfile.mkdtemp()
    >>> with dataset_writer(root, command="annotator annotate"):
    ...     print(holder_of(root).split(" (")[0])
    `annotator annotate`
    """
    real = Path(os.path.realpath(root))
    with _guard:
        if real in _held:  # this process holds it already: taken again
            _held[real] += 1
            fd, made = None, []
        else:
            made = _missing(real)
            fd = _acquire(Path(root), real, command, wait)
            _held[real] = 1
    try:
        yield Path(root)
    finally:
        with _guard:
            _held[real] -= 1
            if _held[real] == 0:
                del _held[real]
                if fd is not None:
                    _release(real, fd, made)


def _missing(real: Path) -> list[Path]:
    """The folders that creating ``real`` makes, innermost first."""
    out = []
    p = real
    while not p.exists() and p != p.parent:
        out.append(p)
        p = p.parent
    return out


def _acquire(root: Path, real: Path, command: str, wait: bool) -> int | None:
    if root.exists() and not root.is_dir():
        raise UserError("is a file, not a dataset folder", path=root)
    while True:
        try:
            root.mkdir(parents=True, exist_ok=True)
            fd = os.open(real, os.O_RDONLY)
        except OSError as exc:
            raise UserError(f"cannot lock the dataset ({exc.strerror or exc})", path=root) from None
        if sys.platform == "win32":  # no flock: no lock between processes
            return fd
        _lock(fd, root, real, wait)
        try:  # a holder that made the folder removes it when it fails: lock the new one
            same = os.stat(real).st_ino == os.fstat(fd).st_ino
        except OSError:
            same = False
        if same:
            break
        os.close(fd)
    since = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    doc = {"command": command, "pid": os.getpid(), "host": socket.gethostname(), "since": since}
    try:
        write_json(real / HOLDER_FILE, doc)
    except UserError:  # a read-only dataset: the lock still holds, undescribed
        pass
    return fd


def _lock(fd: int, root: Path, real: Path, wait: bool) -> None:
    import fcntl

    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        who = _described(real)
        if not wait:
            os.close(fd)
            raise DatasetBusy(
                f"is being written by {who}: wait for it to finish, or pass --wait to start "
                "when it has",
                path=root,
            ) from None
        print(f"annotator: waiting for {who} to finish writing {root}", file=sys.stderr)
        while True:  # polled, so that Ctrl-C and SIGTERM stop the wait at once
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError:
                time.sleep(0.05)
            except BaseException:
                os.close(fd)
                raise


def _described(real: Path, patience_s: float = 1.0) -> str:
    """The holder as it describes itself, given an instant to do so (it writes its
    description right after taking the lock)."""
    deadline = time.monotonic() + patience_s
    while True:
        who = holder_of(real)
        if who != "another command" or time.monotonic() > deadline:
            return who
        time.sleep(0.02)


def _release(real: Path, fd: int, made: list[Path]) -> None:
    try:
        (real / HOLDER_FILE).unlink(missing_ok=True)
    except OSError:
        pass
    for folder in made:  # the folders this hold created, if the command left them empty
        try:
            folder.rmdir()
        except OSError:
            break
    os.close(fd)  # closing the folder's descriptor drops the flock
