"""Repairing poses in the review page, in real headless Chromium against a viewer on
127.0.0.1, on a copy of the sample scenes where one instance's annotation was moved by 3 mm
and 4 degrees (and, for adding a part, one instance deleted from annotation.json): refine,
undo, redo, nudges, a missing part added with M + a click, and the BOP export of the result."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from devkit.polling import wait_until

pytest.importorskip("playwright.sync_api")

from test_viewer_browser import (  # noqa: E402
    _as_sent,
    _canvas_rgb,
    _open,
    _serving,
    _session,
    _shows,
)

from annotator.cli import main as cli  # noqa: E402
from annotator.dataset import load_dataset, read_poses  # noqa: E402
from annotator.geometry.lie import matrix_to_rotvec  # noqa: E402
from annotator.geometry.transforms import axis_angle  # noqa: E402
from annotator.symmetry import PoseSpace  # noqa: E402

pytestmark = [
    pytest.mark.browser,
    pytest.mark.slow,
    pytest.mark.filterwarnings("ignore:Queued a:UserWarning"),
]

SCENE = "000000"
MOVED = "bracket/01"  # 12 markers in both cameras, hardly occluded
DELETED = "cylinder/04"


def _annotation(root: Path) -> Path:
    return root / "scenes" / SCENE / "annotation.json"


def _edit_annotation(root: Path, fn) -> None:
    path = _annotation(root)
    doc = json.loads(path.read_text())
    fn(doc["instances"])
    path.write_text(json.dumps(doc))


def _move(rec: dict, centroid: np.ndarray) -> None:
    """``rec``'s pose moved by 3 mm and turned by 4 degrees about its centre."""
    R = np.array(rec["cam_R_m2c"]).reshape(3, 3)
    t = np.array(rec["cam_t_m2c"])
    c = R @ centroid + t
    dR = axis_angle(np.array([1.0, 2.0, -1.0]), np.radians(4.0))
    shift = 3.0 * np.array([0.6, -0.8, 0.0])
    rec["cam_R_m2c"] = (dR @ R).ravel().tolist()
    rec["cam_t_m2c"] = (dR @ (t - c) + c + shift).tolist()


@pytest.fixture()
def moved(sample_copy: Path) -> Path:
    """The sample with MOVED's annotation moved and DELETED taken out of annotation.json."""
    ds = load_dataset(sample_copy)
    centroid = ds.objects[MOVED.split("/")[0]].mesh.moments.centroid

    def change(instances: list) -> None:
        for rec in instances:
            if f"{rec['object']}/{rec['instance']}" == MOVED:
                _move(rec, centroid)
        instances[:] = [i for i in instances if f"{i['object']}/{i['instance']}" != DELETED]

    _edit_annotation(sample_copy, change)
    return sample_copy


def _saved(root: Path, key: str) -> dict | None:
    p = root / "scenes" / SCENE / "review.json"
    if not p.exists():
        return None
    return json.loads(p.read_text()).get("poses", {}).get(key)


def _error_fraction(root: Path, key: str, R: np.ndarray, t: np.ndarray) -> float:
    """Distance of a pose to gt.json's (symmetry-aware RMS surface displacement), as a
    fraction of the part's diameter."""
    ds = load_dataset(root)
    obj = ds.objects[key.split("/")[0]]
    space = PoseSpace.from_moments(obj.mesh.moments, obj.symmetry)
    gt = next(p for p in read_poses(root / "scenes" / SCENE / "gt.json") if p.key == key)
    return float(space.distance(R, t, gt.R, gt.t)[0]) / space.diameter


def _pose(rec: dict) -> tuple[np.ndarray, np.ndarray]:
    return np.array(rec["cam_R_m2c"]).reshape(3, 3), np.array(rec["cam_t_m2c"])


def _auto(root: Path, key: str) -> tuple[np.ndarray, np.ndarray]:
    doc = json.loads(_annotation(root).read_text())
    rec = next(i for i in doc["instances"] if f"{i['object']}/{i['instance']}" == key)
    return _pose(rec)


def _on_screen(session) -> np.ndarray:
    """What the page should show now: the zoom (sent exact) or the mosaic (as JPEG)."""
    if session.shown.on_canvas is not None and session.shown.on_canvas[0] == "zoom":
        return session.shown.zoom[1].image
    return _as_sent(session.shown.mosaic[1].image)


def _select(page, session, key: str) -> None:
    page.get_by_role("button", name=key, exact=True).first.click()
    assert wait_until(lambda: session.nav.selected == key)
    page.get_by_text(f"Scene {SCENE}").first.click()  # keys go to the page again


