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
import hashlib
import json
import os
import re
import shutil
import stat
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from annotator.errors import Notice, UserError


class WriteError(UserError, OSError):
    """A file or folder could not be written (the message names it and says why)."""


def _umask() -> int:
    # The only portable way to read the umask is to set it; set it straight back.
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically, creating parent folders as needed.

    The temporary file is locked (``flock``) while it is written; the first write of a
    process into a folder removes the temporary files there that a killed writer left
    (unlocked, and older than :data:`ABANDONED_AFTER_S`).
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            mode = stat.S_IMODE(path.stat().st_mode)
        except FileNotFoundError:
            mode = 0o666 & ~_umask()
        _sweep_once(path.parent)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise WriteError(f"cannot write ({exc.strerror or exc})", path=path) from None
    try:
        _flock(fd, blocking=True)
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


#: A temporary file of :func:`write_bytes` this old and unlocked was left by a killed writer
#: (a live one locks it right after making it: the age covers only that instant).
ABANDONED_AFTER_S = 10.0
# ".<name>.<mkstemp's 8 characters>.tmp": the only names a sweep ever removes.
_TEMPORARY_NAME = re.compile(r"^\..+\.[a-z0-9_]{8}\.tmp$")
_SWEPT: set[str] = set()


def _flock(fd: int, *, blocking: bool) -> bool:
    """An exclusive ``flock`` on ``fd``: True if taken (always, where there is no flock)."""
    try:
        import fcntl
    except ImportError:
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
    except OSError:
        return False
    return True


def _sweep_once(folder: Path) -> None:
    """Remove the temporary files that killed writers left in ``folder`` (once a process)."""
    key = os.fspath(folder)  # as spelt: a folder spelt twice is only swept twice
    if key in _SWEPT:
        return
    _SWEPT.add(key)
    remove_abandoned_files(folder)


def remove_abandoned_files(
    folder: Path, *, older_than_s: float = ABANDONED_AFTER_S, remove: bool = True
) -> list[Path]:
    """Delete the temporary files of :func:`write_bytes` in ``folder`` whose writer is gone
    (no ``flock`` on them) and that are older than ``older_than_s``; return them (only
    found, not deleted, with ``remove=False``). Any other file is left alone, whatever its
    name."""
    removed: list[Path] = []
    if not hasattr(os, "O_NOFOLLOW"):
        return removed
    try:
        entries = [e for e in os.scandir(folder) if _TEMPORARY_NAME.match(e.name)]
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        try:
            if not entry.is_file(follow_symlinks=False):
                continue
            if now - entry.stat(follow_symlinks=False).st_mtime < older_than_s:
                continue
            fd = os.open(entry.path, os.O_RDONLY | os.O_NOFOLLOW)
        except OSError:
            continue
        try:
            if _flock(fd, blocking=False):
                if remove:
                    os.unlink(entry.path)
                removed.append(Path(entry.path))
        except OSError:
            pass
        finally:
            os.close(fd)
    return removed


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


#: A dataset's journal of files written together (:func:`write_together`).
JOURNAL = ".annotator-journal.json"
#: How long a reader waits for a live writer's journal to be finished.
JOURNAL_WAIT_S = 10.0


class JournalNotice(Notice):
    """A journal left in a dataset that could not be finished here (a read-only copy): the
    files are read as they are."""


def _digest(text: str | None) -> str | None:
    return None if text is None else hashlib.sha256(text.encode("utf-8")).hexdigest()


def _read_or_none(path: Path) -> str | None:
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None


