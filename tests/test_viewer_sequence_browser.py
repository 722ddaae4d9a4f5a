"""A sequence's review page (one moving rig) in real headless Chromium against a viewer on
127.0.0.1: a few frames side by side as one rig in the scene frame, their pending contours
where each frame's silhouettes are, P to the next frames, H rejecting one frame on its own
and taking it back, a nudge written in the scene frame and seen in every shown frame, and Y
accepting the whole scene."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from devkit.polling import wait_until

pytest.importorskip("playwright.sync_api")

from test_viewer_browser import (  # noqa: E402
    PENDING_RGB,
    _as_sent,
    _canvas_rgb,
    _open,
    _serving,
    _session,
    _shows,
)

from annotator.dataset import load_dataset, read_poses  # noqa: E402
from annotator.dataset.frames import read_frames  # noqa: E402

pytestmark = [
    pytest.mark.browser,
    pytest.mark.slow,
    pytest.mark.filterwarnings("ignore:Queued a:UserWarning"),
]

SCENE = "000000"
CAMERAS = ("left", "right")


@pytest.fixture()
def served(sequence, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(sequence, root)
    with _serving(root) as app:
        yield app, root


def _review(root: Path) -> dict | None:
    p = root / "scenes" / SCENE / "review.json"
    return json.loads(p.read_text()) if p.exists() else None


def _title(page) -> str:
    return page.get_by_text("frames shown:").first.inner_text()


def _camera_tiles(session) -> list:
    """The mosaic's tiles of cameras (``<frame>:<camera>``), not depth or disagreement."""
    return [t for t in session.shown.mosaic[1].tiles if t.name == t.camera]


