"""Review state without a browser: review.json (statuses, new fields, round trip),
decisions, staleness, filters, two servers, changes seen by polling, write failures, scene
warnings, and bad input."""

from __future__ import annotations

import json

import pytest

from annotator.dataset.figures import depth_regions
from annotator.dataset.poses import read_pose_file, read_poses, write_poses
from annotator.dataset.review import (
    NO_POSE_REASON,
    MissingPart,
    Review,
    ReviewStatus,
    read_review,
    write_review,
)
from annotator.errors import UserError
from annotator.review import ReviewState, SaveError


def test_review_status_is_the_json_string() -> None:
    assert ReviewStatus.ACCEPTED == "accepted" and str(ReviewStatus.REJECTED) == "rejected"
    assert f"{ReviewStatus.PENDING}" == "pending"
    assert json.dumps({"s": ReviewStatus.ACCEPTED}) == '{"s": "accepted"}'
    assert Review("accepted", {"a/1": "rejected"}).instances["a/1"] is ReviewStatus.REJECTED


def test_review_file_round_trips_new_and_unknown_fields(tmp_path) -> None:
    path = tmp_path / "review.json"
    review = Review(
        ReviewStatus.REJECTED,
        {"box/01": ReviewStatus.ACCEPTED},
        "2026-11-22T16:04:00+00:00",
        "fp",
        extra={"note": "kept as is"},
        reason=NO_POSE_REASON,
        missing=[MissingPart("left", (612.0, 433.5), "2026-11-22T16:03:58+00:00")],
        decided_by="page-abc-1",
    )
    write_review(path, review)
    doc = json.loads(path.read_text())
    assert doc["status"] == "rejected" and doc["instances"] == {"box/01": "accepted"}
    assert doc["missing"] == [
        {"camera": "left", "pixel": [612.0, 433.5], "at": "2026-11-22T16:03:58+00:00"}
    ]
    assert doc["note"] == "kept as is" and doc["reason"] == NO_POSE_REASON
    again = read_review(path)
    assert again == review
    # Files written before these fields read as before, and nothing new is written for them.
    write_review(path, Review("accepted"))
    assert set(json.loads(path.read_text())) == {
        "status",
        "instances",
        "decided_at",
        "annotation_fingerprint",
    }


@pytest.mark.parametrize(
    ("doc", "message"),
    [
        ({"status": "maybe"}, "unknown scene status"),
        ({"missing": [{"camera": "left", "pixel": [1]}]}, "'missing' must be a list"),
        ({"missing": {"camera": "left"}}, "'missing' must be a list"),
        ({"reason": 3}, "'reason' must be a string"),
    ],
)
def test_malformed_review_files_are_one_clear_error(tmp_path, doc, message) -> None:
    path = tmp_path / "review.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(UserError, match=message):
        read_review(path)


def test_decisions_are_saved_and_seen_by_a_second_state(sample_copy) -> None:
    a, b = ReviewState(sample_copy), ReviewState(sample_copy)
    sid = a.ids[0]
    a.set_scene(sid, "accepted", by="page-a")
    doc = json.loads((sample_copy / "scenes" / sid / "review.json").read_text())
    assert doc["status"] == "accepted" and doc["annotation_fingerprint"] and doc["decided_at"]
    assert doc["decided_by"] == "page-a"
    assert b.info(sid).status == ReviewStatus.ACCEPTED
    key = b.info(sid).poses[0].key
    assert b.toggle_instance(sid, key) == ReviewStatus.REJECTED
    assert a.info(sid).instance_status(key) == ReviewStatus.REJECTED
    assert a.progress() == (1, 4)
    assert [s for s in a.ids if a.matches(s, "pending")] == a.ids[1:]
    b.set_instance(sid, key, "accepted")
    assert a.info(sid).instance_status(key) == ReviewStatus.ACCEPTED


def test_poll_reports_changes_by_other_hands_only(sample_copy) -> None:
    a, b = ReviewState(sample_copy), ReviewState(sample_copy)
    assert a.poll() == set()
    a.set_scene("000001", "rejected")
    assert a.poll() == set()  # its own write
    b.set_scene("000002", "accepted")
    assert a.poll() == {"000002"}
    assert a.poll() == set()


def test_no_pose_here_rejects_the_scene_and_keeps_every_mark(sample_copy) -> None:
    st = ReviewState(sample_copy)
    st.mark_missing("000000", "left", (100.04, 200.0))
    st.mark_missing("000000", "right", (5.0, 6.0))
    info = st.info("000000")
    assert info.status == ReviewStatus.REJECTED and info.review.reason == NO_POSE_REASON
    assert [(m.camera, m.pixel) for m in info.review.missing] == [
        ("left", (100.0, 200.0)),
        ("right", (5.0, 6.0)),
    ]
    st.set_scene("000000", "rejected")  # rejecting again keeps them
    assert len(st.info("000000").review.missing) == 2
    st.set_scene("000000", "accepted")  # every part is posed after all: no marks, no reason
    info = st.info("000000")
    assert info.review.missing == [] and info.review.reason is None


def test_a_failed_write_raises_one_line_and_changes_nothing(sample_copy, monkeypatch) -> None:
    st = ReviewState(sample_copy)

    def refuse(path, review):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr("annotator.review.state.write_review", refuse)
    with pytest.raises(SaveError, match=r"review.json: cannot write \(Permission denied\)") as exc:
        st.set_scene("000000", "accepted")
    assert "\n" not in str(exc.value)
    assert st.info("000000").status == ReviewStatus.PENDING and st.decided == 0


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
    assert st.info("000000").status == ReviewStatus.REJECTED and st.info("000000").error is None


def test_warnings_old_and_new_forms_flag_the_scene(sample_copy) -> None:
    path = sample_copy / "scenes" / "000000" / "annotation.json"
    poses, rest = read_pose_file(path)
    region = {"box": [10, 20, 60, 90], "pixels": 812, "depth_mm": [431.0, 447.5]}
    rest["warnings"] = [
        "an old plain-text warning",
        {"kind": "unexplained_depth", "message": "depth no part explains", "regions": [region]},
        {"kind": "blurred", "message": "left.png is blurred"},
        {"kind": "weird"},
        42,
    ]
    write_poses(path, poses, **rest)
    st = ReviewState(sample_copy)
    info = st.info("000000")
    assert info.flagged and st.matches("000000", "flagged")
    kinds = [w.kind for w in info.warnings]
    assert kinds == ["note", "unexplained_depth", "blurred", "weird", "note"]
    assert [w.text for w in info.warnings][2:] == ["left.png is blurred", "weird", "42"]
    (r,) = depth_regions(info.warnings)
    assert r.box == (10, 20, 60, 90) and r.pixels == 812 and r.depth_mm == (431.0, 447.5)
    assert "812 px" in r.describe() and "431-448 mm" in r.describe()


def test_a_region_with_malformed_figures_is_still_shown() -> None:
    from annotator.dataset.figures import SceneWarning

    w = SceneWarning.from_json(
        {
            "kind": "unexplained_depth",
            "message": "m",
            "regions": [{"box": [1, 2, 3, 4], "depth_mm": ["a", 3], "unread_markers": ["x"]}],
        }
    )
    (r,) = depth_regions([w])
    assert r.depth_mm is None and r.unread_markers == () and r.describe() == "x 1-3, y 2-4"
