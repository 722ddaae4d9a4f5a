"""A scene's lock across processes: several review servers on one dataset change a scene's
review.json one at a time. The lock is a ``flock`` on the scene's folder, taken again freely
by the thread that holds it (a change made inside another)."""

from __future__ import annotations

import os
import time
from pathlib import Path

from annotator.review.scenes import SaveError

__all__ = ["LOCK_WAIT_S", "FolderLocks"]

#: How long a change waits for another server's lock on the scene.
LOCK_WAIT_S = 5.0


class FolderLocks:
    """The ``flock``s one review state holds, one per scene, each counted (re-entrant).
    Callers serialise their own threads (the state's lock); this spans processes."""

    def __init__(self) -> None:
        self._held: dict[str, list[int]] = {}

    def hold(self, sid: str, folder: Path) -> None:
        """Take scene ``sid``'s lock (on ``folder``), or once more if it is held here.

        Raises:
            SaveError: another server keeps it longer than :data:`LOCK_WAIT_S`, or the
                folder has gone.
        """
        held = self._held.get(sid)
        if held is not None:
            held[1] += 1
            return
        try:
            fd = os.open(folder, os.O_RDONLY)
        except OSError:
            raise SaveError(f"{folder}: the scene's folder is gone (deleted or moved)") from None
        deadline = time.monotonic() + LOCK_WAIT_S
        try:
            import fcntl
        except ImportError:  # not POSIX: the pages of this server are still serialised
            self._held[sid] = [fd, 1]
            return
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError:
                if time.monotonic() > deadline:
                    os.close(fd)
                    raise SaveError(
                        f"{folder}: another review server has kept the scene locked for "
                        f"{LOCK_WAIT_S:g} s; try again"
                    ) from None
                time.sleep(0.01)
        self._held[sid] = [fd, 1]

    def release(self, sid: str) -> None:
        """Give back one hold of :meth:`hold` (the lock goes with the last one)."""
        held = self._held[sid]
        held[1] -= 1
        if held[1] == 0:
            del self._held[sid]
            os.close(held[0])  # closing the descriptor releases the flock
