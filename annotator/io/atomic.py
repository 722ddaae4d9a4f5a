"""Atomic file writes: a temporary file in the same folder, fsync, then ``os.replace``.

A reader (or a crash) therefore sees either the old file or the new one, never half of one.

Modes: files and folders get the mode a plain ``open()`` / ``mkdir()`` would give them under
the process's umask (0644 and 0755 under umask 022), and a replaced file keeps its mode, so a
dataset shared between users stays readable by them.

A write that fails (read-only folder, full disk, a folder in the way) raises
:class:`WriteError`: a one-line :class:`~annotator.errors.UserError` naming the file, which
is also an ``OSError`` for callers that catch those.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import stat
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from annotator.errors import UserError


class WriteError(UserError, OSError):
    """A file or folder could not be written (the message names it and says why)."""


def _umask() -> int:
    # The only portable way to read the umask is to set it; set it straight back.
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically, creating parent folders as needed."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            mode = stat.S_IMODE(path.stat().st_mode)
        except FileNotFoundError:
            mode = 0o666 & ~_umask()
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise WriteError(f"cannot write ({exc.strerror or exc})", path=path) from None
    try:
        with os.fdopen(fd, "wb") as f:
            os.fchmod(f.fileno(), mode)
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise WriteError(f"cannot write ({exc.strerror or exc})", path=path) from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_text(path: str | Path, text: str) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    write_bytes(path, text.encode("utf-8"))


def write_json(path: str | Path, obj: Any, *, indent: int | None = 1) -> None:
    """Write ``obj`` as JSON to ``path`` atomically (numpy scalars and arrays are converted)."""
    write_text(path, json.dumps(obj, indent=indent, default=_to_builtin) + "\n")


def _to_builtin(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot serialise {type(obj).__name__} to JSON")


#: The file that marks a folder as one of the project's temporary folders. Abandoned
#: temporary folders are recognised by it (and by their free lock), never by name alone: a
#: folder of the user's whose name happens to look like ours is never removed or renamed.
TEMPORARY_MARK = ".annotator-temporary"


def temporary_folder(parent: Path, prefix: str) -> tuple[Path, int | None]:
    """Create a folder in ``parent`` named ``prefix<random>``, locked and marked as ours.

    Returns the folder and the descriptor holding its ``flock`` (None where there is no
    ``flock``); close the descriptor when the folder is finished with. The lock is taken
    before the mark is written, so a sweeping neighbour never sees a marked, unlocked folder
    that is still in use.
    """
    tmp = Path(tempfile.mkdtemp(prefix=prefix, dir=parent))
    os.chmod(tmp, 0o777 & ~_umask())
    lock = _lock(tmp)
    (tmp / TEMPORARY_MARK).write_text("made by annotator; removed when its lock is free\n")
    return tmp, lock


@contextmanager
def atomic_folder(out: str | Path) -> Iterator[Path]:
    """Build a folder in a temporary sibling and put it in place of ``out`` only on success.

    Whatever goes wrong inside the ``with`` block (an error, Ctrl-C), ``out`` is left as it was
    and the temporary folder is removed: never half a dataset or half an export. The old
    ``out`` is moved aside (into a second temporary folder) before the new one takes its name
    and deleted only after, so a crash at any moment leaves one of the two complete.

    A symbolic link ``out`` is followed: its target is replaced and the link stays.

    The temporary folders (:func:`temporary_folder`) are locked while in use; one left
    behind by a killed process is no longer locked and is removed by the next call for the
    same ``out`` (after putting an old ``out`` it holds back in place if ``out`` is gone),
    while one that another running process is building is left alone.
    """
    out = Path(out)
    if out.is_symlink():
        out = Path(os.path.realpath(out))
    prefix = f".{out.name}."
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        _remove_abandoned(out)
        tmp, lock = temporary_folder(out.parent, prefix)
    except OSError as exc:
        raise WriteError(f"cannot create the folder ({exc.strerror or exc})", path=out) from None
    try:
        yield tmp
        if out.exists() or out.is_symlink():
            trash, trash_lock = temporary_folder(out.parent, prefix)
            try:
                out.rename(trash / "old")
                tmp.rename(out)
                shutil.rmtree(trash, ignore_errors=True)
            finally:
                if trash_lock is not None:
                    os.close(trash_lock)
        else:
            tmp.rename(out)
        (out / TEMPORARY_MARK).unlink(missing_ok=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        if lock is not None:
            os.close(lock)


def _lock(folder: Path) -> int | None:
    """An exclusive ``flock`` on ``folder`` (held until the descriptor is closed)."""
    try:
        import fcntl
    except ImportError:  # not POSIX: abandoned folders are then left for the user
        return None
    fd = os.open(folder, os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    return fd


def _remove_abandoned(out: Path) -> None:
    """Delete the temporary siblings of ``out`` whose builder is gone (marked, lock free)."""
    prefix = f".{out.name}."
    for cand in sorted(out.parent.iterdir()):
        if cand.name.startswith(prefix) and cand.is_dir() and not cand.is_symlink():
            remove_if_abandoned(cand, restore=out)


def remove_if_abandoned(folder: Path, *, restore: Path | None = None) -> bool:
    """Delete ``folder`` if it is one of the project's temporary folders (it carries
    :data:`TEMPORARY_MARK`) and no process holds its ``flock`` (whoever made it is gone);
    leave it otherwise. True if it was removed.

    With ``restore``: a folder killed while holding the old ``restore`` (moved aside by
    :func:`atomic_folder` before the new one took its name) gives it back first, if
    ``restore`` is gone.
    """
    try:
        import fcntl
    except ImportError:  # not POSIX: nobody can tell; keep it
        return False
    if not (folder / TEMPORARY_MARK).is_file():
        return False  # not ours
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return False  # its owner is alive
    else:
        old = folder / "old"
        if restore is not None and old.is_dir() and not (restore.exists() or restore.is_symlink()):
            with contextlib.suppress(OSError):
                old.rename(restore)
        shutil.rmtree(folder, ignore_errors=True)
        return True
    finally:
        os.close(fd)
