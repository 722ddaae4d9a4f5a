"""Several reviewers on one dataset: edits merge or conflict visibly, across servers
(processes) and pages, and an undo only undoes a page's own step while it is still the last.

Two :class:`ReviewState` objects are two servers (each with its own cache of the files);
the processes test runs real ones.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from annotator.dataset.review import RepairStep, read_review
from annotator.geometry.transforms import make_transform
from annotator.review import Conflict, ReviewState

SCENE = "000001"


def _moved(state: ReviewState, key: str, dx: float) -> np.ndarray:
    pose = state.info(SCENE).pose(key)
    assert pose is not None
    return make_transform(pose.R, pose.t + [dx, 0.0, 0.0])


def _keys(state: ReviewState) -> list[str]:
    return [p.key for p in state.info(SCENE).poses]


def test_a_decision_keeps_another_servers_pose_edit(sample_copy: Path) -> None:
    a, b = ReviewState(sample_copy), ReviewState(sample_copy)
    key, other = _keys(a)[:2]
    a.info(SCENE)  # a's cache holds the file as it was
    b.set_pose(SCENE, key, _moved(b, key, 2.0), [{"op": "nudge"}], by="page-b")
    a.set_instance(SCENE, other, "rejected", by="page-a")
    a.set_pose(SCENE, other, _moved(a, other, -1.0), [{"op": "nudge"}], by="page-a")
    review = read_review(sample_copy / "scenes" / SCENE / "review.json")
    assert review is not None
    assert set(review.poses) == {key, other} and review.instances == {other: "rejected"}
    assert review.poses[key].decided_by == "page-b"


def test_a_change_computed_on_an_older_pose_is_refused(sample_copy: Path) -> None:
    a, b = ReviewState(sample_copy), ReviewState(sample_copy)
    key = _keys(a)[0]
    seen = a.info(SCENE).review.poses.get(key)  # None: the page computed from the auto pose
    T = _moved(a, key, 1.0)
    b.set_pose(SCENE, key, _moved(b, key, 5.0), [{"op": "nudge"}], by="page-b")
    with pytest.raises(Conflict, match=f"{key} was changed by page-b at .*nothing was written"):
        a.stage_pose(SCENE, key, T, [{"op": "nudge"}], by="page-a", expect=seen)
    review = read_review(sample_copy / "scenes" / SCENE / "review.json")
    assert review is not None and review.poses[key].decided_by == "page-b"
    # Computed again on what the file holds now, it goes through; the locks were given back.
    now = a.info(SCENE).review.poses.get(key)
    a.set_pose(SCENE, key, _moved(a, key, 1.0), [{"op": "nudge"}], by="page-a", expect=now)
    again = read_review(sample_copy / "scenes" / SCENE / "review.json")
    assert again is not None and again.poses[key].decided_by == "page-a"


def test_an_undo_never_throws_away_a_later_edit_of_another(sample_copy: Path) -> None:
    a, b = ReviewState(sample_copy), ReviewState(sample_copy)
    key = _keys(a)[0]
    mine = a.set_pose(SCENE, key, _moved(a, key, 1.0), [], by="page-a", expect=None).poses[key]
    theirs = b.set_pose(SCENE, key, _moved(b, key, 3.0), [], by="page-b", expect=mine)
    with pytest.raises(Conflict, match="changed by page-b"):
        a.restore_pose(SCENE, key, None, by="page-a", expect=mine)  # a's undo
    review = read_review(sample_copy / "scenes" / SCENE / "review.json")
    assert review is not None
    assert np.allclose(review.poses[key].t, theirs.poses[key].t)
    # b's own undo is still its last step: it goes through.
    b.restore_pose(SCENE, key, mine, by="page-b", expect=theirs.poses[key])
    back = read_review(sample_copy / "scenes" / SCENE / "review.json")
    assert back is not None and np.allclose(back.poses[key].t, mine.t)


_SERVER = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from annotator.geometry.transforms import make_transform
    from annotator.review import ReviewState
    root, me, keys = sys.argv[1], sys.argv[2], sys.argv[3].split(",")
    state = ReviewState(root)
    for n in range(int(sys.argv[4])):
        for key in keys:
            pose = state.info("000001").pose(key)
            T = make_transform(pose.R, pose.t + [0.5, 0.0, 0.0])
            state.set_pose("000001", key, T, [{"op": "nudge", "n": n}], by=me)
            if n % 3 == 0:
                state.toggle_instance("000001", key, by=me)
            time.sleep(0.002)
    """
)


