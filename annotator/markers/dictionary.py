"""ArUco dictionaries: OpenCV's predefined ones by name, and custom ones from a file.

Wherever a dictionary is named (dataset.yaml's ``markers.dictionary``, board.yaml's
``dictionary``, ``annotator markers --dictionary``, ``annotator calibrate --dictionary``) it
is either a predefined name (``DICT_4X4_1000``) or the path of a dictionary file in
OpenCV's own format, as ``cv2.aruco.Dictionary.writeDictionary`` writes it::

    %YAML 1.2
    ---
    nmarkers: 35
    markersize: 6
    maxCorrectionBits: 5
    marker_0: "1011...0"        # markersize**2 bits, row by row, 1 = white
    ...

Relative paths are resolved by the reader of the file that names them (against that
file's folder: see :func:`resolve_dictionary`), so that a dataset can be moved as a whole.
:func:`custom_dictionary` makes one with ``cv2.aruco.extendDictionary`` and checks the
smallest distance between its markers (in bits, over the four turns of each), which is what
decides how many wrong bits a reading can correct.
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from annotator.errors import UserError
from annotator.io.atomic import write_text
from annotator.io.documents import read_text

PREDEFINED_PREFIX = "DICT_"


def is_predefined(name: str) -> bool:
    """True if ``name`` is one of OpenCV's predefined dictionary names."""
    return name.startswith(PREDEFINED_PREFIX) and isinstance(getattr(cv2.aruco, name, None), int)


def resolve_dictionary(name: str, folder: str | Path) -> str:
    """The dictionary as it should be opened: a predefined name unchanged, a file path made
    absolute against ``folder`` (the folder of the file that names it)."""
    if name.startswith(PREDEFINED_PREFIX):
        return name
    path = Path(os.path.expanduser(name))
    return str(path if path.is_absolute() else (Path(folder) / path).resolve())


def dictionary(name: str) -> cv2.aruco.Dictionary:
    """The dictionary ``name``: a predefined name (``DICT_4X4_1000``) or the path of a
    dictionary file (OpenCV's format); UserError naming the file if it does not parse."""
    if name.startswith(PREDEFINED_PREFIX):
        if not is_predefined(name):
            raise UserError(f"unknown ArUco dictionary {name!r}")
        return _predefined(name)
    path = Path(name)
    if not path.is_file():
        raise UserError(
            f"unknown ArUco dictionary {name!r}: neither a predefined name (DICT_...) nor a "
            "dictionary file",
            path=path if path.suffix else None,
        )
    stat = path.stat()
    return _from_file(str(path.resolve()), stat.st_mtime_ns, stat.st_size)


def dictionary_size(name: str) -> int:
    """How many distinct markers the dictionary has."""
    return int(dictionary(name).bytesList.shape[0])


@lru_cache(maxsize=16)
def _predefined(name: str) -> cv2.aruco.Dictionary:
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


@lru_cache(maxsize=16)
def _from_file(path: str, _mtime_ns: int, _size: int) -> cv2.aruco.Dictionary:
    # Keyed by modification time and size too: a file rewritten in place is read again.
    text = read_text(path)
    bad = "not an ArUco dictionary file (OpenCV's format: nmarkers, markersize, marker_0, ...)"
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError):  # the Python binding wraps parse errors in SystemError
        raise UserError(f"{bad}: its YAML does not parse", path=path) from None
    try:
        root = fs.root()
        n = int(root.getNode("nmarkers").real())
        size = int(root.getNode("markersize").real())
        if n < 1 or not 3 <= size <= 8:
            raise UserError(
                f"{bad}: nmarkers must be at least 1 and markersize 3..8, got {n} and {size}",
                path=path,
            )
        bits = []
        for k in range(n):
            node = root.getNode(f"marker_{k}")
            code = node.string() if node.isString() else ""
            if len(code) != size * size or set(code) - {"0", "1"}:
                raise UserError(
                    f"{bad}: marker_{k} must be a string of {size * size} bits (0/1)", path=path
                )
            bits.append(np.frombuffer(code.encode(), np.uint8).reshape(size, size) - ord("0"))
        node = root.getNode("maxCorrectionBits")
        correction = int(node.real()) if not node.empty() else 0
    finally:
        fs.release()
    _check_distinct(bits, path)
    byte_list = np.concatenate([cv2.aruco.Dictionary.getByteListFromBits(b) for b in bits])
    return cv2.aruco.Dictionary(byte_list, size, correction)


