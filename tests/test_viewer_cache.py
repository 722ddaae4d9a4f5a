"""The prefetch cache: made once, in the background or in the asking thread, most recent
request first, versions, failures and the size bound."""

from __future__ import annotations

import threading
import time

import pytest

from viewer.drawing import cache
from viewer.drawing.cache import PrefetchCache


@pytest.fixture()
def quick(monkeypatch):
    monkeypatch.setattr(cache, "QUIET_SECONDS", 0.0)
    c: PrefetchCache[str] = PrefetchCache(size=3)
    yield c
    c.stop()


def test_get_makes_a_value_once_and_keeps_it(quick) -> None:
    calls = []
    make = lambda: calls.append(1) or "v"  # noqa: E731
    assert quick.get(("s", 1), make) == "v"
    assert quick.get(("s", 1), make) == "v"
    assert len(calls) == 1
    assert quick.get(("s", 2), make) == "v" and len(calls) == 2  # a new version


def test_prefetched_values_are_ready_and_waited_for(quick) -> None:
    release = threading.Event()
    made = threading.Event()

    def slow() -> str:
        made.set()
        release.wait(5)
        return "slow"

    quick.prefetch("a", slow)
    assert made.wait(5)
    threading.Timer(0.05, release.set).start()
    assert quick.get("a", lambda: "other") == "slow"  # waits for the one under way
    assert quick.ready("a")


def test_most_recent_request_first_and_failures_raise(quick) -> None:
    gate, started = threading.Event(), threading.Event()
    order = []
    quick.prefetch("block", lambda: started.set() or (gate.wait(5) and "b"))
    assert started.wait(5)  # the worker is busy: the next three queue up
    for key in ("x", "y", "z"):
        quick.prefetch(key, lambda key=key: order.append(key) or key)
    gate.set()
    end = time.monotonic() + 5
    while not all(quick.ready(k) for k in "xyz") and time.monotonic() < end:
        time.sleep(0.01)
    assert order == ["z", "y", "x"]
    assert quick.get("z", lambda: "never") == "z"

    def broken() -> str:
        raise ValueError("bad scene")

    with pytest.raises(ValueError, match="bad scene"):
        quick.get("bad", broken)
    assert quick.get("bad", lambda: "fixed") == "fixed"  # the next call tries again


def test_the_least_recently_used_values_are_dropped(quick) -> None:
    for key in "abcd":
        quick.get(key, lambda key=key: key)
    assert not quick.ready("a") and all(quick.ready(k) for k in "bcd")


def test_put_and_drop_keep_what_a_repair_made() -> None:
    cache: PrefetchCache[str] = PrefetchCache(size=4)
    try:
        cache.put(("a", 1), "first")
        cache.put(("a", 2), "second")
        cache.put(("b", 1), "other scene")
        cache.drop(lambda key: key[0] == "a" and key != ("a", 2))
        assert not cache.ready(("a", 1)) and cache.ready(("a", 2)) and cache.ready(("b", 1))
        assert cache.get(("a", 2), lambda: "made again") == "second"
    finally:
        cache.stop()
