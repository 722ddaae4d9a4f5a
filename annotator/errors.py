"""User-facing errors.

A :class:`UserError` is a problem with the user's input (a file, an option). The CLI prints it
as one line, ``annotator: error: <message>``, and exits with status 2; it never shows a
traceback for it. Library code raises it with the offending file named in the message.
"""

from __future__ import annotations

from pathlib import Path


class UserError(Exception):
    """A mistake in the user's input, reported as one line naming the file and the problem.

    >>> from pathlib import Path
    >>> print(UserError("no rig section", path=Path("ds/dataset.yaml")))
    ds/dataset.yaml: no rig section
    """

    def __init__(self, message: str, *, path: str | Path | None = None) -> None:
        self.path = None if path is None else Path(path)
        self.message = message
        super().__init__(f"{path}: {message}" if path is not None else message)


class Terminated(KeyboardInterrupt):
    """The process received SIGTERM: it stops like on Ctrl-C (work in progress is dropped,
    files already written stay), and exits with status 143."""


class Notice(UserWarning):
    """Something the user should know that does not stop the work (a journal this copy
    cannot finish, say): issued with :func:`warnings.warn`, printed by the CLI as one
    ``annotator: warning: <message>`` line."""
