"""The review page in real headless Chromium against a viewer on 127.0.0.1: overlays drawn,
buttons and hotkeys write review.json, two pages with their own cursors and shared
decisions, the zoom, "no pose here", a failed write shown in the page, and the token."""

from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import time
from argparse import Namespace
from pathlib import Path

import cv2
import numpy as np
import pytest

from devkit.headless import free_port
from devkit.polling import wait_until

playwright = pytest.importorskip("playwright.sync_api")

import viewer.server.app  # noqa: E402
from viewer.page import pictures  # noqa: E402
from viewer.server.app import ReviewApp  # noqa: E402

# A page closed while its scene is being sent: viser warns of what it can no longer deliver
# (the server ignores that warning; pytest records it anyway).
pytestmark = [
    pytest.mark.browser,
    pytest.mark.slow,
    pytest.mark.filterwarnings("ignore:Queued a:UserWarning"),
]

VIEWPORT = {"width": 1400, "height": 1000}
PENDING_RGB = (255, 220, 0)


@contextlib.contextmanager
def _serving(root: Path, **kwargs):
    # The pages open on the first scene: the sample's 000003 has a physics flag.
    kwargs.setdefault("start_scene", "000000")
    app = ReviewApp(root, host="127.0.0.1", port=free_port(), **kwargs)
    try:
        yield app
    finally:
        app.stop()
        with socket.socket() as s:  # the server really stopped
            assert s.connect_ex(("127.0.0.1", app.port)) != 0


@pytest.fixture()
def served(sample_copy):
    with _serving(sample_copy) as app:
        yield app, sample_copy


def _review(root, sid):
    p = root / "scenes" / sid / "review.json"
    return json.loads(p.read_text()) if p.exists() else None


def _status(root, sid):
    doc = _review(root, sid)
    return None if doc is None else doc["status"]


def _open(browser, url: str, first: str = "Scene 000000"):
    page = browser.new_page(viewport=VIEWPORT)
    page.goto(url)
    page.get_by_text(first).first.wait_for(timeout=30000)
    page.wait_for_selector("canvas", timeout=30000)
    return page


def _session(app: ReviewApp, count: int = 1):
    assert wait_until(lambda: len(app.sessions) >= count), "no page connected"
    return list(app.sessions.values())[count - 1]


def _canvas_rgb(page) -> tuple[np.ndarray, dict]:
    box = page.locator("canvas").first.bounding_box()
    png = page.screenshot(clip=box)
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
    return img.astype(int), box


def _as_sent(picture: np.ndarray) -> np.ndarray:
    """``picture`` (RGB) as the page gets it: the mosaic goes as JPEG, quality 85."""
    ok, data = cv2.imencode(".jpg", picture[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 85])
    return cv2.imdecode(data, cv2.IMREAD_COLOR)[:, :, ::-1]


def _shows(page, picture, timeout: float = 10.0) -> bool:
    """The canvas shows ``picture()`` (RGB, canvas-sized, as sent): nearly every pixel within
    a few levels (viser's own notices and axes are drawn over a few)."""

    def close() -> bool:
        img, _ = _canvas_rgb(page)
        expected = picture()
        if img.shape[:2] != expected.shape[:2]:
            return False
        return float((np.abs(img - expected.astype(int)).max(axis=-1) <= 8).mean()) > 0.9

    return wait_until(close, timeout)


def _interior_pixel(mask: np.ndarray) -> tuple[int, int]:
    """The pixel of ``mask`` farthest from its edge."""
    dist = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 5)
    y, x = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return int(x), int(y)


def test_review_page_end_to_end(browser, served) -> None:
    app, root = served
    page = _open(browser, app.url)
    try:
        session = _session(app)
        assert _shows(page, lambda: _as_sent(session.shown.mosaic[1].image)), (
            "the mosaic is not on the canvas"
        )
        img, _ = _canvas_rgb(page)
        yellow = np.all(np.abs(img - np.array(PENDING_RGB)) < 40, axis=-1)
        assert yellow.sum() > 200, "no pending contour visible"

        # Click "Accept scene": scene 000000 accepted, the page moves to 000001.
        page.get_by_role("button", name="Accept scene (Y)").click()
        assert wait_until(lambda: _status(root, "000000") == "accepted")
        page.get_by_text("Scene 000001").first.wait_for(timeout=15000)

        # Hotkeys: N rejects 000001 (and moves on), K goes back, J forward.
        page.get_by_text("Scene 000001").first.click()
        page.keyboard.press("n")
        assert wait_until(lambda: _status(root, "000001") == "rejected")
        page.get_by_text("Scene 000002").first.wait_for(timeout=15000)
        page.keyboard.press("k")
        page.get_by_text("Scene 000001").first.wait_for(timeout=15000)
        page.keyboard.press("j")
        page.get_by_text("Scene 000002").first.wait_for(timeout=15000)
        page.keyboard.press("y")
        assert wait_until(lambda: _status(root, "000002") == "accepted")
        page.get_by_text("reviewed 3 / 4").first.wait_for(timeout=15000)
    finally:
        page.close()