def _check_contours(page, session) -> None:
    """Every camera tile on the canvas has pending contours, and they lie on the
    silhouettes of that tile's camera (its own frame's), not elsewhere."""
    img, _ = _canvas_rgb(page)
    yellow = np.all(np.abs(img - np.array(PENDING_RGB)) < 40, axis=-1)
    layers = {layer.name: layer for layer in session.shown.prep.layers}
    for tile in _camera_tiles(session):
        inst = layers[tile.camera].instance
        near = cv2.dilate((inst >= 0).astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        vs, us = np.nonzero(yellow[tile.y0 : tile.y0 + tile.height, tile.x0 : tile.x0 + tile.width])
        assert len(us) > 100, f"no pending contour in {tile.camera}"
        x, y = tile.to_full(us + tile.x0, vs + tile.y0)
        x = np.clip(np.round(x).astype(int), 0, inst.shape[1] - 1)
        y = np.clip(np.round(y).astype(int), 0, inst.shape[0] - 1)
        on = float(near[y, x].mean())
        assert on > 0.9, f"{tile.camera}: only {on:.0%} of the contour on its silhouettes"


def test_sequence_review_page_end_to_end(browser, served) -> None:
    app, root = served
    page = _open(browser, app.url, first=f"Scene {SCENE}")
    try:
        session = _session(app)
        info = app.state.info(SCENE)
        shown = info.shown
        assert len(shown) == 3 and len(set(shown)) == 3
        # The title says which frames are shown.
        page.get_by_text("frames shown:").first.wait_for(timeout=15000)
        title = _title(page)
        assert all(f in title for f in shown), title
        # The mosaic: each shown frame's two cameras, then depth and disagreement.
        assert _shows(page, lambda: _as_sent(session.shown.mosaic[1].image))
        tiles = session.shown.mosaic[1].tiles
        assert [t.camera for t in _camera_tiles(session)] == [
            f"{f}:{c}" for f in shown for c in CAMERAS
        ]
        assert len(tiles) == 8 and {t.name for t in tiles[6:]} == {"depth", "disagreement"}
        _check_contours(page, session)

        # P: the next frames, in the title and on the canvas.
        page.get_by_text(f"Scene {SCENE}").first.click()
        page.keyboard.press("p")
        assert wait_until(lambda: session.info(SCENE).shown != shown)
        now = session.info(SCENE).shown
        assert wait_until(lambda: all(f in _title(page) for f in now) and now[0] in _title(page))
        assert wait_until(
            lambda: (
                [t.camera for t in _camera_tiles(session)]
                == [f"{f}:{c}" for f in now for c in CAMERAS]
            )
        )
        assert _shows(page, lambda: _as_sent(session.shown.mosaic[1].image))
        _check_contours(page, session)

        # H rejects the first shown frame on its own; H again takes it back.
        page.keyboard.press("h")
        assert wait_until(lambda: (_review(root) or {}).get("frames") == {now[0]: "rejected"})
        assert wait_until(lambda: f"{now[0]} (rejected)" in _title(page))
        assert _review(root)["status"] == "pending"
        page.keyboard.press("h")
        assert wait_until(lambda: "frames" not in (_review(root) or {"frames": 1}))
        assert wait_until(lambda: "(rejected)" not in _title(page))

        # A repair: I selects an instance, 2 nudges it +1 mm along x of the first shown
        # frame's reference camera; review.json holds the pose in the scene frame, and the
        # overlay moves in every shown frame.
        before = session.shown.prep
        page.keyboard.press("i")
        assert wait_until(lambda: session.nav.selected is not None)
        key = session.nav.selected
        k = before.keys.index(key)
        page.keyboard.press("2")
        assert wait_until(lambda: key in (_review(root) or {}).get("poses", {}))
        edited = _review(root)["poses"][key]
        ann = {p.key: p for p in read_poses(root / "scenes" / SCENE / "annotation.json")}
        frames = read_frames(root / "scenes" / SCENE / "annotation.json")
        ds = load_dataset(root)
        scene_T_cam = frames[now[0]].scene_T_rig @ ds.rig.cameras[0].rig_T_cam
        R = np.array(edited["cam_R_m2c"]).reshape(3, 3)
        t = np.array(edited["cam_t_m2c"])
        assert np.allclose(R, ann[key].R, atol=1e-9)
        assert np.allclose(t - ann[key].t, scene_T_cam[:3, 0] * 1.0, atol=1e-6)
        assert wait_until(
            lambda: session.shown.prep is not before and key in session.shown.prep.keys
        )
        after = session.shown.prep
        k2 = after.keys.index(key)
        old = {layer.name: layer.instance == k for layer in before.layers}
        new = {layer.name: layer.instance == k2 for layer in after.layers}
        for name in (f"{f}:{c}" for f in now for c in CAMERAS):
            if old[name].any() or new[name].any():
                assert (old[name] ^ new[name]).any(), f"{key} did not move in {name}"
        assert sum((old[n] ^ new[n]).any() for n in old) >= len(now)

        # Y accepts the scene as a whole; the repaired pose stays.
        page.keyboard.press("y")
        assert wait_until(lambda: (_review(root) or {}).get("status") == "accepted")
        assert key in _review(root)["poses"]
    finally:
        page.close()


def test_the_3d_view_of_a_sequence_shows_the_shown_frames_cameras(browser, served) -> None:
    """V: the parts, the first shown frame's depth points and the shown frames' cameras,
    all in the scene frame; after P (in the 3D view) the new frames' cameras."""
    app, _ = served
    page = _open(browser, app.url, first=f"Scene {SCENE}")
    try:
        session = _session(app)
        assert _shows(page, lambda: _as_sent(session.shown.mosaic[1].image))
        page.get_by_text(f"Scene {SCENE}").first.click()
        page.keyboard.press("v")
        assert wait_until(lambda: session.scene.showing_3d)

        def drawn() -> list[str]:
            return [name for name, _ in session.scene._shown_cameras[0]]

        shown = session.info(SCENE).shown
        expected = [f"{f}:{c}" for f in shown for c in CAMERAS]
        assert wait_until(lambda: drawn() == expected), drawn()
        page.keyboard.press("p")
        assert wait_until(lambda: session.info(SCENE).shown != shown)
        now = session.info(SCENE).shown
        assert wait_until(lambda: drawn() == [f"{f}:{c}" for f in now for c in CAMERAS])
        page.keyboard.press("v")
        assert wait_until(lambda: not session.scene.showing_3d)
    finally:
        page.close()