def _check_distinct(bits: list[np.ndarray], path: str) -> None:
    """UserError unless every marker reads as itself alone: no two markers alike in any turn
    (one id would be read for the other), none alike turned (its corners' order unknown)."""
    turns: dict[bytes, tuple[int, int]] = {}  # each earlier marker's four turns
    for i, b in enumerate(bits):
        same = turns.get(b.tobytes())
        if same is not None:
            j, k = same
            turned = "" if k == 0 else f" turned by {90 * k} degrees"
            raise UserError(
                f"marker_{i} is marker_{j}{turned}: a reading could not tell them apart; every marker must differ from "
                "every other in all four turns",
                path=path,
            )
        for k in range(1, 4):
            if np.array_equal(np.rot90(b, k), b):
                raise UserError(
                    f"marker_{i} looks the same turned by {90 * k} degrees: its corners' order "
                    "could not be read",
                    path=path,
                )
        for k in range(4):
            turns.setdefault(np.rot90(b, k).tobytes(), (i, k))


def marker_bit_grids(d: cv2.aruco.Dictionary) -> np.ndarray:
    """(n, s, s) uint8 inner bits of every marker of ``d`` (1 = white), row by row."""
    n = d.markerSize
    return np.stack(
        [
            cv2.aruco.Dictionary.getBitsFromByteList(d.bytesList[i : i + 1], n)
            for i in range(len(d.bytesList))
        ]
    )


def min_distance(d: cv2.aruco.Dictionary) -> int:
    """Smallest Hamming distance (bits) between two markers of ``d`` in any of their turns,
    and between a marker and its own turns (a marker that looks like itself turned cannot
    tell its orientation)."""
    bits = marker_bit_grids(d).astype(bool)
    n = len(bits)
    flat = bits.reshape(n, -1)
    best = bits.shape[1] ** 2
    for k in range(1, 4):
        turned = np.rot90(bits, k, axes=(1, 2)).reshape(n, -1)
        best = min(best, int((flat != turned).sum(axis=1).min()))
    for k in range(4):
        turned = np.rot90(bits, k, axes=(1, 2)).reshape(n, -1)
        dist = (flat[:, None, :] != turned[None, :, :]).sum(axis=2)
        dist[np.arange(n), np.arange(n)] = best  # a marker against itself unturned
        best = min(best, int(dist.min()))
    return best


def custom_dictionary(
    count: int, bits: int, *, min_bits: int, seed: int = 0
) -> cv2.aruco.Dictionary:
    """``count`` markers of ``bits`` x ``bits`` cells, at least ``min_bits`` apart (made by
    ``cv2.aruco.extendDictionary``); UserError if that distance is not reached."""
    if count < 1 or not 3 <= bits <= 8 or min_bits < 1:
        raise UserError(
            f"a dictionary needs at least 1 marker of 3..8 bits a side and a minimum distance of "
            f"at least 1, got {count} markers, {bits} bits, distance {min_bits}"
        )
    d = cv2.aruco.extendDictionary(count, bits, cv2.aruco.Dictionary(), seed)
    reached = min_distance(d)
    if reached < min_bits:
        raise UserError(
            f"{count} markers of {bits}x{bits} bits reach a minimum distance of {reached} bits, "
            f"not {min_bits}: ask for fewer markers, more bits or a smaller distance"
        )
    # OpenCV's rule: a reading may be off by up to (distance - 1) / 2 bits.
    return cv2.aruco.Dictionary(d.bytesList, bits, (reached - 1) // 2)


def write_dictionary(path: str | Path, d: cv2.aruco.Dictionary) -> None:
    """Write ``d`` atomically in OpenCV's dictionary format (readable by OpenCV itself)."""
    fs = cv2.FileStorage(".yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    d.writeDictionary(fs)
    write_text(path, fs.releaseAndGetString())
