"""The review state of a sequence without a browser: pictures made for the frames a version
of the scene showed (not those shown by the time they are made), a frame moved by a new
annotation makes a new view, and nudges go along the first shown frame's camera."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from annotator.repair import Nudge, NudgeKind
from annotator.review import ReviewState
from viewer.page import repair

pytestmark = pytest.mark.slow


@pytest.fixture()
def copy(sequence: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "ds"
    shutil.copytree(sequence, dst)
    return dst


def _cameras(state: ReviewState, sid: str, info=None) -> list[str]:
    return [c.name for c in state.view(sid, info)[0].rig.cameras]


def test_a_version_of_the_scene_keeps_its_own_frames(copy: Path) -> None:
    state = ReviewState(copy)
    sid = state.ids[0]
    old = state.info(sid)
    new = state.info(sid, 1)
    assert new.shown != old.shown and new.view != old.view
    assert _cameras(state, sid, old) == [f"{f}:{c}" for f in old.shown for c in ("left", "right")]
    assert _cameras(state, sid, new) == [f"{f}:{c}" for f in new.shown for c in ("left", "right")]
    view, scene = state.view(sid, old)
    assert scene.depth_path.parent.name == old.shown[0]  # its depth is its first frame's


def test_a_frame_moved_by_a_new_annotation_is_a_new_view(copy: Path) -> None:
    state = ReviewState(copy)
    sid = state.ids[0]
    info = state.info(sid)
    first = info.shown[0]
    before = state.view(sid)[0].rig.cameras[0].rig_T_cam.copy()
    path = copy / "scenes" / sid / "annotation.json"
    doc = json.loads(path.read_text())
    T = np.array(doc["frames"][first]["scene_T_rig"]).reshape(4, 4)
    T[0, 3] += 5.0  # the frame placed 5 mm elsewhere; no instance pose changes
    doc["frames"][first]["scene_T_rig"] = T.ravel().tolist()
    path.write_text(json.dumps(doc))
    after_info = state.info(sid)
    assert after_info.fingerprint == info.fingerprint and after_info.view != info.view
    after = state.view(sid)[0].rig.cameras[0].rig_T_cam
    assert np.allclose(after[:3, 3] - before[:3, 3], [5.0, 0.0, 0.0])


def test_a_nudge_goes_along_the_first_shown_frames_camera(copy: Path) -> None:
    state = ReviewState(copy)
    sid = state.ids[0]
    info = state.info(sid, 1)
    ds = state.view(sid, info)[0]
    pose = info.poses[0]
    T = repair.nudge(ds, info, pose.key, Nudge(NudgeKind.MOVE, 0, 1.0))
    scene_T_cam = ds.rig.cameras[0].rig_T_cam
    assert not np.allclose(scene_T_cam[:3, :3], np.eye(3))  # not the scene frame's axes
    assert np.allclose(T[:3, 3] - pose.t, scene_T_cam[:3, 0])
    assert np.allclose(T[:3, :3], pose.R)
    turned = repair.nudge(ds, info, pose.key, Nudge(NudgeKind.TURN, 2, 10.0))
    axis = scene_T_cam[:3, 2]
    dR = turned[:3, :3] @ pose.R.T
    assert np.allclose(dR @ axis, axis, atol=1e-9)  # a turn about that camera's z


def test_a_sequence_not_annotated_yet_shows_its_first_frame(copy: Path) -> None:
    from viewer.drawing.overlays import prepare

    (copy / "scenes" / "000000" / "annotation.json").unlink()
    state = ReviewState(copy)
    info = state.info("000000")
    assert not info.annotated and info.shown == ()
    ds, scene = state.view("000000")
    prep = prepare(ds, scene, list(info.poses))
    assert not prep.messages  # no "left.png: image file is missing"
    assert [layer.name for layer in prep.layers] == ["000000:left", "000000:right"]
