"""The review server: one viser server, one shared review state and prefetch cache, and one
:class:`~viewer.session.Session` per browser page.

Each page has its own cursor, filter, selection and zoom. Decisions are shared: a decision
made in one page reaches the other pages of this server at once, and a poll of the scenes'
files (every :data:`POLL_SECONDS`) brings those of other servers on the same dataset, so the
progress bar is the same everywhere.

Connections are checked (:mod:`viewer.access`): only pages of this server, and with a token
when one is required. A server listening beyond this machine requires a token.
"""

from __future__ import annotations

import secrets
import socket
import threading
from pathlib import Path

import viser

from annotator.errors import UserError
from viewer.access import Access, Guard, install, is_loopback
from viewer.cache import PrefetchCache
from viewer.mosaic import compose
from viewer.overlays import Prepared, prepare
from viewer.session import Session
from viewer.state import ReviewState, SceneInfo
from viewer.style import Look

POLL_SECONDS = 0.5


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
    """

    def __init__(
        self,
        root: str | Path,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        token: str | None = None,
    ) -> None:
        if not is_loopback(host) and not token:
            raise UserError(
                f"--host {host} makes the page reachable from other machines, and the page "
                "writes files: give a --token"
            )
        _check_listenable(host)
        self.state = ReviewState(root)
        self.cache: PrefetchCache[Prepared] = PrefetchCache(size=6)
        self.tag = secrets.token_hex(3)  # tells this server's pages from another server's
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port = self.server.get_port()
        self.access = Access(host, self.port, token or None)
        try:
            self.guard: Guard = install(self.server, self.access)
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
        self.sessions: dict[int, Session] = {}
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
            self.sessions[client.client_id] = session

    def _disconnect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            session = self.sessions.pop(client.client_id, None)
        if session is not None:
            session.close()

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
        ds = self.state.ds

        def make() -> Prepared:
            prep = prepare(ds, ds.scene(sid), list(info.poses))
            with self._lock:
                sizes = {s.viewport for s in self.sessions.values()}
            look = Look.of(self.state.info(sid))
            for w, h in sizes:  # the mosaic for the pages' canvases, ahead of time
                compose(prep, look, w, h)
            return prep

        return make

    def prepared(self, sid: str, info: SceneInfo) -> Prepared:
        """The overlays and point cloud of a scene (waits if they are being prepared)."""
        return self.cache.get((sid, info.fingerprint), self._make(sid, info))

    def prefetch(self, sid: str) -> None:
        """Prepare a scene in the background."""
        info = self.state.info(sid)
        self.cache.prefetch((sid, info.fingerprint), self._make(sid, info))

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
