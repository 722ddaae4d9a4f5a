"""Scenes that disappear under an open review page (issue 26), in real headless Chromium: a
deleted scene is reported in the page and never decided, a key pressed while the page is
still switching decides nothing, and a dataset deleted whole is reported and its decisions
are shown as not saved. The server's log gets no traceback."""

from __future__ import annotations

import contextlib
import json
import shutil
import threading
import time
from pathlib import Path

import pytest

from devkit.headless import free_port
from devkit.polling import wait_until

playwright = pytest.importorskip("playwright.sync_api")


import viewer.page.rendering  # noqa: E402
from viewer.page.panel import Panel  # noqa: E402
from viewer.server.app import ReviewApp  # noqa: E402

pytestmark = [
    pytest.mark.browser,
    pytest.mark.slow,
    pytest.mark.filterwarnings("ignore:Queued a:UserWarning"),
]

VIEWPORT = {"width": 1400, "height": 1000}
GONE = "the scene's folder is gone"
NOT_SAVED = "is NOT saved"


@pytest.fixture()
def shown(monkeypatch) -> list[str]:
    """The scene titles every page was sent, in order."""
    titles: list[str] = []
    lock = threading.Lock()
    real = Panel.show

    def show(self, view, keys):
        with lock:
            titles.append(view.title.splitlines()[0])
        return real(self, view, keys)

    monkeypatch.setattr(Panel, "show", show)
    return titles


@contextlib.contextmanager
def _serving(root: Path):
    app = ReviewApp(root, host="127.0.0.1", port=free_port(), start_scene="000000")
    try:
        yield app
    finally:
        app.stop()


def _decisions(root: Path) -> dict[str, str]:
    return {
        p.parent.name: json.loads(p.read_text())["status"]
        for p in sorted((root / "scenes").glob("*/review.json"))
    }


def _open(browser, app: ReviewApp):
    page = browser.new_page(viewport=VIEWPORT)
    page.goto(app.url)
    _title(page, "000000").wait_for(timeout=30000)
    page.wait_for_selector("canvas", timeout=30000)
    assert wait_until(lambda: len(app.sessions) == 1)
    _title(page, "000000").click()  # the page has the keyboard
    return page, next(iter(app.sessions.values()))


def _pictures_on_page(page) -> int:
    """The scene pictures in the page (viser's own logos are SVG)."""
    return page.locator("img[src^='data:image/jpeg'], img[src^='data:image/png']").count()


def _title(page, sid: str):
    """The panel's title naming scene ``sid`` (not a notice that mentions it)."""
    return page.get_by_role("heading", name=f"Scene {sid}")


def test_a_deleted_scene_is_reported_and_never_decided(browser, sample_copy, shown, capfd) -> None:
    with _serving(sample_copy) as app:
        page, session = _open(browser, app)
        try:
            assert wait_until(lambda: _pictures_on_page(page) >= 1)
            shutil.rmtree(sample_copy / "scenes" / "000001")
            # J Y J Y K K, each key once the page shows what the last one did.
            page.keyboard.press("j")
            page.get_by_text(GONE).first.wait_for(timeout=10000)
            assert _title(page, "000001").is_visible()
            assert wait_until(lambda: _pictures_on_page(page) == 0), "000000's pictures stayed"
            page.keyboard.press("y")
            page.get_by_text(NOT_SAVED).first.wait_for(timeout=10000)
            assert not (sample_copy / "scenes" / "000001").exists()  # not made again
            page.keyboard.press("j")
            _title(page, "000002").wait_for(timeout=10000)
            page.keyboard.press("y")  # 000002 is shown: it is decided
            assert wait_until(lambda: _decisions(sample_copy) == {"000002": "accepted"})
            _title(page, "000003").wait_for(timeout=10000)
            page.keyboard.press("k")
            _title(page, "000002").wait_for(timeout=10000)
            page.keyboard.press("k")
            _title(page, "000001").wait_for(timeout=10000)
            page.get_by_text(GONE).first.wait_for(timeout=10000)

            # The same keys at once, without waiting for the page: whatever is decided was
            # shown in the page when its key was pressed, and the gone scene never is.
            page.keyboard.press("k")
            _title(page, "000000").wait_for(timeout=10000)
            shown.clear()
            for key in "jyjykk":
                page.keyboard.press(key)
            time.sleep(1.5)
            decided = _decisions(sample_copy)
            titles = {"## Scene 000000", "## Scene 000002", *shown}  # shown before, or now
            assert "000001" not in decided and not (sample_copy / "scenes" / "000001").exists()
            for sid in decided:
                assert f"## Scene {sid}" in titles, f"{sid} was decided, never shown: {shown}"
        finally:
            page.close()
    err = capfd.readouterr().err
    assert "Traceback" not in err, err


def test_a_key_pressed_while_the_page_switches_decides_nothing(
    browser, sample_copy, monkeypatch
) -> None:
    real = viewer.page.rendering.compose

    def slow(*args, **kwargs):  # a scene that takes a second to draw
        time.sleep(1.0)
        return real(*args, **kwargs)

    with _serving(sample_copy) as app:
        page, session = _open(browser, app)
        try:
            monkeypatch.setattr(viewer.page.rendering, "compose", slow)
            page.keyboard.press("j")
            assert wait_until(lambda: session.nav.current == "000001", 5.0)
            page.keyboard.press("y")  # the page still shows 000000
            page.get_by_text(NOT_SAVED).first.wait_for(timeout=10000)
            page.get_by_text("still showing scene 000000").first.wait_for(timeout=5000)
            _title(page, "000001").wait_for(timeout=10000)
            assert _decisions(sample_copy) == {}
            assert session.displayed == "000001"
            page.keyboard.press("y")  # now it is shown: saved, and the red notice goes
            assert wait_until(lambda: _decisions(sample_copy) == {"000001": "accepted"})
            page.get_by_text(NOT_SAVED).first.wait_for(state="hidden", timeout=10000)
        finally:
            page.close()


def test_a_dataset_deleted_whole_is_reported_and_nothing_is_saved(
    browser, sample_copy, capfd
) -> None:
    with _serving(sample_copy) as app:
        page, session = _open(browser, app)
        try:
            shutil.rmtree(sample_copy)
            # Seen by the server's poll of the files: the page says so without a key.
            page.get_by_text(GONE).first.wait_for(timeout=10000)
            page.keyboard.press("y")
            page.get_by_text(NOT_SAVED).first.wait_for(timeout=10000)
            page.keyboard.press("n")
            page.keyboard.press("j")
            _title(page, "000001").wait_for(timeout=10000)
            page.get_by_text(GONE).first.wait_for(timeout=10000)
            assert not sample_copy.exists()
        finally:
            page.close()
    err = capfd.readouterr().err
    assert "Traceback" not in err, err
