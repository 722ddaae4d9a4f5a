"""What bounds the review server's memory, whatever its pages announce.

A page tells the server the size of its canvas, and the pictures are made to that size: a
page announcing a 30000 x 30000 canvas would otherwise make every mosaic 2.7 GB. So:

- the size a page's pictures are made for is clamped to an 8K screen
  (:func:`clamp_viewport`, :data:`MAX_VIEWPORT`, in either orientation, keeping the
  aspect); the browser scales a clamped picture up to the canvas, and clicks, which are
  fractions of the canvas, still land on the right pixel;
- the caches of pictures and of prepared scenes are bounded by bytes
  (:class:`BytesLRU`, and :class:`viewer.drawing.cache.PrefetchCache`'s ``max_bytes``), not by a
  count of entries whose size a page chooses;
- what a page that closed had made is dropped, and the freed memory is handed back to the
  operating system (:func:`give_back`). With glibc's defaults it would mostly stay with the
  process: an array freed above the allocator's mmap threshold raises the threshold to its
  size (up to 32 MB), so the next ones of that size are carved from the heaps of the threads
  that made them, and a heap's free space goes back only where whole pages are free. The
  server therefore fixes the threshold (:func:`bound_allocator`, :data:`MMAP_THRESHOLD`):
  pictures and arrays of 4 MB or more are mapped on their own and unmapped when freed.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterator
from typing import Generic, TypeVar

#: The largest canvas pictures are made for: an 8K screen (landscape, or portrait).
MAX_VIEWPORT = (7680, 4320)

K = TypeVar("K", bound=Hashable)
V = TypeVar("V")


def clamp_viewport(width: int, height: int) -> tuple[int, int]:
    """``width`` x ``height`` scaled down, keeping its aspect, to fit :data:`MAX_VIEWPORT`
    (its long side along the viewport's long side); unchanged if it fits."""
    long_side, short_side = max(MAX_VIEWPORT), min(MAX_VIEWPORT)
    scale = min(1.0, long_side / max(width, height), short_side / max(min(width, height), 1))
    if scale >= 1.0:
        return width, height
    return max(1, int(width * scale)), max(1, int(height * scale))


def picture_size(width: int, height: int, shown: tuple[int, int] | None) -> tuple[int, int] | None:
    """The size to make a page's pictures when its canvas says it is ``width`` x ``height``
    and the pictures are ``shown`` at that size (None: none yet), within 8K
    (:func:`clamp_viewport`); None for a canvas too small to be one (under 64 pixels).

    viser lowers the canvas's resolution while its 3D frames are slow (an adaptive pixel
    ratio: after the 3D camera moves, on a software renderer) and says so. A picture made to
    that would be scaled up by the browser: blurred, no longer pixel for pixel. So a size of
    the same shape as the one shown (within 1 %) but smaller is taken for that and the one
    shown is kept; a canvas of another shape, or larger, is a new one.

    >>> picture_size(1400, 1000, None)
    (1400, 1000)
    >>> picture_size(1050, 750, (1400, 1000))  # the same canvas at 3/4 of its pixel ratio
    (1400, 1000)
    >>> picture_size(1200, 1000, (1400, 1000))  # a narrower canvas
    (1200, 1000)
    """
    if width < 64 or height < 64:
        return None
    size = clamp_viewport(width, height)
    if shown is not None and size[0] < shown[0] and size[1] < shown[1]:
        if abs(size[0] * shown[1] - size[1] * shown[0]) <= 0.01 * shown[0] * shown[1]:
            return shown
    return size


class BytesLRU(Generic[K, V]):
    """A least-recently-used mapping bounded by the bytes of its values (``weigh``), not
    their count. The entry put last is always kept, even alone over the bound: it is the
    one a page is about to show. Pages' threads share it: every operation holds a lock."""

    def __init__(self, max_bytes: int, weigh: Callable[[V], int]) -> None:
        self.max_bytes = max_bytes
        self._weigh = weigh
        self._items: OrderedDict[K, tuple[V, int]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    @property
    def nbytes(self) -> int:
        """The bytes of the values held (as weighed when they were put)."""
        return self._bytes

    def get(self, key: K) -> V | None:
        with self._lock:
            hit = self._items.get(key)
            if hit is None:
                return None
            self._items.move_to_end(key)
            return hit[0]

    def put(self, key: K, value: V) -> None:
        size = int(self._weigh(value))
        with self._lock:
            self._pop(key)
            self._items[key] = (value, size)
            self._bytes += size
            while self._bytes > self.max_bytes and len(self._items) > 1:
                _, (_, dropped) = self._items.popitem(last=False)
                self._bytes -= dropped

    def _pop(self, key: K) -> V | None:
        hit = self._items.pop(key, None)
        if hit is None:
            return None
        self._bytes -= hit[1]
        return hit[0]

    def pop(self, key: K) -> V | None:
        with self._lock:
            return self._pop(key)

    def drop(self, unwanted: Callable[[K], bool]) -> None:
        """Remove every entry whose key is ``unwanted``."""
        with self._lock:
            for key in [k for k in self._items if unwanted(k)]:
                self._pop(key)

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._bytes = 0

    def keys(self) -> list[K]:
        with self._lock:
            return list(self._items)

    def __contains__(self, key: object) -> bool:
        with self._lock:
            return key in self._items

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)

    def __iter__(self) -> Iterator[K]:
        return iter(self.keys())


#: Allocations of this size or more get their own mapping (glibc's ``M_MMAP_THRESHOLD``):
#: a 1400 x 1000 mosaic is 4.2 MB, a panel resized for it under 1 MB.
MMAP_THRESHOLD = 4 * 2**20
_M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter number


def _libc() -> ctypes.CDLL | None:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"))
        libc.malloc_trim.argtypes, libc.malloc_trim.restype = [ctypes.c_size_t], ctypes.c_int
        libc.mallopt.argtypes, libc.mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    except (OSError, AttributeError, TypeError):  # not glibc: its own ways, left alone
        return None
    return libc


_LIBC = _libc()


def bound_allocator() -> None:
    """Give arrays of :data:`MMAP_THRESHOLD` or more their own mappings from now on, in this
    process (glibc; nothing elsewhere): freed, they go back to the operating system."""
    if _LIBC is not None:
        _LIBC.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)


def give_back() -> None:
    """Collect unreachable objects (a closed page's handles hold each other in cycles) and
    return the freed memory to the operating system where the C library allows it."""
    gc.collect()
    if _LIBC is not None:
        _LIBC.malloc_trim(0)
