"""Repaired poses without a browser: review.json's ``poses`` read, validated and written,
applied by the viewer's state, the export and the evaluation, kept by a new ``annotate`` run
and stale once the auto pose under them changes; the overlays of a moved pose re-rendered in
place equal those prepared anew; a page's edit shown first and on disk once its key is done,
or said not to be saved."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest

from annotator.cli import main as cli
from annotator.dataset import load_dataset
from annotator.dataset.records import SceneAnnotation
from annotator.dataset.review import EditedPose, Review, apply_edits, read_review, write_review
from annotator.errors import UserError
from annotator.export.selection import select_scenes
from annotator.formats import ours
from annotator.geometry.transforms import axis_angle, make_transform
from annotator.review import ReviewState
from viewer.drawing.overlays import prepare, repose

if TYPE_CHECKING:
    from websockets.sync.client import ClientConnection

    from viewer.page.session import Session
    from viewer.server.app import ReviewApp

SCENE = "000001"
KEY = "brick/03"


def _review_path(root: Path) -> Path:
    return root / "scenes" / SCENE / "review.json"


def _edited(state: ReviewState) -> np.ndarray:
    auto = state.info(SCENE).pose(KEY)
    T = make_transform(axis_angle([0.0, 0.0, 1.0], 0.02) @ auto.R, auto.t + [1.5, 0.0, -0.5])
    state.set_pose(SCENE, KEY, T, [{"op": "nudge"}], by="page-test")
    return T


def test_an_edit_is_saved_in_review_json_and_read_back(sample_copy) -> None:
    state = ReviewState(sample_copy)
    annotation = (sample_copy / "scenes" / SCENE / "annotation.json").read_bytes()
    T = _edited(state)
    doc = json.loads(_review_path(sample_copy).read_text())
    rec = doc["poses"][KEY]
    assert rec["source"] == "edited" and rec["decided_by"] == "page-test" and rec["at"]
    assert rec["steps"] == [{"op": "nudge"}]
    assert np.allclose(np.reshape(rec["cam_R_m2c"], (3, 3)), T[:3, :3])
    assert np.allclose(rec["cam_t_m2c"], T[:3, 3])
    assert doc["status"] == "pending"  # an edit is not a decision
    # annotation.json is untouched; the state shows the edit.
    assert (sample_copy / "scenes" / SCENE / "annotation.json").read_bytes() == annotation
    info = state.info(SCENE)
    assert info.edited == {KEY} and not info.stale
    assert np.allclose(info.pose(KEY).t, T[:3, 3]) and not np.allclose(
        info.auto_pose(KEY).t, T[:3, 3]
    )
    assert info.view != info.fingerprint
    # Undo to nothing: the auto pose again.
    state.restore_pose(SCENE, KEY, None)
    assert not state.info(SCENE).edited
    assert "poses" not in json.loads(_review_path(sample_copy).read_text())


def test_an_edit_keeps_an_earlier_decision_as_it_was(sample_copy) -> None:
    state = ReviewState(sample_copy)
    state.set_scene(SCENE, "accepted", by="page-a")
    decided = json.loads(_review_path(sample_copy).read_text())
    _edited(state)
    doc = json.loads(_review_path(sample_copy).read_text())
    for name in ("status", "decided_at", "decided_by", "annotation_fingerprint"):
        assert doc[name] == decided[name]


@pytest.mark.parametrize(
    "bad, message",
    [
        ({"x": {}}, "the key must be 'object/instance'"),
        ({"brick/03": {"cam_R_m2c": [1] * 9, "cam_t_m2c": [0, 0, 0]}}, "not a rotation"),
        ({"brick/03": {"cam_R_m2c": [1, 0, 0], "cam_t_m2c": [0, 0, 0]}}, "9 finite numbers"),
        (
            {"brick/03": {"cam_R_m2c": np.eye(3).ravel().tolist(), "cam_t_m2c": [0, 0, "1"]}},
            "9 finite numbers",
        ),
        (
            {
                "brick/03": {
                    "cam_R_m2c": np.eye(3).ravel().tolist(),
                    "cam_t_m2c": [0, 0, 1],
                    "source": "auto",
                }
            },
            "source must be 'edited'",
        ),
        ([], "'poses' must map"),
    ],
)
def test_malformed_poses_in_review_json_are_one_line_errors(tmp_path, bad, message) -> None:
    path = tmp_path / "review.json"
    path.write_text(json.dumps({"status": "pending", "poses": bad}))
    with pytest.raises(UserError, match=message) as err:
        read_review(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_export_and_evaluate_use_the_edited_pose(sample_copy) -> None:
    state = ReviewState(sample_copy)
    T = _edited(state)
    state.set_scene(SCENE, "accepted")
    ds = load_dataset(sample_copy)
    sel = select_scenes(ds)
    (chosen,) = [s for s in sel.scenes if s.scene.id == SCENE]
    pose = next(p for p in chosen.poses if p.key == KEY)
    assert np.allclose(pose.R, T[:3, :3]) and np.allclose(pose.t, T[:3, 3])
    # The evaluation's ground truth where a scene has no gt.json, and the annotation as
    # results: both with the edit.
    (sample_copy / "scenes" / SCENE / "gt.json").unlink()
    gt = ours.read_ground_truth(sample_copy)
    assert any(np.allclose(t, T[:3, 3]) for t in gt.poses[(SCENE, "brick")].t)
    res = ours.annotations_as_results(sample_copy, gt)
    assert any(np.allclose(t, T[:3, 3]) for t in res.poses[(SCENE, "brick")].t)


def test_an_added_instance_is_exported_and_goes_stale_once_annotate_poses_it(sample_copy) -> None:
    path = sample_copy / "scenes" / SCENE / "annotation.json"
    doc = json.loads(path.read_text())
    (gone,) = [i for i in doc["instances"] if f"{i['object']}/{i['instance']}" == KEY]
    doc["instances"].remove(gone)
    original = path.read_text()
    path.write_text(json.dumps(doc))
    state = ReviewState(sample_copy)
    T = make_transform(np.reshape(gone["cam_R_m2c"], (3, 3)), np.array(gone["cam_t_m2c"]) + 0.5)
    state.set_pose(SCENE, KEY, T, [{"op": "add"}])
    info = state.info(SCENE)
    assert info.edited == {KEY} and info.pose(KEY) is not None and info.auto_pose(KEY) is None
    sel = select_scenes(load_dataset(sample_copy), include_pending=True)
    (chosen,) = [s for s in sel.scenes if s.scene.id == SCENE]
    assert KEY in {p.key for p in chosen.poses}
    # annotate poses it now: the hand-made pose is stale, the scene is not exported.
    path.write_text(original)
    info = state.info(SCENE)
    assert info.stale_edits == {KEY} and info.stale
    sel = select_scenes(load_dataset(sample_copy), include_pending=True)
    assert sel.skipped[SCENE] == "stale pose edit (annotation changed since)"


def test_annotate_again_keeps_edits_and_a_changed_auto_pose_makes_them_stale(sample_copy) -> None:
    state = ReviewState(sample_copy)
    T = _edited(state)
    assert cli(["annotate", str(sample_copy), "--scenes", SCENE, "--force", "--workers", "1"]) == 0
    review = read_review(_review_path(sample_copy))
    assert np.allclose(review.poses[KEY].t, T[:3, 3])  # kept
    info = state.info(SCENE)
    assert info.edited == {KEY} and not info.stale  # the same auto pose: still current
    # The auto pose changes under the edit (another annotate, other sites): stale.
    path = sample_copy / "scenes" / SCENE / "annotation.json"
    doc = json.loads(path.read_text())
    for rec in doc["instances"]:
        if f"{rec['object']}/{rec['instance']}" == KEY:
            rec["cam_t_m2c"][0] += 0.2
    path.write_text(json.dumps(doc))
    info = state.info(SCENE)
    assert info.stale_edits == {KEY} and info.stale and not info.edited
    assert np.allclose(info.pose(KEY).t, info.auto_pose(KEY).t)  # the auto pose is shown


def test_apply_edits_on_plain_records() -> None:
    from annotator.dataset.poses import InstancePose

    p = InstancePose("brick", "01", np.eye(3), np.zeros(3))
    from annotator.dataset.review import instance_fingerprint

    edit = EditedPose(np.eye(3), np.ones(3), auto_fingerprint=instance_fingerprint(p))
    added = EditedPose(np.eye(3), np.full(3, 2.0))
    out = apply_edits([p], Review(poses={"brick/01": edit, "gear/07": added}))
    assert [q.key for q in out.poses] == ["brick/01", "gear/07"]
    assert np.allclose(out.poses[0].t, 1.0) and np.allclose(out.poses[1].t, 2.0)
    assert out.edited == {"brick/01", "gear/07"} and not out.stale
    # Written and read back, the edits are the same.


def test_a_moved_pose_rendered_in_place_equals_one_prepared_anew(sample) -> None:
    ds = load_dataset(sample)
    sc = next(s for s in ds.scenes() if s.id == SCENE)
    poses = SceneAnnotation.read(sc.annotation_path).instances
    prep = prepare(ds, sc, poses)
    k = [p.key for p in poses].index(KEY)
    moved = list(poses)
    moved[k] = dataclasses.replace(
        poses[k], R=axis_angle([0.0, 1.0, 0.0], 0.08) @ poses[k].R, t=poses[k].t + [4.0, -2.0, 1.0]
    )
    fast = repose(ds, prep, moved, KEY)
    full = prepare(ds, sc, moved)
    assert fast is not None
    for a, b in zip(fast.layers, full.layers):
        assert (a.instance != b.instance).sum() <= 2  # float rounding of separate BVHs
        assert a.boxes == b.boxes
        assert [len(c) for c in a.contours] == [len(c) for c in b.contours]
    assert np.abs(fast.disagreement.astype(int) - full.disagreement).max() <= 8
    # An instance taken away is not in-place work: prepared anew.
    assert repose(ds, prep, moved[:k] + moved[k + 1 :], poses[k + 1].key) is None


def test_edits_survive_a_write_and_a_read(tmp_path) -> None:
    edit = EditedPose(
        axis_angle([1.0, 0.0, 0.0], 0.3), np.array([1.0, 2.0, 3.0]), [{"op": "refine"}], "p", "t"
    )
    path = tmp_path / "review.json"
    write_review(path, Review(poses={"brick/01": edit}))
    back = read_review(path).poses["brick/01"]
    assert np.allclose(back.R, edit.R) and np.allclose(back.t, edit.t)
    assert ([s.to_json() for s in back.steps], back.decided_by, back.at, back.auto_fingerprint) == (
        [{"op": "refine"}],
        "p",
        "t",
        None,
    )


def test_letting_the_gizmo_go_saves_the_pose_it_was_dragged_to(sample) -> None:
    import viser

    from devkit.headless import free_port
    from viewer.page.scene3d import Scene3D, _wxyz

    ds = load_dataset(sample)
    sc = next(s for s in ds.scenes() if s.id == SCENE)
    pose = next(p for p in SceneAnnotation.read(sc.annotation_path).instances if p.key == KEY)
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        got: list[tuple[str, np.ndarray]] = []
        scene = Scene3D(
            server.scene,
            ds,
            on_part=lambda key: None,
            on_canvas=lambda x, y: None,
            on_gizmo=lambda key, T: got.append((key, T)),
        )
        scene.showing_3d = True
        scene._build_3d()
        scene.show_gizmo(pose)
        gizmo = scene._gizmo
        start = (np.array(gizmo.wxyz), np.array(gizmo.position))
        turn = axis_angle([0.0, 0.0, 1.0], np.radians(5.0))

        class Event:  # what viser hands the callback
            def __init__(self, phase, wxyz, position):
                self.phase = phase
                self.target = type("T", (), {"wxyz": wxyz, "position": position})()

        scene._gizmo_moved(Event("start", *start))
        R = turn @ pose.R
        moved = start[1] + [0.002, 0.0, 0.0]
        scene._gizmo_moved(Event("update", _wxyz(R), moved))
        assert not got  # saved when let go only
        scene._gizmo_moved(Event("end", _wxyz(R), moved))
        ((key, T),) = got
        assert key == KEY
        c = pose.R @ ds.objects["brick"].mesh.moments.centroid + pose.t
        # Turned about the gizmo (the part's centre) and moved 2 mm along x.
        assert np.allclose(T[:3, :3], R, atol=1e-9)
        assert np.allclose(
            T[:3, :3] @ ds.objects["brick"].mesh.moments.centroid + T[:3, 3], c + [2, 0, 0]
        )
    finally:
        server.stop()


def test_the_view_of_a_pose_made_ahead_is_the_one_saving_it_gives(sample_copy) -> None:
    # Overlays made ahead of A are kept under the view the scene will have: it must match.
    state = ReviewState(sample_copy)
    info = state.info(SCENE)
    auto = info.pose(KEY)
    T = make_transform(axis_angle([0.0, 1.0, 0.0], 0.05) @ auto.R, auto.t + [0.0, 2.0, 0.0])
    poses, view = info.with_pose(KEY, T)
    assert [p.key for p in poses] == [p.key for p in info.poses] and view != info.view
    state.set_pose(SCENE, KEY, T, [{"op": "alternative"}], by="page-test")
    assert state.info(SCENE).view == view
    assert state.info(SCENE).with_pose(KEY, auto.T)[1] == info.view


def test_a_pose_moved_twice_in_place_equals_one_prepared_anew(sample) -> None:
    # The second move reuses the neighbours' casts kept by the first: still the same pixels.
    ds = load_dataset(sample)
    sc = next(s for s in ds.scenes() if s.id == SCENE)
    poses = SceneAnnotation.read(sc.annotation_path).instances
    k = [p.key for p in poses].index(KEY)
    prep = prepare(ds, sc, poses)
    for step in ([3.0, 1.0, 0.0], [-2.0, 4.0, 1.0]):
        moved = list(poses)
        moved[k] = dataclasses.replace(
            poses[k], R=axis_angle([1.0, 0.0, 0.0], 0.05) @ poses[k].R, t=poses[k].t + step
        )
        prep = repose(ds, prep, moved, KEY)
        assert prep is not None
    assert any(j != k for layer in prep.layers for j in layer.alone)  # neighbours kept
    _assert_prepared_anew(ds, sc, moved, prep)


def _assert_prepared_anew(ds, sc, poses, fast) -> None:
    """``fast`` (made in place) shows the pixels of ``poses`` prepared anew."""
    assert fast is not None
    full = prepare(ds, sc, poses)
    for a, b in zip(fast.layers, full.layers):
        assert (a.instance != b.instance).sum() <= 2  # float rounding of separate BVHs
        assert a.boxes == b.boxes
        assert np.abs(a.shade.astype(int) - b.shade).max() <= 1
    assert np.abs(fast.disagreement.astype(int) - full.disagreement).max() <= 8


def test_after_an_undo_the_next_move_reuses_the_neighbours_and_equals_one_prepared_anew(
    sample, monkeypatch
) -> None:
    """Nudge, undo, nudge: the second move starts from the layers shown before the first
    (the undo shows them again), which keep the neighbours the first move cast."""
    import viewer.drawing.overlays

    cast = viewer.drawing.overlays._cast_alone
    neighbours: list[int] = []  # per move, the neighbours cast

    def counted(camera, placed, rect, bound, earlier):
        neighbours[-1] += bound is not None
        return cast(camera, placed, rect, bound, earlier)

    monkeypatch.setattr(viewer.drawing.overlays, "_cast_alone", counted)
    ds = load_dataset(sample)
    sc = next(s for s in ds.scenes() if s.id == SCENE)
    poses = SceneAnnotation.read(sc.annotation_path).instances
    k = [p.key for p in poses].index(KEY)
    shown = prepare(ds, sc, poses)
    assert not any(layer.alone for layer in shown.layers)
    moves = []
    for step in ([1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]):
        moved = list(poses)
        moved[k] = dataclasses.replace(poses[k], t=poses[k].t + step)
        neighbours.append(0)
        moves.append((moved, repose(ds, shown, moved, KEY)))
    assert neighbours[0] > 0 and neighbours[1] == 0
    # The first move left its neighbours' casts in the layers it started from ...
    assert all(j != k for layer in shown.layers for j in layer.alone)
    assert any(layer.alone for layer in shown.layers)
    for moved, fast in moves:  # ... and every move gives the pixels of one prepared anew
        _assert_prepared_anew(ds, sc, moved, fast)


def test_the_overlays_made_ahead_for_a_stay_through_the_scenes_repairs(sample_copy) -> None:
    from devkit.headless import free_port
    from viewer.server.app import ReviewApp

    app = ReviewApp(sample_copy, host="127.0.0.1", port=free_port())
    try:
        state = app.state
        info = state.info(SCENE)
        prep = app.prepared(SCENE, info)
        auto = info.pose(KEY)
        ahead = make_transform(auto.R, auto.t + [0.0, 3.0, 0.0])  # the next candidate, say
        poses, view = info.with_pose(KEY, ahead)
        app.ahead(SCENE, view, repose(state.ds, prep, poses, KEY, parallel=False))
        # A nudge meanwhile drops the scene's other versions, not the one made ahead.
        state.set_pose(SCENE, KEY, make_transform(auto.R, auto.t + [1.0, 0.0, 0.0]), [], by="p")
        now = state.info(SCENE)
        app.reposed(SCENE, now, repose(state.ds, prep, list(now.poses), KEY), before=info.view)
        assert app.cache.ready((SCENE, view)) and app.cache.ready((SCENE, now.view))
        # A then shows it as it is: saving that pose gives that view.
        state.set_pose(SCENE, KEY, ahead, [{"op": "alternative"}], by="p")
        assert app.cache.ready((SCENE, state.info(SCENE).view))
    finally:
        app.stop()


def _page_on(app: ReviewApp, sid: str, key: str) -> tuple[ClientConnection, Session]:
    """A bare page (no browser) showing the zoom on instance ``key`` of scene ``sid``."""
    from devkit.polling import wait_until
    from devkit.wire import open_page

    ws = open_page(app.port, width=1000, height=800)
    assert wait_until(lambda: len(app.sessions) == 1), "the page did not connect"
    session = next(iter(app.sessions.values()))
    assert wait_until(lambda: session.displayed is not None)
    # The page opens on the first scene with a physics flag, which may lie either side of sid.
    ids = list(session.nav.scenes.ids)
    while session.nav.current != sid:
        ahead = ids.index(session.nav.current) < ids.index(sid)
        session.next() if ahead else session.previous()
    session.select(key)
    assert wait_until(
        lambda: session.shown.zoom_for is not None and session.shown.zoom_for[0] == sid
    )
    assert wait_until(lambda: not session._rendering)  # the next render is the key's own
    return ws, session


def test_a_nudge_is_shown_first_and_on_disk_when_its_key_is_done(sample_copy, monkeypatch) -> None:
    import annotator.review.state
    import viewer.page.pictures
    from devkit.headless import free_port
    from viewer.server.app import ReviewApp

    app = ReviewApp(sample_copy, host="127.0.0.1", port=free_port())
    try:
        ws, session = _page_on(app, SCENE, KEY)
        order: list[str] = []
        write, encode = annotator.review.state.write_review, viewer.page.pictures.zoom_layers

        def writing(path, review):
            order.append("write")
            write(path, review)

        def encoding(*args, **kwargs):
            order.append("pixels")
            return encode(*args, **kwargs)

        monkeypatch.setattr(annotator.review.state, "write_review", writing)
        monkeypatch.setattr(viewer.page.pictures, "zoom_layers", encoding)
        before = app.state.info(SCENE).pose(KEY).t.copy()
        session.nudge(0, +1)
        # The new zoom went out before the write, and the pose is on disk once the key is
        # handled: a server killed now loses nothing.
        assert order[:2] == ["pixels", "write"], order
        rec = json.loads(_review_path(sample_copy).read_text())["poses"][KEY]
        assert np.allclose(rec["cam_t_m2c"], before + [1.0, 0.0, 0.0])
        assert ReviewState(sample_copy).info(SCENE).view == session.shown.zoom_for[1]
        assert not session.unsaved and len(session.editor.history[SCENE]) == 1
        ws.close()
    finally:
        app.stop()


def test_a_nudge_that_cannot_be_written_is_said_so_and_taken_back(sample_copy, monkeypatch) -> None:
    import annotator.review.state
    from devkit.headless import free_port
    from viewer.server.app import ReviewApp

    app = ReviewApp(sample_copy, host="127.0.0.1", port=free_port())
    try:
        ws, session = _page_on(app, SCENE, KEY)
        shown = app.state.info(SCENE).view

        def refuse(path, review):
            raise PermissionError(13, "Permission denied", str(path))

        monkeypatch.setattr(annotator.review.state, "write_review", refuse)
        session.nudge(0, +1)
        assert (
            "NOT saved" in session.unsaved[SCENE] and "Permission denied" in session.unsaved[SCENE]
        )
        assert not _review_path(sample_copy).exists()
        # The page shows the pose the file holds again, and there is nothing to undo.
        assert app.state.info(SCENE).view == shown and session.shown.zoom_for[1] == shown
        assert not session.editor.history.get(SCENE)
        # The next change that can be written clears the red notice.
        monkeypatch.undo()
        session.nudge(0, +1)
        assert SCENE not in session.unsaved and _review_path(sample_copy).exists()
        ws.close()
    finally:
        app.stop()