def test_two_servers_at_once_lose_nothing(sample_copy: Path) -> None:
    keys = _keys(ReviewState(sample_copy))
    half = len(keys) // 2
    mine, theirs = keys[:half], keys[half:]
    rounds = 12
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _SERVER, str(sample_copy), name, ",".join(ks), str(rounds)],
            stderr=subprocess.PIPE,
            text=True,
        )
        for name, ks in (("server-a", mine), ("server-b", theirs))
    ]
    for p in procs:
        _, err = p.communicate(timeout=240)
        assert p.returncode == 0, err
    doc = json.loads((sample_copy / "scenes" / SCENE / "review.json").read_text())
    auto = {p.key: p.t for p in ReviewState(sample_copy).info(SCENE).auto}
    assert set(doc["poses"]) == set(keys)
    for key, rec in doc["poses"].items():
        # Every one of a server's nudges is there: none written over by the other.
        assert rec["steps"][-1]["n"] == rounds - 1, (key, rec["steps"])
        assert np.allclose(rec["cam_t_m2c"], auto[key] + [0.5 * rounds, 0.0, 0.0])
    # Four toggles each (rounds 0, 3, 6, 9): back where they started, none lost.
    assert all(v == "accepted" for v in doc["instances"].values())
    assert set(doc["instances"]) == set(keys)


@pytest.mark.slow
def test_a_pages_undo_after_another_reviewers_edit_is_refused_and_said(sample_copy: Path) -> None:
    from test_viewer_repair import KEY, _page_on

    from devkit.headless import free_port
    from viewer.server.app import ReviewApp

    app = ReviewApp(sample_copy, host="127.0.0.1", port=free_port())
    try:
        ws, session = _page_on(app, SCENE, KEY)
        session.nudge(0, +1)
        assert len(session.editor.history[SCENE]) == 1 and not session.unsaved
        other = ReviewState(sample_copy)  # a second server, another reviewer
        theirs = other.set_pose(SCENE, KEY, _moved(other, KEY, 4.0), [], by="page-other")
        session.undo()
        assert "NOT saved" in session.unsaved[SCENE] and "page-other" in session.unsaved[SCENE]
        review = read_review(sample_copy / "scenes" / SCENE / "review.json")
        assert review is not None and review.poses[KEY].decided_by == "page-other"
        assert np.allclose(review.poses[KEY].t, theirs.poses[KEY].t)
        assert not session.editor.history.get(SCENE)  # that step is no longer this page's to undo
        # A nudge computed from what the page showed before the other's edit is refused too;
        # the page then shows the other's pose, and a nudge from it goes through.
        seen = app.state.info(SCENE)
        other.set_pose(SCENE, KEY, _moved(other, KEY, 1.0), [], by="page-other")
        session.editor._edit(
            SCENE,
            KEY,
            _moved(app.state, KEY, 1.0),
            RepairStep.from_json({"op": "nudge"}),
            seen=seen,
        )
        assert "page-other" in session.unsaved[SCENE]
        session.nudge(0, +1)
        assert SCENE not in session.unsaved
        review = read_review(sample_copy / "scenes" / SCENE / "review.json")
        assert review is not None and review.poses[KEY].decided_by == session.id
        ws.close()
    finally:
        app.stop()
