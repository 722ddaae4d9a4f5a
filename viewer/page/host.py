"""What a review page needs of the server it belongs to (:class:`viewer.server.app.ReviewApp`): the
shared review state, the prepared scenes and their cache, the inputs of repairs, and where
to say that scenes changed. A page holds it as this Protocol, so the page's modules never
import the app (which imports them), and their tests can hand them a fake.
"""

from __future__ import annotations

from typing import Any, Protocol

from annotator.review import ReviewState, SceneInfo
from viewer.drawing.cache import PrefetchCache
from viewer.drawing.overlays import Prepared
from viewer.page.repair import RepairInputs


class ReviewHost(Protocol):
    """The server of a page (see the module docstring)."""

    state: ReviewState
    cache: PrefetchCache[Prepared]
    tag: str  # tells this server's pages from another server's
    start_scene: str | None  # where a new page opens (None: the navigator's choice)

    def prepared(self, sid: str, info: SceneInfo) -> Prepared:
        """The scene's overlays for the poses of ``info`` (made, or from the cache)."""
        ...

    def reposed(self, sid: str, info: SceneInfo, prep: Prepared, before: str) -> None:
        """Keep ``prep``, made from the overlays of view ``before`` by a repair."""
        ...

    def ahead(self, sid: str, view: str, prep: Prepared) -> None:
        """Keep ``prep``, made ahead of a key for view ``view``."""
        ...

    def repair_inputs(self, sid: str, info: SceneInfo) -> RepairInputs:
        """The scene's images, depth and markers read, for repairs (as ``info`` shows it)."""
        ...

    def drew(self) -> None:
        """A page made a picture: the cache may trim itself."""
        ...

    def prefetch(self, sid: str) -> None:
        """Prepare scene ``sid`` in the background (a page is heading there)."""
        ...

    def prefetch_frames(self, sid: str, at: int, step: int = 1) -> None:
        """Prepare the frames P (Shift+P: ``step`` -1) would show of sequence ``sid`` on a
        page whose window is ``at`` frames on."""
        ...

    def changed(self, origin: Any, sids: set[str]) -> None:
        """Scenes ``sids`` changed through page ``origin``: tell the other pages."""
        ...
