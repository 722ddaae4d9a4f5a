"""The review server: one viser server, one shared review state and prefetch cache, and one
:class:`~viewer.page.session.Session` per browser page.

Each page has its own cursor, filter, selection and zoom. Decisions are shared: a decision
made in one page reaches the other pages of this server at once, and a poll of the scenes'
files (every :data:`POLL_SECONDS`) brings those of other servers on the same dataset, so the
progress bar is the same everywhere.

Connections are checked (:mod:`viewer.server.access`): only pages of this server, and with a token
when one is required. A server listening beyond this machine requires a token. Frames a
connection sends that are not viser's messages are dropped (:mod:`viewer.server.messages`).

Memory (:mod:`viewer.drawing.memory`): prepared scenes are kept within :data:`CACHE_BYTES`, the
pictures drawn from them for a page are dropped when the page closes, and the freed memory is
given back to the operating system then.
"""

from __future__ import annotations

import secrets
import socket
import threading
import warnings
from collections.abc import Hashable
from pathlib import Path

import viser

from annotator.errors import UserError
from annotator.review import ReviewState, SceneInfo, frames_digest
from viewer.drawing.cache import PrefetchCache
from viewer.drawing.memory import bound_allocator, give_back
from viewer.drawing.mosaic import compose, forget
from viewer.drawing.overlays import Prepared, prepare
from viewer.drawing.style import Look
from viewer.page.repair import RepairInputs
from viewer.page.session import Session
from viewer.server import messages
from viewer.server.access import Access, Guard, install, is_loopback
from viewer.server.startup import check_port, start_viser

# A page that closes while its scene is being sent: the rest of the scene goes nowhere, as
# it should; viser warns of each such message, which says nothing to the reviewer.
warnings.filterwarnings(
    "ignore", message=r"Queued a \w+ on a closed connection", category=UserWarning
)

POLL_SECONDS = 0.5
#: A closed page's last objects are freed by viser's teardown after the page's disconnect
#: callback: the memory is given back then, and once more this long after.
GIVE_BACK_AGAIN_SECONDS = 2.0
#: Prepared scenes kept (the next ones, prepared ahead): at most this many ...
CACHE_SCENES = 6
#: ... and within these bytes, pictures drawn for the pages included (a scene of the sample
#: dataset is 20 MB, plus about 8 MB per 1400 x 1000 page and up to 250 MB per 8K page).
CACHE_BYTES = 1024 * 2**20
#: Scenes whose detected markers and depth are kept for repairs.
REPAIR_SCENES = 3


def _check_listenable(host: str) -> None:
    """UserError unless this machine can listen on ``host`` (viser would retry a thousand
    ports and then wait forever)."""
    try:
        infos = socket.getaddrinfo(
            host or None, 0, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )
        family, kind, proto, _, address = infos[0]
        with socket.socket(family, kind, proto) as s:
            s.bind(address)
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise UserError(f"--host {host}: cannot listen on this address ({reason})") from None


