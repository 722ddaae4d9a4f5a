"""Driving the review page from headless Chromium, as the browser tests and
``benchmarks/bench_viewer.py`` do: Debian's Chromium through Playwright, against a viewer on
127.0.0.1 at a free port (:func:`free_port`, the one :mod:`devkit.served` uses too).
"""

from __future__ import annotations

from typing import Any

from devkit.served import free_port

__all__ = ["CHROMIUM", "CHROMIUM_ARGS", "free_port", "launch_chromium"]

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