def write_together(root: str | Path, texts: dict[Path, str]) -> None:
    """Write several text files under ``root`` so that either all of them take their new
    text or none does, even if the process is killed half-way.

    The new texts, and the files as they were, go first into ``root/.annotator-journal.json``
    (written atomically, and locked while this runs); then each file is written atomically;
    then the journal is removed. Stopped on purpose (Ctrl-C, SIGTERM), the files written so
    far are put back as they were: nothing is completed behind the user's back. Killed, the
    journal stays, and the next reader finishes it (:func:`finish_interrupted`) if the files
    are still as the journal left them.

    Raises:
        UserError: a file does not lie inside ``root`` (through a link, say).
    """
    root = Path(root)
    real_root = os.path.realpath(root)
    entries: dict[str, str] = {}
    before: dict[str, str | None] = {}
    for path, text in texts.items():
        rel = os.path.relpath(os.path.realpath(path), real_root)
        if rel.startswith(".."):
            raise UserError(f"lies outside the dataset {root}: not written", path=path)
        entries[rel] = text
        before[rel] = _read_or_none(root / rel)
    if not entries:
        return
    doc = {"written_by": "annotator", "files": entries, "before": before}
    lock = _write_locked(root / JOURNAL, json.dumps(doc, indent=1).encode("utf-8"))
    try:
        try:
            for rel, text in entries.items():
                write_text(root / rel, text)
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM (annotator.errors.Terminated)
            for rel, old in before.items():
                with contextlib.suppress(OSError):
                    if old is None:
                        (root / rel).unlink(missing_ok=True)
                    else:
                        write_text(root / rel, old)
            (root / JOURNAL).unlink(missing_ok=True)
            raise
        # A reader may have finished the same journal meanwhile: gone is as good as removed.
        try:
            (root / JOURNAL).unlink(missing_ok=True)
        except OSError as exc:
            raise WriteError(
                f"cannot remove it ({exc.strerror or exc})", path=root / JOURNAL
            ) from None
    finally:
        if lock is not None:
            os.close(lock)


def _write_locked(path: Path, data: bytes) -> int | None:
    """Write ``path`` atomically, its ``flock`` taken before it is in place; the descriptor
    holding it (None where there is no ``flock``)."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise WriteError(f"cannot write ({exc.strerror or exc})", path=path) from None
    try:
        with contextlib.suppress(ImportError):
            import fcntl

            fcntl.flock(fd, fcntl.LOCK_EX)
        os.write(fd, data)
        os.fsync(fd)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except OSError as exc:
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise WriteError(f"cannot write ({exc.strerror or exc})", path=path) from None
    return fd


def finish_interrupted(root: str | Path) -> list[Path]:
    """Finish the files written together (:func:`write_together`) that a killed process
    left half-written in ``root``; return them (none if there is no journal, or if its
    writer is still at work and finishes it).

    A journal is played only over the files it started from: each must hold either its old
    text or its new one. Where a dataset cannot be written (a read-only copy), the files are
    left as they are and a :class:`JournalNotice` says so.

    Raises:
        UserError: the journal is unreadable, lists a file outside the dataset, or a file it
            lists has been changed since (restored, edited): naming the journal and how to
            discard it.
    """
    root = Path(root)
    journal = root / JOURNAL
    try:
        fd = os.open(journal, os.O_RDONLY)
    except FileNotFoundError:
        return []
    except OSError as exc:
        raise UserError(f"cannot read it ({exc.strerror or exc})", path=journal) from None
    try:
        if not _wait_for_writer(fd):
            return []  # still locked: its writer is alive and writing the files itself
        try:
            if os.fstat(fd).st_ino != os.stat(journal).st_ino:
                return []  # finished and replaced meanwhile: not the journal locked
        except FileNotFoundError:
            return []  # its writer finished it
        return _play(root)
    finally:
        os.close(fd)


def _wait_for_writer(fd: int) -> bool:
    """Take the journal's lock (its writer is gone, or done), waiting a little for a live
    writer; False if it is still held then."""
    try:
        import fcntl
    except ImportError:
        return True
    deadline = time.monotonic() + JOURNAL_WAIT_S
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except OSError:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.02)


def _play(root: Path) -> list[Path]:
    journal = root / JOURNAL
    discard = f"delete {journal} to keep the files as they are now"
    try:
        doc = json.loads(journal.read_text(encoding="utf-8"))
        files, before = doc["files"], doc.get("before")
        if not isinstance(files, dict) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in files.items()
        ):
            raise ValueError("'files' must map paths to texts")
        if before is not None and not isinstance(before, dict):
            raise ValueError("'before' must map paths to texts")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise UserError(
            f"cannot finish the files an interrupted command was writing together ({exc}); "
            f"{discard} once the files it lists are as they should be",
            path=journal,
        ) from None
    real_root = os.path.realpath(root)
    for rel, text in files.items():
        target = root / rel
        outside = os.path.relpath(os.path.realpath(target), real_root).startswith("..")
        if os.path.isabs(rel) or ".." in Path(rel).parts or outside:
            raise UserError(
                f"lists {rel!r}, which is not inside the dataset; nothing was written: {discard}",
                path=journal,
            )
        now = _digest(_read_or_none(target))
        was = _digest(before.get(rel)) if before is not None else now
        if now not in (was, _digest(text)):
            raise UserError(
                f"an interrupted `annotator sites` was writing {rel}, which has been changed "
                f"since (restored or edited); nothing was written: {discard}",
                path=journal,
            )
    written = []
    try:
        for rel, text in files.items():
            target = root / rel
            if _read_or_none(target) != text:
                write_text(target, text)
            written.append(target)
        journal.unlink(missing_ok=True)
    except OSError as exc:  # a read-only copy: read it as it is, and say so
        why = exc.message if isinstance(exc, UserError) else (exc.strerror or str(exc))
        warnings.warn(
            JournalNotice(
                f"{journal}: an interrupted `annotator sites` left the files it lists "
                f"half-written, and this copy cannot be written ({why}): they are read as "
                "they are; finish them on a writable copy"
            ),
            stacklevel=4,
        )
        return []
    return written


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
def atomic_folder(
    out: str | Path, *, still_replaceable: Callable[[Path], None] | None = None
) -> Iterator[Path]:
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

    ``still_replaceable(out)``, when given, is called just before an existing ``out`` is
    replaced, holding ``out``'s own ``flock`` (the one a review server takes to write a
    scene's review.json): it raises to keep ``out`` as it is, when what was checked before
    the folder was built no longer holds (a reviewer decided on the scene meanwhile).
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
            held = _hold(out) if still_replaceable is not None else None
            try:
                if still_replaceable is not None:
                    still_replaceable(out)
                trash, trash_lock = temporary_folder(out.parent, prefix)
                try:
                    out.rename(trash / "old")
                    tmp.rename(out)
                    shutil.rmtree(trash, ignore_errors=True)
                finally:
                    if trash_lock is not None:
                        os.close(trash_lock)
            finally:
                if held is not None:
                    os.close(held)
        else:
            tmp.rename(out)
        (out / TEMPORARY_MARK).unlink(missing_ok=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        if lock is not None:
            os.close(lock)


def _hold(folder: Path) -> int | None:
    """``folder``'s ``flock``, waited for (its other holders keep it an instant)."""
    try:
        import fcntl
    except ImportError:
        return None
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return None
    fcntl.flock(fd, fcntl.LOCK_EX)
    return fd


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


