"""The review page in real headless Chromium: overlays drawn, buttons and hotkeys write
review.json, navigation, and a reload shows the saved state."""

from __future__ import annotations

import json
import socket
import time

import numpy as np
import pytest

playwright = pytest.importorskip("playwright.sync_api")

from viewer.app import ReviewApp  # noqa: E402

pytestmark = pytest.mark.browser

CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture()
def served(sample_copy):
    app = ReviewApp(sample_copy, host="127.0.0.1", port=_free_port())
    yield app, sample_copy
    app.stop()
    with socket.socket() as s:  # the server really stopped
        assert s.connect_ex(("127.0.0.1", app.port)) != 0


def _wait(predicate, timeout=15.0):
    end = time.time() + timeout
    while time.time() < end:
        if predicate():
            return True
        time.sleep(0.1)
    return False


def _status(root, sid):
    p = root / "scenes" / sid / "review.json"
    return json.loads(p.read_text())["status"] if p.exists() else None


def test_review_page_end_to_end(served, tmp_path) -> None:
    app, root = served
    with playwright.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            page.goto(f"http://127.0.0.1:{app.port}")
            page.wait_for_selector("canvas", timeout=30000)
            page.get_by_text("Scene 000000").first.wait_for(timeout=30000)
            page.wait_for_selector("img", timeout=30000)
            time.sleep(2.0)
            # Overlays: pending contours are yellow (255, 220, 0) in the camera panels.
            shot = tmp_path / "page.png"
            page.screenshot(path=str(shot), full_page=True)
            import cv2

            img = cv2.imread(str(shot))[:, :, ::-1].astype(int)
            yellow = (
                (np.abs(img[..., 0] - 255) < 40)
                & (np.abs(img[..., 1] - 220) < 40)
                & (img[..., 2] < 80)
            )
            assert yellow.sum() > 200, "no pending contour visible in the screenshot"
            assert img.std() > 20, "blank page"

            # Click "Accept scene": scene 000000 accepted, the page moves to 000001.
            page.get_by_role("button", name="Accept scene (Y)").click()
            assert _wait(lambda: _status(root, "000000") == "accepted")
            page.get_by_text("Scene 000001").first.wait_for(timeout=15000)

            # Hotkeys: N rejects 000001 (and moves on), K goes back, J forward.
            page.mouse.click(5, 995)
            page.keyboard.press("n")
            assert _wait(lambda: _status(root, "000001") == "rejected")
            page.get_by_text("Scene 000002").first.wait_for(timeout=15000)
            page.keyboard.press("k")
            page.get_by_text("Scene 000001").first.wait_for(timeout=15000)
            page.keyboard.press("j")
            page.get_by_text("Scene 000002").first.wait_for(timeout=15000)
            page.keyboard.press("y")
            assert _wait(lambda: _status(root, "000002") == "accepted")

            # A reload shows the saved state.
            page.get_by_role("button", name="Previous (K)").click()
            page.get_by_text("Scene 000002").first.wait_for(timeout=15000)
            page.reload()
            page.get_by_text("Scene 000002").first.wait_for(timeout=30000)
            assert page.get_by_text("accepted").first.is_visible()
            assert page.get_by_text("reviewed 3 / 4").first.is_visible()
        finally:
            browser.close()
