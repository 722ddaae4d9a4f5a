"""What a ROS 1 bag cut short, or never closed, still holds.

A ROS 1 bag (format 2.0) writes its index last: a recording that was killed, or a file cut
short, has none, and ``rosbags`` refuses it ("reindex before reading"). Its records are
still there in order: after the ``#ROSBAG V2.0`` line and the bag header, chunks
(``op=0x05``; uncompressed, ``bz2`` or ``lz4``), each holding connection records
(``op=0x07``: topic, type, message definition) and message records (``op=0x02``:
connection, time, the serialised message). :class:`SalvageReader` reads them front to back
and stops at the first record that is not whole; it offers what ingest uses of a
``rosbags`` reader (``connections``, ``messages``, ``deserialize``, ``close``).
"""

from __future__ import annotations

import bz2
import struct
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

MAGIC = b"#ROSBAG V2.0\n"
_MSGDATA, _BAGHEADER, _CHUNK, _CONNECTION = 2, 3, 5, 7


@dataclass(frozen=True)
class SalvagedConnection:
    """A connection record: what rosbags' connections give ingest."""

    id: int
    topic: str
    msgtype: str
    msgdef: str


def _fields(header: bytes) -> dict[str, bytes]:
    """A record header's ``name=value`` fields."""
    out: dict[str, bytes] = {}
    at = 0
    while at + 4 <= len(header):
        (n,) = struct.unpack_from("<I", header, at)
        field = header[at + 4 : at + 4 + n]
        at += 4 + n
        name, _, value = field.partition(b"=")
        out[name.decode("latin-1")] = value
    return out


def _records(
    data: Any, at: int, end: int | None = None
) -> Iterator[tuple[dict[str, bytes], int, int]]:
    """The records of ``data[at:end]``: their header fields and where their data lies
    (start, length). A record whose data is cut ends them, given with the data there is and
    the field ``cut`` (a chunk's whole records can still be read from it)."""
    end = len(data) if end is None else end
    while at + 4 <= end:
        (hlen,) = struct.unpack_from("<I", data, at)
        if at + 4 + hlen + 4 > end:
            return
        fields = _fields(bytes(data[at + 4 : at + 4 + hlen]))
        (dlen,) = struct.unpack_from("<I", data, at + 4 + hlen)
        start = at + 8 + hlen
        if start + dlen > end:
            fields["cut"] = b"1"
            yield fields, start, end - start
            return
        yield fields, start, dlen
        at = start + dlen


def _decompress(kind: str, data: bytes) -> bytes:
    """A chunk's records, as far as its (possibly cut) data goes."""
    if kind == "none":
        return data
    if kind == "bz2":
        try:
            return bz2.BZ2Decompressor().decompress(data)
        except (OSError, EOFError, ValueError):
            return b""
    if kind == "lz4":
        import lz4.frame

        try:
            return lz4.frame.LZ4FrameDecompressor().decompress(data)
        except RuntimeError:
            return b""
    return b""


def is_unindexed(path: Path) -> bool:
    """Whether ``path`` is a ROS 1 bag whose index is missing (never closed, or cut)."""
    try:
        with path.open("rb") as f:
            head = f.read(4096 + 64)
        size = path.stat().st_size
    except OSError:
        return False
    if not head.startswith(MAGIC):
        return False
    for fields, _, _ in _records(head, len(MAGIC)):
        if fields.get("op") == bytes([_BAGHEADER]):
            (index_pos,) = struct.unpack("<Q", fields.get("index_pos", bytes(8))[:8])
            return index_pos == 0 or index_pos >= size
        return False
    return False


class SalvageReader:
    """The connections and messages of a ROS 1 bag without its index (module docstring).

    The file is mapped, not read: a message is found again from its chunk (decompressed
    once for its run of messages) when :meth:`messages` hands it out."""

    def __init__(self, path: Path) -> None:
        import mmap

        from rosbags.typesys import Stores, get_types_from_msg, get_typestore
        from rosbags.typesys.msg import normalize_msgtype

        self.path = path
        with path.open("rb") as f:
            self._map: Any = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        # (chunk start, length, compression) per chunk; (conn, time ns, chunk, at, length)
        # per message, ``chunk`` -1 for a record outside chunks (its place in the file).
        self._chunks: list[tuple[int, int, str]] = []
        self._messages: list[tuple[int, int, int, int, int]] = []
        found: dict[int, SalvagedConnection] = {}
        for fields, at, n in _records(self._map, len(MAGIC)):
            op = fields.get("op", b"\x00")[0]
            if op == _CHUNK:
                kind = fields.get("compression", b"none").decode()
                self._chunks.append((at, n, kind))
                inner = self._chunk(len(self._chunks) - 1)
                for sub, a, m in _records(inner, 0):
                    if "cut" not in sub:
                        self._take(
                            sub, inner, a, m, len(self._chunks) - 1, found, normalize_msgtype
                        )
            elif op in (_CONNECTION, _MSGDATA) and "cut" not in fields:
                self._take(fields, self._map, at, n, -1, found, normalize_msgtype)
        self.connections = list(found.values())
        self._typestore = get_typestore(Stores.ROS1_NOETIC)
        for conn in self.connections:
            if conn.msgtype not in self._typestore.types and conn.msgdef:
                self._typestore.register(get_types_from_msg(conn.msgdef, conn.msgtype))

    def _chunk(self, k: int) -> bytes:
        at, n, kind = self._chunks[k]
        return _decompress(kind, bytes(self._map[at : at + n]))

    def _take(
        self,
        fields: dict[str, bytes],
        data: Any,
        at: int,
        n: int,
        chunk: int,
        found: dict[int, SalvagedConnection],
        normalize: Any,
    ) -> None:
        op = fields.get("op", b"\x00")[0]
        if op == _CONNECTION:
            (cid,) = struct.unpack("<I", fields["conn"][:4])
            if cid not in found:
                inner = _fields(bytes(data[at : at + n]))
                found[cid] = SalvagedConnection(
                    cid,
                    fields["topic"].decode(),
                    normalize(inner.get("type", b"").decode()),
                    inner.get("message_definition", b"").decode(),
                )
        elif op == _MSGDATA:
            (cid,) = struct.unpack("<I", fields["conn"][:4])
            sec, nsec = struct.unpack("<II", fields["time"][:8])
            self._messages.append((cid, sec * 1_000_000_000 + nsec, chunk, at, n))

    def messages(
        self, connections: Collection[SalvagedConnection] = ()
    ) -> Iterator[tuple[SalvagedConnection, int, bytes]]:
        """``(connection, time ns, raw message)`` in file order (all when none are given)."""
        by_id = {c.id: c for c in self.connections}
        wanted = {c.id for c in connections} or set(by_id)
        held: tuple[int, bytes] = (-2, b"")
        for cid, t, chunk, at, n in self._messages:
            if cid not in wanted or cid not in by_id:
                continue
            if chunk < 0:
                raw = bytes(self._map[at : at + n])
            else:
                if held[0] != chunk:
                    held = (chunk, self._chunk(chunk))
                raw = held[1][at : at + n]
            yield by_id[cid], t, raw

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        """The message ``raw`` of type ``msgtype``."""
        return self._typestore.deserialize_ros1(raw, msgtype)

    def close(self) -> None:
        """Unmap the file."""
        self._map.close()
