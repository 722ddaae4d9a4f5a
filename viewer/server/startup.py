"""Starting viser's server without waiting forever.

``viser.ViserServer()`` (1.1.1) binds its port in a thread of its own and waits, with no
timeout, until that thread says it listens. If the thread dies first (an exception: a port
above 65535 raises OverflowError there) or gives up (none of the thousand ports it tries is
free), nothing says so, and the caller waits forever. :func:`start_viser` therefore makes the
server in a helper thread and waits for it while watching viser's thread (found in the
helper's frame of ``WebsockServer.start``; an exception there is caught by a
``threading.excepthook`` set for the start-up only, which also keeps its traceback out of
the log): its death, with or without an exception, or :data:`START_SECONDS` without an
answer, is a one-line :class:`~annotator.errors.UserError`. The port is checked before
anything starts (:func:`check_port`).
"""

from __future__ import annotations

import sys
import threading
import time
from types import FrameType, TracebackType
from typing import TYPE_CHECKING, Any

from annotator.errors import UserError

if TYPE_CHECKING:
    import viser

#: How long a server may take to listen before the start is given up.
START_SECONDS = 30.0
PORTS = range(1, 65536)
_POLL_SECONDS = 0.02
_WORKER = "_background_worker"  # viser.infra.WebsockServer's thread function


def check_port(port: int) -> None:
    """UserError unless ``port`` is a TCP port number (1 to 65535)."""
    if port not in PORTS:
        raise UserError(f"--port {port}: not a port number (1 to 65535)")


def _in_worker(frame: FrameType | None) -> bool:
    while frame is not None:
        code = frame.f_code
        if code.co_name == _WORKER and "viser" in code.co_filename:
            return True
        frame = frame.f_back
    return False


def _traceback_in_worker(tb: TracebackType | None) -> bool:
    while tb is not None:
        if _in_worker(tb.tb_frame):
            return True
        tb = tb.tb_next
    return False


def _server_thread(helper: threading.Thread) -> threading.Thread | None:
    """viser's server thread, read from the frame of ``WebsockServer.start`` where
    ``helper`` waits for it (None before it is started)."""
    frame = sys._current_frames().get(helper.ident or -1)
    while frame is not None:
        code = frame.f_code
        if code.co_name == "start" and "viser" in code.co_filename:
            thread = getattr(frame.f_locals.get("self"), "_server_thread", None)
            return thread if isinstance(thread, threading.Thread) else None
        frame = frame.f_back
    return None


def _wait_for(helper: threading.Thread, died: list[BaseException]) -> str | None:
    """Wait until ``helper`` has made the server (None), or why it will not: viser's thread
    died (``died``: the exception that killed it, if any) or did not listen in time."""
    deadline = time.monotonic() + START_SECONDS
    while True:
        helper.join(_POLL_SECONDS)
        if not helper.is_alive():
            return None
        thread = _server_thread(helper)
        dead = thread is not None and not thread.is_alive()
        # Read after the thread's death: its excepthook has run by then (it runs before the
        # thread is marked dead), so an exception that killed it is in ``died``.
        if died:
            return f"{type(died[0]).__name__}: {died[0]}"
        if dead:
            return "no free port among the thousand it tried"
        if time.monotonic() > deadline:
            return f"not listening after {START_SECONDS:.0f} s"


def start_viser(host: str, port: int, **kwargs: Any) -> viser.ViserServer:
    """``viser.ViserServer(host=host, port=port, **kwargs)``, or a UserError if its thread
    fails to listen (see the module docstring)."""
    import viser  # here: check_port is for the command line before the heavy imports

    check_port(port)
    made: list[viser.ViserServer] = []
    raised: list[BaseException] = []
    died: list[BaseException] = []  # what killed viser's thread
    abandoned = threading.Event()

    def make() -> None:
        try:
            server = viser.ViserServer(host=host, port=port, **kwargs)
        except BaseException as exc:
            raised.append(exc)
            return
        if abandoned.is_set():  # the caller gave up (Ctrl-C, timeout): serve nobody
            server.stop()
        else:
            made.append(server)

    previous = threading.excepthook

    def hook(args: threading.ExceptHookArgs) -> None:
        if _traceback_in_worker(args.exc_traceback) and args.exc_value is not None:
            died.append(args.exc_value)  # reported once, below, as one line
        else:
            previous(args)

    threading.excepthook = hook
    helper = threading.Thread(target=make, name="viser-start", daemon=True)
    try:
        helper.start()
        why = _wait_for(helper, died)
    except BaseException:
        abandoned.set()
        raise
    finally:
        if threading.excepthook is hook:
            threading.excepthook = previous
    if why is not None:
        # The helper stays blocked where viser waits (a daemon thread: it does not keep the
        # process alive). Releasing it would let viser finish making a server whose thread
        # is dead, and print its banner with an address that serves nothing.
        abandoned.set()
        raise UserError(f"cannot serve on {host}:{port} ({why})")
    if raised:
        raise raised[0]
    return made[0]
