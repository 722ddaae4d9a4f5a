"""A bare client of viser's websocket protocol, for the tests and benchmarks: what a page
that is not viser's own (a script, a hostile or broken client) can send the review server.

A page is a websocket with viser's subprotocol; the server treats it as a page once it has
sent a camera message (:func:`camera_message`), which also announces the size of its canvas.
Messages to the server are msgpack maps with a ``type`` field; what the server sends back
(zstd-compressed windows of messages) is not decoded here.
"""

from __future__ import annotations

import socket
from typing import Any

import msgspec
import viser
from websockets.sync.client import ClientConnection, connect

SUBPROTOCOL = f"viser-v{viser.__version__}"


def camera_message(width: int, height: int) -> bytes:
    """A viewer camera message announcing a ``width`` x ``height`` canvas."""
    return msgspec.msgpack.encode(
        {
            "type": "ViewerCameraMessage",
            "wxyz": (1.0, 0.0, 0.0, 0.0),
            "position": (0.0, 0.0, -1.0),
            "fov": 1.0,
            "near": 0.01,
            "far": 100.0,
            "image_height": height,
            "image_width": width,
            "look_at": (0.0, 0.0, 0.0),
            "up_direction": (0.0, -1.0, 0.0),
        }
    )


def open_page(
    port: int, *, width: int = 1400, height: int = 1000, **kwargs: Any
) -> ClientConnection:
    """A connection to the server on 127.0.0.1:``port`` that has announced a canvas (it
    reads nothing unless its owner calls ``recv``)."""
    ws = connect(
        f"ws://127.0.0.1:{port}/",
        subprotocols=[SUBPROTOCOL],  # type: ignore[list-item]
        proxy=None,
        open_timeout=10,
        max_size=None,
        **kwargs,
    )
    ws.send(camera_message(width, height))
    return ws


def drop(ws: ClientConnection) -> None:
    """Leave abruptly, as a killed browser does (no closing handshake)."""
    try:
        ws.socket.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    ws.socket.close()