def test_refine_undo_redo_and_export(browser, moved, tmp_path) -> None:
    with _serving(moved) as app:
        page = _open(browser, app.url)
        try:
            session = _session(app)
            moved_R, moved_t = _auto(moved, MOVED)
            assert _error_fraction(moved, MOVED, moved_R, moved_t) > 0.02  # really off
            _select(page, session, MOVED)
            page.keyboard.press("r")
            page.get_by_text(f"{MOVED} refined").first.wait_for(timeout=30000)
            rec = _saved(moved, MOVED)
            assert rec is not None and rec["source"] == "edited"
            assert rec["steps"][-1]["op"] == "refine" and rec["decided_by"] == session.id
            assert _error_fraction(moved, MOVED, *_pose(rec)) < 0.005
            # The panel says the residuals before and after; the table marks the edit.
            assert "before:" in session.panel.repair.content
            assert "✎ edited" in session.panel.table.content
            refined = _pose(rec)

            page.keyboard.press("u")  # back to the moved auto pose
            assert wait_until(lambda: _saved(moved, MOVED) is None)
            assert wait_until(lambda: session.displayed == SCENE and session.shown.prep is not None)
            shown = app.state.info(SCENE).pose(MOVED)
            assert np.allclose(shown.R, moved_R) and np.allclose(shown.t, moved_t)
            # The page shows the moved pose's overlay again.
            assert _shows(page, lambda: _on_screen(session))

            page.keyboard.press("Shift+U")  # redo: the refined pose again
            assert wait_until(lambda: _saved(moved, MOVED) is not None)
            R, t = _pose(_saved(moved, MOVED))
            assert np.allclose(R, refined[0]) and np.allclose(t, refined[1])
            page.keyboard.press("y")  # accept the scene
            assert wait_until(
                lambda: (
                    json.loads((moved / "scenes" / SCENE / "review.json").read_text())["status"]
                    == "accepted"
                )
            )
        finally:
            page.close()
    # annotation.json is what annotate wrote (the moved pose); the export has the edit.
    assert np.allclose(_auto(moved, MOVED)[1], moved_t)
    out = tmp_path / "bop"
    assert cli(["export", str(moved), str(out), "--format", "bop", "--cameras", "left"]) in (0, 1)
    (gt_file,) = out.glob(f"*/{int(SCENE):06d}/scene_gt.json")
    entries = json.loads(gt_file.read_text())["0"]
    poses = [(np.array(e["cam_R_m2c"]).reshape(3, 3), np.array(e["cam_t_m2c"])) for e in entries]
    assert any(
        np.allclose(R, refined[0], atol=1e-6) and np.allclose(t, refined[1], atol=1e-4)
        for R, t in poses
    )
    assert not any(np.allclose(t, moved_t, atol=1e-3) for _, t in poses)


def test_a_nudge_moves_the_pose_by_exactly_its_step(browser, moved) -> None:
    key = "bracket/02"
    with _serving(moved) as app:
        page = _open(browser, app.url)
        try:
            session = _session(app)
            R0, t0 = _auto(moved, key)
            _select(page, session, key)
            page.keyboard.press("2")  # +x, 1 mm
            assert wait_until(lambda: _saved(moved, key) is not None)
            R1, t1 = _pose(_saved(moved, key))
            assert np.allclose(R1, R0, atol=1e-12)
            assert np.allclose(t1 - t0, [1.0, 0.0, 0.0], atol=1e-9)
            page.keyboard.press("g")  # turn
            page.keyboard.press("4")  # +1 degree about y
            assert wait_until(lambda: len(_saved(moved, key)["steps"]) == 2)
            R2, _ = _pose(_saved(moved, key))
            w = matrix_to_rotvec(R2 @ R1.T)
            assert np.allclose(w, [0.0, np.radians(1.0), 0.0], atol=1e-9)
            steps = _saved(moved, key)["steps"]
            assert [s["kind"] for s in steps] == ["move", "turn"]
            # The overlay on screen is that of the nudged pose.
            assert _shows(page, lambda: _on_screen(session))
        finally:
            page.close()


