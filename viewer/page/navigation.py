"""Where one reviewer is: the current scene, the filter, the selected instance and whether
the zoom is open. Each browser page has its own :class:`Navigator`; the scenes' decisions are
shared (:class:`annotator.review.state.ReviewState`).

It knows nothing of viser, so it is tested on its own; it only asks the shared state which
scenes there are, which match a filter, which are flagged and which instances a scene has.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from annotator.review import FILTERS


class _SceneLike(Protocol):
    @property
    def flagged(self) -> bool: ...

    @property
    def physics_flagged(self) -> bool: ...

    @property
    def poses(self) -> tuple: ...


class Catalogue(Protocol):
    """What a navigator needs to know about the scenes (ReviewState provides it)."""

    ids: list[str]

    def matches(self, sid: str, flt: str) -> bool: ...

    def info(self, sid: str) -> _SceneLike: ...


@dataclass
class Navigator:
    """One reviewer's cursor over the scenes of a :class:`Catalogue`.

    Moving follows the dataset order, restricted to the scenes that match the filter (all
    scenes if none does); the current scene may itself no longer match (it was just decided
    while the filter is "pending"), and moving is then relative to its place in that order.
    """

    scenes: Catalogue
    current: str | None = None
    filter: str = "all"
    selected: str | None = None
    zoom: bool = False

    def __post_init__(self) -> None:
        if self.current is None and self.scenes.ids:
            # A pose that cannot be physically right is the first thing to look at.
            ids = self.scenes.ids
            self.current = next((s for s in ids if self.scenes.info(s).physics_flagged), ids[0])

    def visible_ids(self) -> list[str]:
        """Scenes matching the filter, in dataset order."""
        if self.filter == "all":
            return list(self.scenes.ids)
        return [sid for sid in self.scenes.ids if self.scenes.matches(sid, self.filter)]

    def _neighbour(self, delta: int) -> str | None:
        ids = self.scenes.ids
        visible = set(self.visible_ids()) or set(ids)
        if self.current not in ids:
            order = [s for s in ids if s in visible]
            return order[0] if order else None
        k = ids.index(self.current)
        seq = ids[k + 1 :] if delta > 0 else list(reversed(ids[:k]))
        return next((s for s in seq if s in visible), None)

    def peek(self, delta: int = +1) -> str | None:
        """The scene a step of ``delta`` (+1 or -1) would go to, None at an end."""
        return self._neighbour(delta)

    def upcoming(self) -> list[str]:
        """The scenes this reviewer may go to next, most likely first: the next two of the
        filter, then the previous one."""
        out = []
        nxt = self._neighbour(+1)
        if nxt is not None:
            out.append(nxt)
            saved = self.current
            self.current = nxt
            try:
                after = self._neighbour(+1)
            finally:
                self.current = saved
            if after is not None:
                out.append(after)
        prev = self._neighbour(-1)
        if prev is not None:
            out.append(prev)
        return out

    def go(self, sid: str) -> None:
        """Show scene ``sid`` (selection and zoom are per scene: they are reset)."""
        if sid != self.current:
            self.current, self.selected, self.zoom = sid, None, False

    def step(self, delta: int) -> bool:
        """Go to the next (+1) or previous (-1) scene of the filter; False at an end."""
        target = self._neighbour(delta)
        if target is None:
            return False
        self.go(target)
        return True

    def next_flagged(self) -> bool:
        """Go to the next flagged scene after the current one (wrapping around); False if
        there is none other."""
        ids = self.scenes.ids
        k = ids.index(self.current) if self.current in ids else -1
        for sid in ids[k + 1 :] + ids[: k + 1]:
            if sid != self.current and self.scenes.info(sid).flagged:
                self.go(sid)
                return True
        return False

    def set_filter(self, flt: str) -> None:
        """Change the filter; if the current scene does not match it, go to the first that
        does."""
        if flt not in FILTERS:
            raise ValueError(f"unknown filter {flt!r}; one of {', '.join(FILTERS)}")
        self.filter = flt
        ids = self.visible_ids()
        if ids and self.current not in ids:
            self.go(ids[0])

    def after_decision(self) -> None:
        """Move on after deciding the current scene (stay if it is the last one)."""
        self.step(+1)

    def keys(self) -> list[str]:
        """The instances of the current scene."""
        if self.current is None:
            return []
        return [p.key for p in self.scenes.info(self.current).poses]

    def select(self, key: str | None, *, zoom: bool = True) -> None:
        """Select an instance (None: none) and open the zoom on it."""
        if key is not None and key not in self.keys():
            return
        self.selected = key
        self.zoom = zoom and key is not None

    def select_next(self) -> None:
        """Select the next instance of the scene (the first if none is) and zoom on it."""
        keys = self.keys()
        if keys:
            k = keys.index(self.selected) if self.selected in keys else -1
            self.select(keys[(k + 1) % len(keys)])

    def toggle_zoom(self) -> None:
        """Open the zoom (on the selected instance, or the first) or close it."""
        if self.zoom:
            self.zoom = False
        elif self.selected is not None:
            self.zoom = True
        else:
            keys = self.keys()
            if keys:
                self.select(keys[0])