def test_a_collapsed_panel_leaves_the_picture_on_the_canvas(browser, served) -> None:
    """The pictures live in the control panel and go with it; the canvas then shows its own
    copy, made to the wider canvas, soon after (not after the long wait kept while the
    panel is open, see viewer.page.pictures)."""
    app, _ = served
    page = _open(browser, app.url)
    try:
        session = _session(app)
        assert _shows(page, lambda: _as_sent(session.shown.mosaic[1].image))
        narrow = session.viewport
        session.client.gui.main_panel.minimize()
        session.client.flush()
        t0 = time.monotonic()
        assert wait_until(lambda: session.viewport[0] > narrow[0] * 1.2)
        assert page.locator("[data-review-picture]").count() == 0  # gone with the panel
        assert _shows(page, lambda: _as_sent(session.shown.mosaic[1].image), timeout=10)
        assert time.monotonic() - t0 < pictures.BACKGROUND_QUIET
    finally:
        page.close()


def test_two_pages_have_their_own_cursor_and_share_decisions(browser, served) -> None:
    app, root = served
    a = _open(browser, app.url)
    b = _open(browser, app.url)
    try:
        _session(app, 2)
        a.get_by_text("Scene 000000").first.click()
        a.keyboard.press("j")
        a.get_by_text("Scene 000001").first.wait_for(timeout=15000)
        time.sleep(0.5)
        assert b.get_by_text("Scene 000000").first.is_visible()  # b did not move
        assert not b.get_by_text("Scene 000001").first.is_visible()

        # a accepts 000001: b's shared progress shows it within a second or two.
        a.keyboard.press("y")
        assert wait_until(lambda: _status(root, "000001") == "accepted")
        b.get_by_text("reviewed 1 / 4").first.wait_for(timeout=3000)

        # b goes there, sees the decision, and rejects the scene: the later decision wins and
        # a is told.
        b.get_by_text("Scene 000000").first.click()
        b.keyboard.press("j")
        b.get_by_text("Scene 000001").first.wait_for(timeout=15000)
        assert b.get_by_text("accepted").first.is_visible()
        b.keyboard.press("n")
        assert wait_until(lambda: _status(root, "000001") == "rejected")
        a.get_by_text("decided after you by another reviewer").first.wait_for(timeout=5000)
    finally:
        a.close()
        b.close()


def test_zoom_on_a_clicked_instance_then_no_pose_here(browser, served) -> None:
    app, root = served
    page = _open(browser, app.url)
    try:
        session = _session(app)
        assert _shows(page, lambda: _as_sent(session.shown.mosaic[1].image))
        picture, prep = session.shown.mosaic[1], session.shown.prep
        # A click on an instance's silhouette in the mosaic opens the zoom on it.
        tile, k = picture.tiles[0], 0
        u, v = tile.to_picture(*_interior_pixel(prep.layers[0].instance == k))
        _, box = _canvas_rgb(page)
        page.mouse.click(box["x"] + u + 0.5, box["y"] + v + 0.5)
        assert wait_until(lambda: session.nav.zoom and session.nav.selected == prep.keys[k])
        assert wait_until(
            lambda: session.shown.zoom is not None and session.shown.on_canvas[0] == "zoom"
        )
        z = session.shown.zoom[1]
        assert _shows(page, lambda: z.image), "the zoom is not on the canvas"
        img, _ = _canvas_rgb(page)
        # Its outline: the pending colour, on the canvas where the zoom drew it, one pixel wide.
        drawn = np.all(z.image == np.array(PENDING_RGB), axis=-1)
        assert drawn.sum() > 100
        seen = np.all(np.abs(img - np.array(PENDING_RGB)) < 12, axis=-1)
        assert (seen & drawn).sum() > 0.9 * drawn.sum()
        thick = cv2.erode(drawn.astype(np.uint8), np.ones((3, 3), np.uint8))
        assert thick.sum() < 0.02 * drawn.sum(), "the outline is more than one pixel wide"
        assert f"| ▶ | {prep.keys[k]} |" in session.panel.table.content
        page.keyboard.press("o")  # fill instead of outline
        assert wait_until(lambda: session.shown.on_canvas[1][-1] is True)

        # "A part has no pose here": M, then a click on the zoom; the pixel is recorded.
        zt = z.tiles[1]  # the second camera's crop, magnified
        x, y = zt.origin[0] + 20.0, zt.origin[1] + 30.0
        u, v = zt.to_picture(x, y)
        page.keyboard.press("m")
        page.get_by_text("Click on a picture where a part without a pose lies").first.wait_for(
            timeout=5000
        )
        page.mouse.click(box["x"] + round(u) + 0.5, box["y"] + round(v) + 0.5)
        assert wait_until(lambda: _status(root, "000000") == "rejected")
        doc = _review(root, "000000")
        assert doc["reason"] == "a part has no pose"
        (mark,) = doc["missing"]
        assert mark["camera"] == zt.camera
        # One screen pixel is 1/magnification camera pixels: the mark is within that.
        assert abs(mark["pixel"][0] - x) <= 1.0 / zt.scale
        assert abs(mark["pixel"][1] - y) <= 1.0 / zt.scale
        page.get_by_text(f"no pose here: {zt.camera}").first.wait_for(timeout=5000)
        page.keyboard.press("z")  # back to the mosaic
        assert wait_until(lambda: session.shown.on_canvas[0] == "mosaic")
    finally:
        page.close()


