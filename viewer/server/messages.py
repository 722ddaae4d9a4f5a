"""What a connection may send: viser's messages, and nothing else.

viser 1.1.1 reads each websocket frame in its connection's consumer loop (``_message_consumer``
in ``viser.infra``) and decodes it with ``Message.deserialize``; a frame that is not one of
its messages (a text frame, bytes that are not msgpack, an unknown message type, missing
fields) raises there, which ends the connection and prints a traceback to the server's log,
once per frame a client cares to send. A message whose fields have the wrong types (a
string for a tuple, a tuple of the wrong length) decodes, and then raises in the handler it
reaches, with a traceback too.

:func:`install` wraps, for every connection, the ``recv`` that loop calls: a frame that is
not a message whose fields match their declared types (:func:`why_malformed`) is dropped
with one line in the log, and the loop gets the next one; the connection stays open. It
reaches the connection through the same private table as :mod:`viewer.server.access`
(``_live_connections`` of viser's ``WebsockServer``), from a connect callback that runs
before the loop starts. Whatever still fails in viser's event loop is one line too
(:func:`install` sets the loop's exception handler).

A frame is decoded twice (here, then by viser): the page's messages are camera updates,
clicks and key commands of a few hundred bytes.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
import threading
import types
import typing
from collections.abc import Callable
from typing import Any, Literal, Union, get_args, get_origin

import msgspec
import viser
from viser.infra import Message

#: At most this much of a frame's failure goes into its log line.
_WHY_CHARS = 160


@functools.cache
def _message_types() -> dict[str, type]:
    return {cls.__name__: cls for cls in Message.get_subclasses()}


@functools.cache
def _fields(cls: type) -> dict[str, Any] | None:
    """The wire fields of a message type and their declared types (None: not known here)."""
    if not dataclasses.is_dataclass(cls):
        return None
    try:
        hints = typing.get_type_hints(cls)
    except Exception:  # an annotation this Python cannot resolve: viser's to decode
        return None
    return {f.name: hints[f.name] for f in dataclasses.fields(cls) if f.name in hints}


def conforms(value: Any, hint: Any) -> bool:
    """True if ``value``, as msgpack decoded it (lists for tuples), may stand for a field
    declared ``hint``. Types this does not know (arrays, nested classes) are viser's to
    decode."""
    origin = get_origin(hint)
    if hint in (int, float):
        return isinstance(value, (int, float))  # both are a number in JavaScript
    if hint in (str, bool):
        return isinstance(value, hint)
    if hint is bytes:
        return isinstance(value, (bytes, bytearray, memoryview))
    if hint is type(None):
        return value is None
    if origin is Literal:
        return any(type(value) is type(a) and value == a for a in get_args(hint))
    if origin in (Union, types.UnionType):
        return any(conforms(value, a) for a in get_args(hint))
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            return False
        args = get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            return all(conforms(v, args[0]) for v in value)
        return len(value) == len(args) and all(map(conforms, value, args))
    if origin is list or hint is list:
        return isinstance(value, (list, tuple))
    if origin is dict or hint is dict:
        return isinstance(value, dict)
    return True


def why_malformed(frame: Any) -> str | None:
    """Why ``frame`` (what a websocket ``recv`` returned) is not one of viser's messages, in
    one line; None if it is one."""
    if not isinstance(frame, bytes):
        return f"a text frame ({len(frame)} characters)"
    size = f"({len(frame)} bytes)"
    try:
        mapping = msgspec.msgpack.decode(frame)
    except Exception as exc:
        return f"not msgpack: {_one_line(exc)} {size}"
    if not isinstance(mapping, dict) or not isinstance(mapping.get("type"), str):
        return f"not a message (no type) {size}"
    cls = _message_types().get(mapping["type"])
    if cls is None:
        return f"unknown message type {mapping['type'][:40]!r} {size}"
    fields = _fields(cls)
    if fields is not None:
        for name, value in mapping.items():
            if name == "type":
                continue
            if name not in fields:
                return f"{cls.__name__} has no field {str(name)[:40]!r} {size}"
            if not conforms(value, fields[name]):
                return f"{cls.__name__}.{name} is not a {fields[name]} {size}"
    try:
        Message.deserialize(frame)
    except Exception as exc:
        return f"{cls.__name__}: {_one_line(exc)} {size}"
    return None


def _one_line(exc: BaseException) -> str:
    return " ".join(f"{type(exc).__name__}: {exc}".split())[:_WHY_CHARS]


class FrameFilter:
    """Drops malformed frames; counts them (:attr:`dropped`) and logs one line each."""

    def __init__(self, log: Callable[[str], None] | None = None) -> None:
        self.dropped = 0
        self._lock = threading.Lock()
        self._log = log or (lambda line: print(line, file=sys.stderr, flush=True))

    def wrap(self, connection: Any, remote: str) -> None:
        """Make ``connection.recv`` skip malformed frames (see the module docstring)."""
        recv = connection.recv

        async def checked_recv(*args: Any, **kwargs: Any) -> Any:
            while True:
                frame = await recv(*args, **kwargs)
                try:
                    why = why_malformed(frame)
                except Exception:  # a flaw of this check must not cost a page its frame
                    why = None
                if why is None:
                    return frame
                with self._lock:
                    self.dropped += 1
                self._log(f"review: dropped a malformed message from {remote}: {why}")

        connection.recv = checked_recv


def install(server: viser.ViserServer) -> FrameFilter:
    """Filter the frames of every connection to ``server``; RuntimeError if this viser
    offers no way to (another version), as :func:`viewer.server.access.install` does."""
    ws = getattr(server, "_websock_server", None)
    live = getattr(ws, "_live_connections", None)
    if ws is None or not isinstance(live, dict) or not hasattr(ws, "on_client_connect"):
        raise RuntimeError(f"viser {viser.__version__} offers no way to filter what pages send")
    frames = FrameFilter()

    async def wrap(conn) -> None:
        raw = live.get(conn.client_id)
        if raw is None or not hasattr(raw, "recv"):
            return
        remote = getattr(raw, "remote_address", None)
        frames.wrap(raw, str(remote[0]) if remote else "?")

    ws.on_client_connect(wrap)
    loop = getattr(ws, "_background_event_loop", None)
    if loop is not None:
        loop.call_soon_threadsafe(loop.set_exception_handler, _one_line_handler)
    return frames


def _one_line_handler(loop: Any, context: dict[str, Any]) -> None:
    """viser's event loop's failures (a handler raising on what a page sent), one line each
    instead of a traceback."""
    exc = context.get("exception")
    what = _one_line(exc) if exc is not None else str(context.get("message", "?"))
    print(f"review: a page's message failed in viser: {what}", file=sys.stderr, flush=True)
