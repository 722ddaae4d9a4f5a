"""P (the next frames of a sequence) in the review viewer, as a reviewer sees it: real
headless Chromium on a synthetic sequence (one moving two-camera rig, 640x512, 12 frames,
annotated), the page showing three frames side by side.

For each of 10 presses of P, 1.5 s apart (a person looks at the frames), the figure is the
time from the key event (the page's own clock) to the first frame the browser composites with
the new frames' pictures, measured as ``benchmarks/bench_viewer.py`` measures a repair key
(Chromium's screencast at 700 px, the picture area equal within JPEG noise to the frame the
page settles on and, where that differs from the frame on screen at the key, at least 3/4 of
the way there: neighbouring frames of a slow hand-held path look much alike). It also prints
the server's time in ``prepared`` (the three new frames' overlays: waiting for them when they
were not made ahead). ``--cold`` leaves out the preparing of the next frames ahead of P.

    .venv/bin/python -m benchmarks.bench_viewer_sequence [--cold]
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.bench_viewer import (
    REPAIR_FRAME_WIDTH,
    Screencast,
    review_page,
    shown_at,
)
from devkit.headless import free_port, launch_chromium
from viewer.server.app import ReviewApp

FRAMES = 12
PRESSES = 10
GAP_MS = 1500


def make_sequence(root: Path) -> Path:
    """A synthetic sequence of :data:`FRAMES` frames, annotated."""
    from annotator.cli import main

    synth = ["synth", str(root), "--scenes", "1", "--frames", str(FRAMES), "--size", "640x512"]
    synth += ["--supersample", "1", "--instances", "6-8", "--seed", "5", "--quiet"]
    assert main(synth) == 0
    assert main(["annotate", str(root), "--quiet"]) == 0
    return root


def browser_presses(app: ReviewApp) -> tuple[list[float], list[float]]:
    """Key press to the new frames on screen (ms) for each P, and the server's time to
    prepare and draw each P's pictures (ms)."""
    from playwright.sync_api import sync_playwright

    server: list[float] = []
    real = app.prepared

    def timed(*args, **kwargs):
        t0 = time.perf_counter()
        try:
            return real(*args, **kwargs)
        finally:
            server.append(1000.0 * (time.perf_counter() - t0))

    out = []
    with sync_playwright() as pw:
        browser = launch_chromium(pw)
        try:
            page = review_page(browser, app.url)
            cast = Screencast(page, REPAIR_FRAME_WIDTH)
            page.wait_for_timeout(1000)
            app.prepared = timed  # type: ignore[method-assign]
            for _ in range(PRESSES):
                page.wait_for_timeout(GAP_MS)
                session = next(iter(app.sessions.values()))
                before = session.info("000000").shown
                page.keyboard.press("p")
                end = time.monotonic() + 10
                while session.info("000000").shown == before and time.monotonic() < end:
                    page.wait_for_timeout(20)
                pressed = page.evaluate("window.__keys[window.__keys.length - 1]")
                out.append(1000.0 * (shown_at(page, cast, pressed, changes=True) - pressed))
            cast.stop()
        finally:
            browser.close()
    return out, server


def main() -> None:
    """Build the sequence, serve it, press P, print the figures."""
    cold = "--cold" in sys.argv[1:]
    with tempfile.TemporaryDirectory() as tmp:
        root = make_sequence(Path(tmp) / "seq")
        app = ReviewApp(root, host="127.0.0.1", port=free_port())
        if cold:
            app.prefetch_frames = lambda sid, at, step=1: None  # type: ignore[method-assign]
        try:
            ms, server = browser_presses(app)
        finally:
            app.stop()
    how = "not prepared ahead" if cold else "prepared ahead"
    print(f"P, key to the new frames on screen ({len(ms)} presses, {GAP_MS} ms apart, {how}):")
    print(f"  median {statistics.median(ms):.0f} ms, worst {max(ms):.0f} ms")
    print("  each: " + ", ".join(f"{m:.0f}" for m in ms))
    if server:
        print(
            f"server: prepared() median {statistics.median(server):.0f} ms, "
            f"worst {max(server):.0f} ms over {len(server)} calls"
        )


if __name__ == "__main__":
    main()