@contextlib.contextmanager
def _unwritable(folder: Path, monkeypatch):
    """``folder`` cannot be written: immutable (root), read-only (others), or, where neither
    is possible, writes fail as they would."""
    if os.geteuid() != 0:
        folder.chmod(0o555)
        try:
            yield
        finally:
            folder.chmod(0o755)
        return
    if subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode == 0:
        try:
            yield
        finally:
            subprocess.run(["chattr", "-i", str(folder)], check=True)
        return

    def refuse(path, review):
        raise PermissionError(1, "Operation not permitted", str(path))

    monkeypatch.setattr("annotator.review.state.write_review", refuse)
    yield


def test_a_failed_write_is_shown_in_the_page(browser, served, monkeypatch) -> None:
    app, root = served
    page = _open(browser, app.url)
    try:
        _session(app)
        with _unwritable(root / "scenes" / "000000", monkeypatch):
            page.get_by_text("Scene 000000").first.click()
            page.keyboard.press("y")
            page.get_by_text("is NOT saved").first.wait_for(timeout=5000)
            assert page.get_by_text("Scene 000000").first.is_visible()  # it stayed
            assert _status(root, "000000") is None
        page.keyboard.press("y")  # writable again: saved, the warning goes
        assert wait_until(lambda: _status(root, "000000") == "accepted")
        page.get_by_text("Scene 000001").first.wait_for(timeout=15000)
        page.get_by_text("is NOT saved").first.wait_for(state="hidden", timeout=5000)
    finally:
        page.close()


def test_a_non_local_host_without_a_token_is_refused(browser, sample_copy, monkeypatch, capsys):
    from annotator.commands import review

    # Tests listen on 127.0.0.1 only: the server is asked for 0.0.0.0 (so it behaves as a
    # non-local one) but binds the loopback address.
    real = viewer.server.app.viser.ViserServer
    monkeypatch.setattr(
        viewer.server.app.viser,
        "ViserServer",
        lambda host, port, **kw: real(host="127.0.0.1", port=port, **kw),
    )
    args = Namespace(
        dataset=str(sample_copy), host="0.0.0.0", port=free_port(), token=None, scene=None
    )
    app = review.start(args)
    try:
        out = capsys.readouterr().out
        token = app.access.token
        assert token and token in out and "refused" in out
        base = f"http://127.0.0.1:{app.port}"
        page = browser.new_page(viewport=VIEWPORT)
        page.goto(base)  # no token
        assert wait_until(lambda: app.guard.refused)
        time.sleep(0.5)
        assert not page.get_by_text("Scene 000000").first.is_visible()
        assert not app.sessions
        page.close()
        url = f"{base}/?websocket=ws://127.0.0.1:{app.port}/%3Ftoken%3D{token}"
        page = browser.new_page(viewport=VIEWPORT)
        page.goto(url)
        assert wait_until(lambda: len(app.sessions) == 1), "the page with the token was refused"
        page.close()
    finally:
        app.stop()
