"""A cache of prepared scenes, filled in the background before a reviewer gets there.

Pages ask for the scenes they are about to show (:meth:`PrefetchCache.prefetch`); one worker
thread prepares them, the most recent request first (a reviewer who skips ahead makes older
requests pointless), once requests have paused for :data:`QUIET_SECONDS` (a page showing a
scene needs the CPU more). :meth:`PrefetchCache.get` returns a prepared scene at once, waits for
one being prepared, or prepares it in the calling thread if nobody has started it, so a page
never queues behind prefetching it did not ask for.

Keys are ``(scene id, version)``: a new version of a scene (its poses changed) is prepared
anew, and the least recently used entries are dropped beyond ``size`` entries or beyond
``max_bytes`` (as ``weigh`` says, weighed again whenever the cache is used: a prepared scene
grows with the pictures drawn from it for the pages' canvases). The entry used last is kept
even alone over the bound.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

T = TypeVar("T")

_MAX_QUEUED = 6
#: Background work waits this long after the last request, so that it does not take the
#: CPU from the page that is showing the scene just asked for.
QUIET_SECONDS = 0.25


def _no_weight(_value: object) -> int:
    return 0


class PrefetchCache(Generic[T]):
    """Values made by ``make`` callables, kept for the ``size`` most recently used keys and
    within ``max_bytes`` of them (``weigh``: the bytes a value holds)."""

    def __init__(
        self,
        *,
        size: int = 8,
        max_bytes: int | None = None,
        weigh: Callable[[T], int] = _no_weight,
    ) -> None:
        self._size = size
        self._max_bytes = max_bytes
        self._weigh = weigh
        self._cond = threading.Condition()
        self._done: OrderedDict[Hashable, T] = OrderedDict()
        self._failed: dict[Hashable, BaseException] = {}
        self._running: set[Hashable] = set()
        self._queue: OrderedDict[Hashable, Callable[[], T]] = OrderedDict()
        self._stopped = False
        self._last_request = 0.0
        self._worker = threading.Thread(target=self._work, name="prefetch", daemon=True)
        self._worker.start()

    def _store(self, key: Hashable, value: T | None, error: BaseException | None) -> None:
        with self._cond:
            self._running.discard(key)
            if error is None:
                self._done[key] = value  # type: ignore[assignment]
                self._done.move_to_end(key)
                self._trim()
            else:
                self._failed[key] = error
            self._cond.notify_all()

    def _trim(self) -> None:
        while len(self._done) > self._size:
            self._done.popitem(last=False)
        if self._max_bytes is None:
            return
        weights = [self._weigh(v) for v in self._done.values()]
        total = sum(weights)
        while total > self._max_bytes and len(self._done) > 1:
            self._done.popitem(last=False)
            total -= weights.pop(0)

    def trim(self) -> None:
        """Drop entries until the values fit ``max_bytes`` again (they may have grown)."""
        with self._cond:
            self._trim()

    def values(self) -> list[T]:
        """The values held now, least recently used first."""
        with self._cond:
            return list(self._done.values())

    def nbytes(self) -> int:
        """The bytes of the values held, as ``weigh`` says now."""
        with self._cond:
            return sum(self._weigh(v) for v in self._done.values())

    def _run(self, key: Hashable, make: Callable[[], T]) -> tuple[T | None, Exception | None]:
        try:
            value = make()
        except Exception as exc:  # handed to whoever asks for the key
            self._store(key, None, exc)
            return None, exc
        self._store(key, value, None)
        return value, None

    def _work(self) -> None:
        while True:
            with self._cond:
                while not self._stopped:
                    quiet = self._last_request + QUIET_SECONDS - time.monotonic()
                    if self._queue and quiet <= 0:
                        break
                    self._cond.wait(timeout=quiet if self._queue else None)
                if self._stopped:
                    return
                key, make = self._queue.popitem(last=True)
                self._running.add(key)
            self._run(key, make)

    def prefetch(self, key: Hashable, make: Callable[[], T]) -> None:
        """Prepare ``key`` in the background unless it is ready or under way."""
        with self._cond:
            self._last_request = time.monotonic()
            if key in self._done or key in self._running or self._stopped:
                return
            self._failed.pop(key, None)
            self._queue[key] = make
            self._queue.move_to_end(key)
            while len(self._queue) > _MAX_QUEUED:
                self._queue.popitem(last=False)
            self._cond.notify_all()

    def put(self, key: Hashable, value: T) -> None:
        """Keep ``value`` as ``key``'s, made elsewhere (a repaired pose's overlays, made from
        the scene's previous ones)."""
        with self._cond:
            self._queue.pop(key, None)
            self._done[key] = value
            self._done.move_to_end(key)
            self._trim()
            self._cond.notify_all()

    def drop(self, unwanted: Callable[[Hashable], bool]) -> None:
        """Forget the values of every key that is ``unwanted`` (not one being made)."""
        with self._cond:
            for key in [k for k in self._done if unwanted(k)]:
                del self._done[key]

    def ready(self, key: Hashable) -> bool:
        with self._cond:
            return key in self._done

    def get(self, key: Hashable, make: Callable[[], T]) -> T:
        """The value of ``key``: cached, awaited, or made now in this thread. An exception
        raised by ``make`` is raised here (once; the next call tries again)."""
        with self._cond:
            self._last_request = time.monotonic()
            while key in self._running:
                self._cond.wait()
            if key in self._done:
                self._done.move_to_end(key)
                self._trim()
                return self._done[key]
            if key in self._failed:
                raise self._failed.pop(key)
            self._queue.pop(key, None)
            self._running.add(key)
        value, error = self._run(key, make)
        if error is not None:
            with self._cond:
                self._failed.pop(key, None)
            raise error
        return value  # type: ignore[return-value]

    def stop(self, timeout: float = 5.0) -> None:
        """End the worker, letting a preparation under way finish (within ``timeout``), so
        that no native code is running when the process exits."""
        with self._cond:
            self._stopped = True
            self._queue.clear()
            self._cond.notify_all()
        if self._worker is not threading.current_thread():
            self._worker.join(timeout)