def test_a_deleted_instance_is_added_back_with_m_a_click_and_r(browser, moved) -> None:
    ds = load_dataset(moved)
    gt = next(p for p in read_poses(moved / "scenes" / SCENE / "gt.json") if p.key == DELETED)
    cam = ds.rig.cameras[0]
    centre = gt.R @ ds.objects["cylinder"].mesh.moments.centroid + gt.t
    x, y = cam.project(centre[None])[0]
    with _serving(moved) as app:
        page = _open(browser, app.url)
        try:
            session = _session(app)
            assert _shows(page, lambda: _as_sent(session.shown.mosaic[1].image))
            tile = session.shown.mosaic[1].tiles[0]
            assert tile.camera == cam.name
            u, v = tile.to_picture(x, y)
            _, box = _canvas_rgb(page)
            page.get_by_text(f"Scene {SCENE}").first.click()
            page.keyboard.press("m")
            page.get_by_text("Click on a picture where a part without a pose lies").first.wait_for(
                timeout=5000
            )
            page.mouse.click(box["x"] + round(u) + 0.5, box["y"] + round(v) + 0.5)
            page.get_by_role("button", name=DELETED, exact=True).first.wait_for(timeout=10000)
            page.get_by_role("button", name=DELETED, exact=True).first.click()
            assert wait_until(lambda: _saved(moved, DELETED) is not None, timeout=20)
            doc = json.loads((moved / "scenes" / SCENE / "review.json").read_text())
            # The part now has a pose: the "no pose here" mark it answers is gone.
            assert doc["status"] == "pending" and not doc.get("missing")
            assert wait_until(lambda: session.nav.selected == DELETED)
            page.get_by_text(f"Scene {SCENE}").first.click()
            page.keyboard.press("r")
            page.get_by_text(f"{DELETED} refined").first.wait_for(timeout=30000)
            rec = _saved(moved, DELETED)
            assert [s["op"] for s in rec["steps"]] == ["add", "refine"]
            assert rec["auto_fingerprint"] is None
            assert _error_fraction(moved, DELETED, *_pose(rec)) < 0.005
        finally:
            page.close()


def test_a_cycles_the_candidates_and_moves_the_3d_camera_only_in_the_3d_view(
    browser, moved
) -> None:
    """A is viser's camera key too (its W A S D): over the pictures it only cycles the
    candidates (a camera moving unseen under them is elsewhere when the 3D view opens, and
    drawing its motion delayed the overlay); in the 3D view it also moves the camera."""
    key = "brick/05"  # one marker in scene 000003: both IPPE solutions are candidates
    with _serving(moved) as app:
        page = _open(browser, app.url)
        try:
            session = _session(app)
            for _ in range(3):
                page.keyboard.press("j")
            page.get_by_text("Scene 000003").first.wait_for(timeout=10000)
            page.get_by_role("button", name=key, exact=True).first.click()
            assert wait_until(lambda: session.nav.selected == key)
            page.get_by_text("Scene 000003").first.click()  # keys go to the page again
            camera = session.client.camera
            assert wait_until(lambda: camera.update_timestamp > 0)
            before = np.array(camera.position)

            page.keyboard.down("a")
            page.wait_for_timeout(300)  # held: viser's camera would move all along
            page.keyboard.up("a")
            page.get_by_text(f"{key}: candidate 2 of").first.wait_for(timeout=10000)
            page.wait_for_timeout(1000)  # any camera motion has been reported by now
            assert np.allclose(camera.position, before)

            # On an AZERTY keyboard Z (open / close the zoom) is where QWERTY's W is, which
            # viser's camera takes (it goes by the key's place): the zoom closes, the camera
            # stays.
            assert session.nav.zoom
            cdp = page.context.new_cdp_session(page)
            azerty_z = {"key": "z", "code": "KeyW", "windowsVirtualKeyCode": 90}
            cdp.send("Input.dispatchKeyEvent", {"type": "keyDown", "text": "z", **azerty_z})
            page.wait_for_timeout(300)
            cdp.send("Input.dispatchKeyEvent", {"type": "keyUp", **azerty_z})
            assert wait_until(lambda: not session.nav.zoom)
            page.wait_for_timeout(1000)
            assert np.allclose(camera.position, before)

            page.keyboard.press("v")
            assert wait_until(lambda: session.scene.showing_3d)
            page.get_by_text("Scene 000003").first.click()
            page.keyboard.down("a")
            page.wait_for_timeout(300)
            page.keyboard.up("a")
            # The candidates cycle (back to the first, the auto pose) and the camera moved.
            page.get_by_text(f"{key}: candidate 1 of").first.wait_for(timeout=10000)
            assert wait_until(lambda: not np.allclose(camera.position, before), timeout=5)
        finally:
            page.close()
