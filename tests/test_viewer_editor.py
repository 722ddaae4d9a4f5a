"""The repair editor with a fake page and a fake server (no viser, no browser): nudges are
written with their steps, undo and redo walk the page's own steps, a change is refused and
said when another reviewer got there first, and nothing is written for a page still
switching scenes."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from annotator.dataset.review import read_review
from annotator.geometry.transforms import make_transform
from annotator.review import ReviewState, SaveError, SceneInfo
from viewer.drawing.overlays import Prepared
from viewer.page.editor import RepairEditor

SCENE = "000001"
KEY = "brick/03"


class _Cache:
    def ready(self, key: object) -> bool:
        return False


@dataclass
class _Host:
    state: ReviewState
    cache: _Cache = field(default_factory=_Cache)
    tag: str = "test"
    reposed_calls: int = 0

    def reposed(self, *args: object, **kwargs: object) -> None:
        self.reposed_calls += 1


@dataclass
class _Page:
    """What :class:`viewer.page.editor.EditorPage` asks for, recording what the editor did."""

    host: _Host
    scene: str | None = SCENE
    selected: str | None = KEY
    switching: bool = False  # the page is still sending another scene
    id: str = "page-fake"
    closed: bool = False
    said: list[str] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)
    renders: int = 0

    def cursor(self) -> tuple[str | None, str | None]:
        return self.scene, self.selected

    def info(self, sid: str) -> SceneInfo:
        return self.host.state.info(sid)

    def shown_scene(self, what: str) -> str | None:
        if self.switching:
            self.refused.append(f"{what}: the page was still switching")
            return None
        return self.scene

    def prepared_scene(self) -> Prepared | None:
        return None  # no overlays to re-render in place: the render makes them

    def write(self, sid: str, what: str, fn: Callable[[], object], *, decision: bool) -> bool:
        try:
            fn()
        except SaveError as exc:
            self.not_saved(sid, what, str(exc))
            return False
        return True

    def not_saved(self, sid: str, what: str, why: str) -> None:
        self.refused.append(f"{what}: {why}")

    def show_repair(self, text: str, nudges: str) -> None:
        self.said.append(text)

    def focus(self, key: str, *, zoom: bool | None = None) -> None:
        self.selected = key

    def request_render(self) -> None:
        self.renders += 1


@pytest.fixture()
def page(sample_copy: Path) -> _Page:
    return _Page(_Host(ReviewState(sample_copy)))


def _saved(page: _Page):
    review = read_review(page.host.state.scene(SCENE).review_path)
    return None if review is None else review.poses.get(KEY)


def test_nudges_are_written_with_their_steps_and_undone_in_order(page: _Page) -> None:
    editor = RepairEditor(page)
    auto = page.host.state.info(SCENE).auto_pose(KEY)
    assert auto is not None
    editor.nudge(0, +1)
    editor.toggle_nudge_kind()
    editor.nudge(2, -1)
    edit = _saved(page)
    assert edit is not None and [s.to_json()["kind"] for s in edit.steps] == ["move", "turn"]
    assert edit.decided_by == "page-fake" and len(editor.history[SCENE]) == 2
    assert "turn" in editor.nudge_text() and page.said[-1].startswith(f"{KEY}: turn")
    editor.undo()
    once = _saved(page)
    assert once is not None and [s.to_json()["kind"] for s in once.steps] == ["move"]
    assert np.allclose(once.t, auto.t + [1.0, 0.0, 0.0])
    editor.undo()
    assert _saved(page) is None  # back to the auto pose
    editor.undo()
    assert page.said[-1] == "nothing to undo in this scene"
    editor.redo()
    editor.redo()
    again = _saved(page)
    assert again is not None and [s.to_json()["kind"] for s in again.steps] == ["move", "turn"]
    editor.close()


def test_an_undo_after_another_reviewers_change_is_refused(page: _Page) -> None:
    editor = RepairEditor(page)
    editor.nudge(1, +1)
    other = ReviewState(page.host.state.ds.root)
    pose = other.info(SCENE).pose(KEY)
    assert pose is not None
    other.set_pose(SCENE, KEY, make_transform(pose.R, pose.t + 3.0), [], by="page-other")
    editor.undo()
    assert page.refused and "changed by page-other" in page.refused[-1]
    edit = _saved(page)
    assert edit is not None and edit.decided_by == "page-other"
    assert not editor.history.get(SCENE) and not editor.future.get(SCENE)
    editor.close()


def test_nothing_is_written_while_the_page_is_switching(page: _Page) -> None:
    editor = RepairEditor(page)
    page.switching = True
    editor.nudge(0, +1)
    editor.reset_pose()
    assert _saved(page) is None and len(page.refused) == 2
    page.switching, page.selected = False, None
    editor.nudge(0, +1)
    assert page.said[-1].startswith("select an instance first") and _saved(page) is None
    editor.close()