class ReviewApp:
    """A review server for one dataset. ``stop()`` ends it.

    Args:
        root: the dataset folder.
        host: address to listen on; anything but this machine's own addresses requires
            ``token``.
        port: port (the next free one if it is taken; see :attr:`port`).
        token: the token a page must present (None: none, for 127.0.0.1 only).
        start_scene: the scene every new page opens on (None: the first with a physics flag,
            else the first).
    """

    def __init__(
        self,
        root: str | Path,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        token: str | None = None,
        start_scene: str | None = None,
    ) -> None:
        if not is_loopback(host) and not token:
            raise UserError(
                f"--host {host} makes the page reachable from other machines, and the page "
                "writes files: give a --token"
            )
        check_port(port)
        _check_listenable(host)
        bound_allocator()
        self.state = ReviewState(root)
        if start_scene is not None and start_scene not in self.state.ids:
            raise UserError(f"--scene {start_scene}: no such scene in {root}")
        self.start_scene = start_scene
        self.cache: PrefetchCache[Prepared] = PrefetchCache(
            size=CACHE_SCENES, max_bytes=CACHE_BYTES, weigh=lambda prep: prep.nbytes
        )
        self.tag = secrets.token_hex(3)  # tells this server's pages from another server's
        try:
            self.server = start_viser(host, port, verbose=False)
        except BaseException:
            self.cache.stop()
            raise
        self.port = self.server.get_port()
        self.access = Access(host, self.port, token or None)
        try:
            self.guard: Guard = install(self.server, self.access)
            self.frames: messages.FrameFilter = messages.install(self.server)
        except BaseException:  # also Ctrl-C meanwhile: never leave a server running
            self.server.stop()
            self.cache.stop()
            raise
        self.server.gui.configure_theme(control_width="large", show_share_button=False)
        # The pictures need no lighting: the environment map (the 3D view's shading) is sent
        # only when a page first shows the 3D view. Without it, software WebGL (headless
        # Chromium, many laptops) opens the page seconds sooner.
        self.server.scene.configure_environment_map(hdri=None)
        self.server.scene.configure_default_lights(enabled=True, cast_shadow=False)
        self._lock = threading.Lock()
        self._repair: dict[tuple[str, tuple[str, ...], str], RepairInputs] = {}
        self._ahead: dict[str, str] = {}  # scene -> the poses (view) prepared ahead for it
        self.sessions: dict[int, Session] = {}
        self._give_back_later: threading.Timer | None = None
        self._left_early: set[int] = set()  # pages that left before their session was listed
        self._stop = threading.Event()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        self._poller = threading.Thread(target=self._poll, name="review-poll", daemon=True)
        self._poller.start()
        if self.state.ids:  # the first page shows at once
            self.prefetch(self.state.ids[0])

    @property
    def url(self) -> str:
        """The address to open in a browser (with the token, if one is required)."""
        return self.access.page_url()

    # ----------------------------------------------------------------- pages
    def _connect(self, client: viser.ClientHandle) -> None:
        if not self.guard.is_admitted(client.client_id) or self._stop.is_set():
            return
        session = Session(self, client)
        with self._lock:
            left = client.client_id in self._left_early
            self._left_early.discard(client.client_id)
            if not left:
                self.sessions[client.client_id] = session
        if left:  # the page went while its session was being made: nobody to show it to
            session.close()
            return
        # Shown once it is listed: pictures are drawn ahead of time, and kept, for the canvas
        # sizes of the pages listed only.
        session.request_render()

    def _disconnect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            session = self.sessions.pop(client.client_id, None)
            if session is None and self.guard.is_admitted(client.client_id):
                self._left_early.add(client.client_id)  # _connect is still making it
        if session is None:
            return
        session.close()  # waits for its render under way: nothing is drawn for it after this
        self.forget_closed_pages()

    def viewports(self) -> set[tuple[int, int]]:
        """The canvas sizes of the open pages."""
        with self._lock:
            return {s.viewport for s in self.sessions.values()}

    def forget_closed_pages(self) -> None:
        """Drop the pictures drawn for canvas sizes no open page has, and give the memory
        back to the operating system."""
        keep = self.viewports()
        for prep in self.cache.values():
            forget(prep, keep)
        give_back()
        with self._lock:
            if self._give_back_later is None or not self._give_back_later.is_alive():
                self._give_back_later = threading.Timer(GIVE_BACK_AGAIN_SECONDS, give_back)
                self._give_back_later.daemon = True
                self._give_back_later.start()

    def changed(self, origin: Session | None, sids: set[str]) -> None:
        """Scenes ``sids`` were decided (by ``origin``, or on disk by other hands): every
        other page updates its progress and, if it shows one of them, the scene."""
        with self._lock:
            others = [s for s in self.sessions.values() if s is not origin]
        for session in others:
            # Each page in its own thread: a slow page must not delay the others.
            threading.Thread(target=session.on_changed, args=(set(sids),), daemon=True).start()

    def _poll(self) -> None:
        while not self._stop.wait(POLL_SECONDS):
            changed = self.state.poll()
            if changed:
                self.changed(None, changed)

    # ---------------------------------------------------------------- scenes
    def _make(self, sid: str, info: SceneInfo):
        # ``info``'s own view of the scene (a sequence: the frames it shows), whatever the
        # scene shows by the time this runs.
        ds, scene = self.state.view(sid, info)

        def make() -> Prepared:
            prep = prepare(ds, scene, list(info.poses))
            look = Look.of(self.state.info(sid))
            for w, h in self.viewports():  # the mosaic for the pages' canvases, ahead of time
                compose(prep, look, w, h)
            # A page that closed meanwhile: what was drawn for it only would stay.
            forget(prep, self.viewports())
            return prep

        return make

    def prepared(self, sid: str, info: SceneInfo) -> Prepared:
        """The overlays and point cloud of a scene (waits if they are being prepared)."""
        return self.cache.get((sid, info.view), self._make(sid, info))

    def reposed(self, sid: str, info: SceneInfo, prep: Prepared, before: str) -> None:
        """``prep`` shows scene ``sid`` as ``info`` has it now (a pose repaired), made from
        its version ``before``. Older versions of the scene are dropped: a reviewer nudging
        a part must not push the scenes prepared ahead out of the cache (the version before
        stays, for an undo)."""
        keep = {(sid, info.view), (sid, before), (sid, info.fingerprint)}
        with self._lock:
            keep.add((sid, self._ahead.get(sid, "")))

        def older(key: Hashable) -> bool:  # the cache's keys are (scene, version)
            return isinstance(key, tuple) and key[0] == sid and key not in keep

        self.cache.drop(older)
        self.cache.put((sid, info.view), prep)

    def ahead(self, sid: str, view: str, prep: Prepared) -> None:
        """``prep`` shows scene ``sid`` with the poses a page may show next (``view``, their
        fingerprint: the next candidate of A); kept through the repairs of the scene until
        another replaces it, so that the key only has to show it."""
        with self._lock:
            self._ahead[sid] = view
        self.cache.put((sid, view), prep)

    def repair_inputs(self, sid: str, info: SceneInfo) -> RepairInputs:
        """The markers as detected and the depth of scene ``sid`` as ``info`` shows it (made
        once, kept for the last few scenes: what R, A and adding a part start from)."""
        # A sequence's: of the frames shown, where the annotation put them.
        key = (sid, info.shown, frames_digest(info.frames, info.shown) if info.shown else "")
        with self._lock:
            hit = self._repair.get(key)
        if hit is not None:
            return hit
        inputs = RepairInputs.read(*self.state.view(sid, info))
        with self._lock:
            self._repair[key] = inputs
            while len(self._repair) > REPAIR_SCENES:
                self._repair.pop(next(iter(self._repair)))
        return inputs

    def drew(self) -> None:
        """A page drew pictures in a prepared scene: keep the cache within its bytes."""
        self.cache.trim()

    def prefetch(self, sid: str) -> None:
        """Prepare a scene in the background (not one whose folder has gone)."""
        info = self.state.info(sid)
        if not info.gone:
            self.cache.prefetch((sid, info.view), self._make(sid, info))

    def prefetch_frames(self, sid: str, at: int, step: int = 1) -> None:
        """Prepare in the background the frames of sequence ``sid`` that P (``step`` 1) or
        Shift+P (-1) would show next on a page whose window is ``at`` frames on (nothing for
        a fixed rig's scene)."""
        info = self.state.shifted(sid, at, step)
        if info is not None and not info.gone:
            self.cache.prefetch((sid, info.view), self._make(sid, info))

    def stop(self) -> None:
        """Stop serving (decisions are all on disk already)."""
        self._stop.set()
        with self._lock:
            sessions = list(self.sessions.values())
            self.sessions.clear()
        for session in sessions:
            session.close()
        self.server.stop()
        self.cache.stop()
        self._poller.join(timeout=2.0)
        with self._lock:
            later = self._give_back_later
        if later is not None:
            later.cancel()