def _abandoned_lock(folder: Path) -> int | None:
    """A descriptor holding ``folder``'s ``flock`` if it is one of the project's temporary
    folders (it carries :data:`TEMPORARY_MARK`) whose builder is gone (the lock was free);
    None otherwise (not ours, alive, or no ``flock`` here: nobody can tell)."""
    try:
        import fcntl
    except ImportError:
        return None
    if not (folder / TEMPORARY_MARK).is_file():
        return None
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None  # its owner is alive
    return fd


def is_abandoned_folder(folder: Path) -> bool:
    """Whether ``folder`` is a temporary folder of :func:`atomic_folder` whose builder is
    gone (marked, its ``flock`` free); nothing is changed."""
    fd = _abandoned_lock(folder)
    if fd is None:
        return False
    os.close(fd)  # (closing drops the lock just taken)
    return True


def remove_if_abandoned(folder: Path, *, restore: Path | None = None) -> bool:
    """Delete ``folder`` if it is one of the project's temporary folders (it carries
    :data:`TEMPORARY_MARK`) and no process holds its ``flock`` (whoever made it is gone);
    leave it otherwise. True if it was removed.

    With ``restore``: a folder killed while holding the old ``restore`` (moved aside by
    :func:`atomic_folder` before the new one took its name) gives it back first, if
    ``restore`` is gone.
    """
    fd = _abandoned_lock(folder)
    if fd is None:
        return False
    try:
        old = folder / "old"
        if restore is not None and old.is_dir() and not (restore.exists() or restore.is_symlink()):
            with contextlib.suppress(OSError):
                old.rename(restore)
        shutil.rmtree(folder, ignore_errors=True)
        return True
    finally:
        os.close(fd)
