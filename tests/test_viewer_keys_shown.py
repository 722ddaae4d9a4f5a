"""A review key acts on what its own page showed (issue 44: faults, round five): two pages
of one server each keep their own frames of a sequence, a decision made on poses that
changed on disk since the page showed them is refused and said, and a page's own keys in
quick succession never conflict with each other."""

from __future__ import annotations

import contextlib
import json
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest

from annotator.dataset.review import ReviewStatus
from devkit.headless import free_port
from devkit.polling import wait_until
from devkit.wire import open_page
from viewer.page.session import Session
from viewer.server.app import ReviewApp

pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore:Queued a:UserWarning")]

SCENE = "000000"


@contextlib.contextmanager
def _pages(root: Path, count: int):
    """A review server on ``root`` and ``count`` pages on it, each showing SCENE (the first)."""
    app = ReviewApp(root, host="127.0.0.1", port=free_port())
    sockets = []
    try:
        for _ in range(count):
            sockets.append(open_page(app.port, width=900, height=700))
        assert wait_until(lambda: len(app.sessions) == count), "the pages did not connect"
        sessions: list[Session] = sorted(app.sessions.values(), key=lambda s: s.id)
        # A page opens on the first scene with a physics flag: each is taken back to SCENE.
        for s in sessions:
            assert wait_until(lambda s=s: s.displayed is not None)
            while s.nav.current != SCENE:
                s.previous()
        assert wait_until(lambda: all(s.displayed == SCENE for s in sessions))
        yield app, sessions
    finally:
        for ws in sockets:
            ws.close()
        app.stop()


def _review(root: Path) -> dict:
    path = root / "scenes" / SCENE / "review.json"
    return json.loads(path.read_text()) if path.exists() else {}


def _move_on_disk(root: Path, dx: float) -> None:
    """What ``annotate --force`` after ``sites`` does: other poses in annotation.json."""
    path = root / "scenes" / SCENE / "annotation.json"
    doc = json.loads(path.read_text())
    doc["instances"][0]["cam_t_m2c"][0] += dx
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(doc))
    tmp.replace(path)


def test_two_pages_each_keep_their_own_frames(sequence: Path, tmp_path: Path) -> None:
    root = tmp_path / "ds"
    shutil.copytree(sequence, root)
    with _pages(root, 2) as (app, (a, b)):
        first = b.info(SCENE).shown
        a.next_frames()  # page A steps on; page B still shows its frames
        assert wait_until(lambda: a.seen(SCENE) is not None and a.seen(SCENE).shown != first)
        assert b.info(SCENE).shown == first and b.seen(SCENE).shown == first
        b.toggle_frame()  # B rejects the first frame *it* shows
        assert _review(root)["frames"] == {first[0]: "rejected"}
        a.toggle_frame()  # A rejects the first frame it shows, another one
        assert _review(root)["frames"] == {first[0]: "rejected", a.seen(SCENE).shown[0]: "rejected"}


def test_an_acceptance_of_poses_never_shown_is_refused(sample_copy: Path) -> None:
    with _pages(sample_copy, 1) as (app, (page,)):
        shown = page.seen(SCENE)
        _move_on_disk(sample_copy, 2.0)
        page.accept()
        assert "status" not in _review(sample_copy) or _review(sample_copy)["status"] == "pending"
        assert "annotation changed on disk" in page.unsaved[SCENE]
        # The page shows the new poses; a decision on them is saved, stamped with them.
        assert wait_until(lambda: page.seen(SCENE).fingerprint != shown.fingerprint)
        now = page.seen(SCENE)
        page.accept()
        review = _review(sample_copy)
        assert review["status"] == "accepted"
        assert review["annotation_fingerprint"] == now.fingerprint
        assert SCENE not in page.unsaved


def test_every_decision_key_checks_what_the_page_showed(sample_copy: Path) -> None:
    with _pages(sample_copy, 1) as (app, (page,)):
        key = page.seen(SCENE).poses[0].key
        page.select(key)
        assert wait_until(lambda: page.nav.selected == key and page.displayed == SCENE)
        _move_on_disk(sample_copy, 1.0)
        page.set_instance(ReviewStatus.REJECTED)
        assert "instances" not in _review(sample_copy)
        assert "annotation changed on disk" in page.unsaved[SCENE]


def test_a_decision_after_another_reviewers_repair_is_refused(sample_copy: Path) -> None:
    with _pages(sample_copy, 2) as (app, (a, b)):
        info = a.seen(SCENE)
        pose = info.poses[0]
        T = pose.T.copy()
        T[0, 3] += 3.0
        app.state.set_pose(SCENE, pose.key, T, [], by=a.id)  # A repairs a part
        b.accept()  # B has not seen the repaired part yet
        assert _review(sample_copy).get("status", "pending") == "pending"
        assert f"{pose.key} was changed by {a.id}" in b.unsaved[SCENE]
        assert wait_until(lambda: b.seen(SCENE).view != info.view)
        b.accept()
        assert _review(sample_copy)["status"] == "accepted"


def test_a_pages_own_quick_keys_never_conflict(sample_copy: Path) -> None:
    with _pages(sample_copy, 1) as (app, (page,)):
        auto = page.seen(SCENE).poses[0]
        page.select(auto.key)
        assert wait_until(lambda: page.nav.selected == auto.key)
        keys = [threading.Thread(target=page.nudge, args=(0, +1)) for _ in range(3)]
        for t in keys:  # three presses at once, as a held key sends them
            t.start()
        for t in keys:
            t.join()
        assert not page.unsaved, page.unsaved
        now = app.state.info(SCENE).pose(auto.key)
        moved = np.linalg.norm(now.t - auto.t)
        assert moved == pytest.approx(3 * 1.0, abs=1e-6)  # each from the one before
        assert "page-" not in page.editor.repair_text


def test_a_start_scene_that_does_not_exist_is_said_in_one_line(sample_copy: Path) -> None:
    from annotator.errors import UserError

    with pytest.raises(UserError, match="--scene 000099: no such scene"):
        ReviewApp(sample_copy, host="127.0.0.1", port=free_port(), start_scene="000099")


def test_every_page_opens_on_the_start_scene(sample_copy: Path) -> None:
    app = ReviewApp(sample_copy, host="127.0.0.1", port=free_port(), start_scene="000002")
    try:
        open_page(app.port, width=900, height=700)
        assert wait_until(lambda: len(app.sessions) == 1)
        session = next(iter(app.sessions.values()))
        assert wait_until(lambda: session.displayed == "000002")
    finally:
        app.stop()
