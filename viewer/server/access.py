"""Who may open the review page: the page writes files, so a websocket connection is
refused unless

- its ``Origin`` (sent by every browser) is the page's own address: the same host and port
  as the request's ``Host``, and that host is this machine (``localhost``, ``127.x``,
  ``::1``), the address served on, or a token is required. A web page from elsewhere that
  the reviewer happens to visit cannot drive the viewer, nor can one that renames itself to
  this machine's address (DNS rebinding) without the token;
- it carries the token (``?token=...`` on the websocket address), when one is required.

By default the server listens on 127.0.0.1 only. Listening on any other address requires a
token; the page's address then names the websocket address with the token
(:meth:`Access.page_url`), as viser's page reads it from its ``websocket`` parameter.

viser 1.1.1 has no documented hook into its websocket handshake (``process_request`` is a
closure inside its server thread, and its ``on_client_connect`` callbacks run only after the
page has sent a first camera message). :func:`install` therefore registers a connect callback
on viser's underlying ``viser.infra.WebsockServer`` (public class, reached through the
server's private ``_websock_server``) and reads the handshake request from its table of live
connections (private ``_live_connections``). That callback runs after the HTTP upgrade but
before viser sends the connection anything or reads anything from it; a refused connection
is closed at once (code 1008, policy violation) and receives no scene, no panel and no file
of the dataset (the HTML page itself is viser's static client, the same for everyone). If
those attributes are missing (another viser version) :func:`install` raises, so the server
does not run unguarded. It also removes viser's "share" handler: a share link is a public
tunnel to this server, token or not.
"""

from __future__ import annotations

import hmac
import ipaddress
import secrets
import socket
import sys
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from urllib.parse import parse_qs, quote, urlsplit

import viser

WILDCARDS = ("0.0.0.0", "::", "")
CLOSE_POLICY_VIOLATION = 1008


def is_loopback(host: str) -> bool:
    """True for addresses and names of this machine only (``localhost``, 127.0.0.0/8, ::1)."""
    h = host.strip("[]").lower()
    if h == "localhost" or h.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(h).is_loopback
    except ValueError:
        return False


def new_token() -> str:
    """A random token for the page's address (128 bits, URL-safe)."""
    return secrets.token_urlsafe(16)


def _host_port(netloc: str, default_port: int) -> tuple[str, int] | None:
    try:
        parts = urlsplit(f"//{netloc}")
        host, port = parts.hostname, parts.port
    except ValueError:
        return None
    if not host:
        return None
    return host.lower(), port if port is not None else default_port


@dataclass
class Access:
    """The rules of one server: where it listens and the token it requires (None: none)."""

    host: str
    port: int
    token: str | None = None

    def refusal(self, path: str, headers: Mapping[str, str]) -> str | None:
        """Why a websocket handshake for ``path`` with ``headers`` is refused (one line), or
        None if it may connect."""
        if self.token is not None:
            given = parse_qs(urlsplit(path).query).get("token", [""])[0]
            if not hmac.compare_digest(given.encode(), self.token.encode()):
                return "missing or wrong token: open the address printed by `annotator review`"
        origin = headers.get("Origin") or headers.get("origin")
        if origin is None:
            return None  # not a browser: nothing a web page could abuse
        parts = urlsplit(origin)
        default = 443 if parts.scheme == "https" else 80
        if parts.scheme not in ("http", "https"):
            return f"origin {origin} is not this page"
        ours = _host_port(parts.netloc, default)
        served = _host_port(headers.get("Host") or headers.get("host") or "", default)
        if ours is None or ours != served:
            return f"origin {origin} is not this page"
        if not (
            is_loopback(ours[0])
            or ours[0] == self.host.strip("[]").lower()
            or self.token is not None
        ):
            return f"origin {origin} is not this machine (a token is required for it)"
        return None

    def public_host(self) -> str:
        """The host name to print: the address served on, or this machine's name for a
        wildcard address."""
        host = socket.gethostname() if self.host in WILDCARDS else self.host
        return f"[{host}]" if ":" in host and not host.startswith("[") else host

    def page_url(self) -> str:
        """The address to open; with a token, it carries the token to the websocket."""
        base = f"http://{self.public_host()}:{self.port}"
        if self.token is None:
            return base
        ws = f"ws://{self.public_host()}:{self.port}/?token={self.token}"
        return f"{base}/?websocket={quote(ws, safe='')}"


@dataclass
class Guard:
    """The connection check installed on a server; it remembers which connections passed."""

    access: Access
    admitted: set[int] = field(default_factory=set)
    refused: list[str] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _told: set[str] = field(default_factory=set)

    def is_admitted(self, client_id: int) -> bool:
        with self._lock:
            return client_id in self.admitted

    def _refuse(self, why: str, remote: str) -> None:
        with self._lock:
            self.refused.append(why)
            first = why not in self._told
            self._told.add(why)
        if first:  # browsers retry every few seconds: say it once per reason
            print(f"review: refused a connection from {remote}: {why}", file=sys.stderr)


def install(server: viser.ViserServer, access: Access) -> Guard:
    """Check every websocket connection to ``server`` against ``access`` (see the module
    docstring for how, and why through viser's private attributes)."""
    ws = getattr(server, "_websock_server", None)
    live = getattr(ws, "_live_connections", None)
    if ws is None or not isinstance(live, dict) or not hasattr(ws, "on_client_connect"):
        raise RuntimeError(
            f"viser {viser.__version__} offers no way to check who connects; "
            "refusing to serve the review page unguarded"
        )
    guard = Guard(access)

    async def check(conn) -> None:
        raw = live.get(conn.client_id)
        request = getattr(raw, "request", None)
        why = (
            "no handshake request"
            if request is None
            else access.refusal(request.path, request.headers)
        )
        if why is None:
            with guard._lock:
                guard.admitted.add(conn.client_id)
            return
        remote = getattr(raw, "remote_address", None)
        guard._refuse(why, str(remote[0]) if remote else "?")
        if raw is not None:
            await raw.close(CLOSE_POLICY_VIOLATION, why[:120])

    ws.on_client_connect(check)
    # viser's "share" button would open a public tunnel to this server, token or not.
    try:
        from viser import _messages

        ws.unregister_handler(_messages.ShareUrlRequest)
    except (ImportError, AttributeError, AssertionError, KeyError):
        pass
    return guard
