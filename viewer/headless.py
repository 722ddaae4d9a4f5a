"""Driving the review page from headless Chromium, as the browser tests and
``benchmarks/bench_viewer.py`` do: Debian's Chromium through Playwright, against a viewer on
127.0.0.1 at a free port.
"""

from __future__ import annotations

import socket
from typing import Any

#: Debian's Chromium (``apt-get install chromium``); Playwright downloads no browser here.
CHROMIUM = "/usr/bin/chromium"
#: Headless, and quiet: nothing fetched from the network besides the page itself.
CHROMIUM_ARGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
)


def launch_chromium(playwright: Any) -> Any:
    """A headless Chromium browser from a running ``sync_playwright()`` context."""
    return playwright.chromium.launch(executable_path=CHROMIUM, args=list(CHROMIUM_ARGS))


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
