"""Review state and overlays without a browser: decisions, staleness, filters, two servers,
bad input, and pixel-exact contours."""

from __future__ import annotations

import json

import numpy as np

from annotator.dataset import load_dataset, read_poses
from annotator.dataset.poses import write_poses
from viewer.overlays import COLOURS, compose, prepare
from viewer.state import ReviewState


def test_decisions_are_saved_and_seen_by_a_second_state(sample_copy) -> None:
    a, b = ReviewState(sample_copy), ReviewState(sample_copy)
    sid = a.ids[0]
    a.set_scene(sid, "accepted")
    doc = json.loads((sample_copy / "scenes" / sid / "review.json").read_text())
    assert doc["status"] == "accepted" and doc["annotation_fingerprint"] and doc["decided_at"]
    assert b.info(sid).status == "accepted"
    key = b.info(sid).poses[0].key
    assert b.toggle_instance(sid, key) == "rejected"
    assert a.info(sid).instance_status(key) == "rejected"
    assert a.progress() == (1, 4)
    assert [s for s in a.ids if a.matches(s, "pending")] == a.ids[1:]


def test_changed_annotation_makes_the_decision_stale(sample_copy) -> None:
    st = ReviewState(sample_copy)
    sid = st.ids[1]
    st.set_scene(sid, "accepted")
    path = sample_copy / "scenes" / sid / "annotation.json"
    poses = read_poses(path)
    poses[0].t = poses[0].t + 5.0
    write_poses(path, poses)
    info = st.info(sid)
    assert info.stale and st.matches(sid, "stale") and st.matches(sid, "pending")


def test_corrupt_review_and_missing_annotation_are_reported_not_fatal(sample_copy) -> None:
    scenes = sample_copy / "scenes"
    (scenes / "000000" / "review.json").write_text("{broken")
    (scenes / "000001" / "annotation.json").unlink()
    st = ReviewState(sample_copy)
    assert "corrupt review file" in st.info("000000").error
    assert not st.info("000001").annotated
    st.set_scene("000000", "rejected")  # the next decision replaces the corrupt file
    assert st.info("000000").status == "rejected" and st.info("000000").error is None


def test_contours_follow_the_projected_silhouette(sample) -> None:
    ds = load_dataset(sample)
    scene = ds.scenes()[0]
    poses = read_poses(scene.annotation_path)
    prep = prepare(ds, scene, poses, max_width=10_000)  # full resolution
    layer = prep.layers[0]
    cam = ds.rig.cameras[0]
    p = poses[0]
    # The contour hugs the projection of the mesh's vertices: every contour point is within
    # a pixel of some projected silhouette pixel, and the projected vertices lie inside it.
    M = cam.cam_T_rig @ p.T
    uv = cam.project(ds.objects[p.object].mesh.vertices @ M[:3, :3].T + M[:3, 3])
    contour = np.concatenate(layer.contours[0])
    lo, hi = contour.min(axis=0), contour.max(axis=0)
    assert np.all(uv.min(axis=0) >= lo - 1.5) and np.all(uv.max(axis=0) <= hi + 1.5)
    states = {q.key: "pending" for q in poses}
    states[p.key] = "accepted"
    panels = compose(prep, states, set(), None)
    rgb = panels[cam.name]
    x, y = contour[0]
    window = rgb[max(y - 1, 0) : y + 2, max(x - 1, 0) : x + 2].reshape(-1, 3)
    green = np.array(COLOURS["accepted"][::-1])
    assert np.any(np.abs(window - green).sum(axis=1) < 60)
    assert {"depth", "disagreement"} <= set(panels)
