"""Who may open the review page: the Origin and token rules, real websocket handshakes
against a server on 127.0.0.1, and the command line's host/token choices."""

from __future__ import annotations

import socket
from argparse import Namespace

import pytest
import viser
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

import viewer.server.app
from annotator.cli import main
from annotator.errors import UserError
from devkit.headless import free_port
from viewer.server.access import Access, is_loopback
from viewer.server.app import ReviewApp


def test_loopback_names() -> None:
    for host in ("127.0.0.1", "127.0.0.2", "localhost", "::1", "[::1]", "app.localhost"):
        assert is_loopback(host), host
    for host in ("0.0.0.0", "::", "192.168.1.5", "example.org", ""):
        assert not is_loopback(host), host


@pytest.mark.parametrize(
    ("access", "path", "headers", "ok"),
    [
        (
            Access("127.0.0.1", 8080),
            "/",
            {"Origin": "http://127.0.0.1:8080", "Host": "127.0.0.1:8080"},
            True,
        ),
        (
            Access("127.0.0.1", 8080),
            "/",
            {"Origin": "http://localhost:8080", "Host": "localhost:8080"},
            True,
        ),
        # An ssh tunnel to another local port: the page's own address.
        (
            Access("127.0.0.1", 8080),
            "/",
            {"Origin": "http://localhost:9000", "Host": "localhost:9000"},
            True,
        ),
        (Access("127.0.0.1", 8080), "/", {"Host": "127.0.0.1:8080"}, True),  # not a browser
        # Another site the reviewer visits, another local page, DNS rebinding.
        (
            Access("127.0.0.1", 8080),
            "/",
            {"Origin": "https://evil.example", "Host": "127.0.0.1:8080"},
            False,
        ),
        (
            Access("127.0.0.1", 8080),
            "/",
            {"Origin": "http://localhost:3000", "Host": "127.0.0.1:8080"},
            False,
        ),
        (
            Access("127.0.0.1", 8080),
            "/",
            {"Origin": "http://evil.example:8080", "Host": "evil.example:8080"},
            False,
        ),
        (Access("127.0.0.1", 8080), "/", {"Origin": "null", "Host": "127.0.0.1:8080"}, False),
        # Beyond this machine: the token, and the page's own origin.
        (
            Access("0.0.0.0", 8080, "s3cret"),
            "/?token=s3cret",
            {"Origin": "http://box:8080", "Host": "box:8080"},
            True,
        ),
        (
            Access("0.0.0.0", 8080, "s3cret"),
            "/",
            {"Origin": "http://box:8080", "Host": "box:8080"},
            False,
        ),
        (
            Access("0.0.0.0", 8080, "s3cret"),
            "/?token=guess",
            {"Origin": "http://box:8080", "Host": "box:8080"},
            False,
        ),
        (
            Access("0.0.0.0", 8080, "s3cret"),
            "/?token=s3cret",
            {"Origin": "http://evil.example", "Host": "box:8080"},
            False,
        ),
        (Access("0.0.0.0", 8080, "s3cret"), "/?token=s3cret", {}, True),
    ],
)
def test_refusal_rules(access, path, headers, ok) -> None:
    why = access.refusal(path, headers)
    assert (why is None) == ok, why
    if why is not None:
        assert "\n" not in why


def test_page_urls_carry_the_token_to_the_websocket() -> None:
    assert Access("127.0.0.1", 8080).page_url() == "http://127.0.0.1:8080"
    url = Access("10.0.0.7", 8081, "tok").page_url()
    assert url == "http://10.0.0.7:8081/?websocket=ws%3A%2F%2F10.0.0.7%3A8081%2F%3Ftoken%3Dtok"
    assert socket.gethostname() in Access("0.0.0.0", 8080, "tok").page_url()


def _handshake(port: int, path: str = "/", origin: str | None = None) -> str:
    """``"open"`` if the server talks to this connection, else the close code."""
    with connect(
        f"ws://127.0.0.1:{port}{path}",
        subprotocols=[f"viser-v{viser.__version__}"],
        origin=origin,
        proxy=None,
        open_timeout=10,
    ) as ws:
        try:
            ws.recv(timeout=5)
        except ConnectionClosed as exc:
            return str(exc.rcvd.code if exc.rcvd else exc)
        except TimeoutError:
            return "silent"
        return "open"


def test_websocket_connections_are_checked_at_the_handshake(sample_copy) -> None:
    app = ReviewApp(sample_copy, host="127.0.0.1", port=free_port(), token="s3cret")
    try:
        port = app.port
        own = f"http://127.0.0.1:{port}"
        assert _handshake(port, "/?token=s3cret", own) == "open"
        assert _handshake(port, "/", own) == "1008"
        assert _handshake(port, "/?token=wrong", own) == "1008"
        assert _handshake(port, "/?token=s3cret", "http://evil.example") == "1008"
        assert any("token" in why for why in app.guard.refused)
    finally:
        app.stop()


def test_a_non_local_host_needs_a_token(sample_copy, monkeypatch, capsys) -> None:
    with pytest.raises(UserError, match="--host 0.0.0.0 .* give a --token"):
        ReviewApp(sample_copy, host="0.0.0.0", port=free_port())
    # From the command line a token is made up and printed (the test binds 127.0.0.1 only).
    from annotator.commands import review

    real = viewer.server.app.viser.ViserServer
    monkeypatch.setattr(
        viewer.server.app.viser,
        "ViserServer",
        lambda host, port, **kw: real(host="127.0.0.1", port=port, **kw),
    )
    app = review.start(
        Namespace(
            dataset=str(sample_copy), host="0.0.0.0", port=free_port(), token=None, scene=None
        )
    )
    try:
        out = capsys.readouterr().out
        assert app.access.token and f"token%3D{app.access.token}" in out
        assert _handshake(app.port, "/") == "1008"
    finally:
        app.stop()
    app = review.start(
        Namespace(
            dataset=str(sample_copy), host="0.0.0.0", port=free_port(), token="mine", scene=None
        )
    )
    try:
        assert app.access.token == "mine" and "token%3Dmine" in capsys.readouterr().out
    finally:
        app.stop()


def test_a_missing_dataset_or_an_address_not_of_this_machine_is_one_line(
    tmp_path, sample_copy, capsys
) -> None:
    assert main(["review", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("annotator: error:") and "\n" not in err
    # 192.0.2.1 is reserved for documentation: no machine has it.
    args = ["review", str(sample_copy), "--host", "192.0.2.1", "--token", "t"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert "--host 192.0.2.1: cannot listen" in err and "\n" not in err
