"""Each reviewer's cursor, without viser: moving through a filter, deciding and moving on,
flagged scenes, instance selection and the zoom, and the scenes to prepare next."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from viewer.page.navigation import Navigator


@dataclass
class _Pose:
    key: str


@dataclass
class _Info:
    flagged: bool = False
    poses: tuple = ()
    physics_flagged: bool = False


@dataclass
class _Scenes:
    """A catalogue: scenes by id, with a status each ("pending", "accepted", ...)."""

    ids: list[str]
    status: dict[str, str] = field(default_factory=dict)
    flagged: set[str] = field(default_factory=set)
    physics: set[str] = field(default_factory=set)  # scenes with a physically impossible pose

    def matches(self, sid: str, flt: str) -> bool:
        st = self.status.get(sid, "pending")
        return {
            "all": True,
            "pending": st == "pending",
            "flagged": sid in self.flagged,
            "rejected": st == "rejected",
            "stale": False,
        }[flt]

    def info(self, sid: str) -> _Info:
        poses = (_Pose(f"{sid}/a"), _Pose(f"{sid}/b"))
        return _Info(sid in self.flagged, poses, sid in self.physics)


def test_two_navigators_on_the_same_scenes_are_independent() -> None:
    scenes = _Scenes(["s0", "s1", "s2", "s3"])
    a, b = Navigator(scenes), Navigator(scenes)
    assert a.current == b.current == "s0"
    a.step(+1)
    a.select("s1/b")
    assert (a.current, a.selected, b.current, b.selected) == ("s1", "s1/b", "s0", None)
    b.set_filter("flagged")
    assert a.filter == "all"


def test_moving_stops_at_the_ends() -> None:
    nav = Navigator(_Scenes(["s0", "s1"]))
    assert not nav.step(-1) and nav.current == "s0"
    assert nav.step(+1) and nav.current == "s1"
    assert not nav.step(+1) and nav.current == "s1"


def test_pending_filter_moves_on_from_a_scene_just_decided() -> None:
    scenes = _Scenes(["s0", "s1", "s2", "s3"])
    nav = Navigator(scenes)
    nav.set_filter("pending")
    scenes.status["s0"] = "accepted"  # decided: no longer in the filter
    nav.after_decision()
    assert nav.current == "s1"
    scenes.status["s2"] = "rejected"
    nav.step(+1)
    assert nav.current == "s3"  # s2 is skipped
    nav.step(-1)
    assert nav.current == "s1"
    nav.set_filter("rejected")
    assert nav.current == "s2"  # the current scene does not match: the first that does
    with pytest.raises(ValueError, match="unknown filter"):
        nav.set_filter("nonsense")


def test_next_flagged_wraps_around() -> None:
    scenes = _Scenes(["s0", "s1", "s2", "s3"], flagged={"s1"})
    nav = Navigator(scenes, current="s2")
    assert nav.next_flagged() and nav.current == "s1"
    assert not nav.next_flagged() and nav.current == "s1"  # no other


def test_selection_zoom_and_scene_changes() -> None:
    nav = Navigator(_Scenes(["s0", "s1"]))
    nav.select_next()
    assert (nav.selected, nav.zoom) == ("s0/a", True)
    nav.select_next()
    assert nav.selected == "s0/b"
    nav.select_next()
    assert nav.selected == "s0/a"  # wraps
    nav.toggle_zoom()
    assert not nav.zoom and nav.selected == "s0/a"
    nav.toggle_zoom()
    assert nav.zoom
    nav.select("elsewhere/x")  # not in this scene: ignored
    assert nav.selected == "s0/a"
    nav.step(+1)  # selection and zoom belong to a scene
    assert (nav.selected, nav.zoom) == (None, False)
    nav.toggle_zoom()
    assert (nav.selected, nav.zoom) == ("s1/a", True)


def test_upcoming_scenes_are_the_next_two_then_the_previous() -> None:
    scenes = _Scenes(["s0", "s1", "s2", "s3", "s4"])
    nav = Navigator(scenes, current="s2")
    assert nav.upcoming() == ["s3", "s4", "s1"]
    scenes.status["s3"] = "accepted"
    nav.set_filter("pending")
    assert nav.upcoming() == ["s4", "s1"]
    assert nav.current == "s2"


def test_a_scene_with_a_physically_impossible_pose_is_shown_first() -> None:
    scenes = _Scenes(["s0", "s1", "s2"], flagged={"s0", "s2"}, physics={"s2"})
    assert Navigator(scenes).current == "s2"
    assert Navigator(_Scenes(["s0", "s1"])).current == "s0"
