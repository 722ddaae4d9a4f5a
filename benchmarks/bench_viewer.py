"""Scene switching in the review viewer, as a reviewer sees it: real headless Chromium
(Playwright with the system Chromium) on the sample scenes (two 1280x1024 cameras, depth),
copied into 24 scenes so that every switch goes to a scene the page has not shown yet.

For each of 20 presses of J, the figure is the time from the key event (the page's own
clock) to the first frame the browser composites with the new pictures. Frames come from
Chromium's screencast (DevTools ``Page.startScreencast``), each stamped with the time the
compositor produced it, so the cost of capturing them is not in the figure. "The new
pictures" means: the picture area of the frame (its left 60%) equals, within JPEG noise,
that of the last frame once the page has been still for 400 ms. Between presses
the script waits one second, as a person looking at the scene would, which is when the next
scenes are prepared. Targets: median <= 300 ms, worst <= 600 ms.

It also prints the server-side part of a switch.

    .venv/bin/python benchmarks/bench_viewer.py
"""

from __future__ import annotations

import base64
import shutil
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from viewer.app import ReviewApp  # noqa: E402
from viewer.headless import free_port, launch_chromium  # noqa: E402

SAMPLE = ROOT / "sample_scenes"
SWITCHES = 20
VIEWPORT = {"width": 1400, "height": 1000}
FRAME_WIDTH = 350  # screencast frames, scaled down: cheap to make, still plenty to compare
KEY_CLOCK = """
window.__keys = [];
document.addEventListener("keydown", () => window.__keys.push(Date.now() / 1000), true);
"""


class Screencast:
    """Frames the page's compositor produces, with their times (seconds since the epoch)."""

    def __init__(self, page) -> None:
        self.frames: list[tuple[float, np.ndarray]] = []
        self._lock = threading.Lock()
        self._cdp = page.context.new_cdp_session(page)
        self._cdp.on("Page.screencastFrame", self._frame)
        self._cdp.send(
            "Page.startScreencast",
            {
                "format": "jpeg",
                "quality": 80,
                "maxWidth": FRAME_WIDTH,
                "maxHeight": FRAME_WIDTH,
                "everyNthFrame": 1,
            },
        )

    def _frame(self, params: dict) -> None:
        try:  # the next frame comes once this one is acknowledged
            self._cdp.send("Page.screencastFrameAck", {"sessionId": params["sessionId"]})
        except Exception:  # the page is closing
            return
        data = np.frombuffer(base64.b64decode(params["data"]), np.uint8)
        img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE).astype(np.int16)
        with self._lock:
            self.frames.append((float(params["metadata"]["timestamp"]), img))

    def since(self, t: float) -> list[tuple[float, np.ndarray]]:
        with self._lock:
            return [f for f in self.frames if f[0] > t]

    def stop(self) -> None:
        self._cdp.send("Page.stopScreencast")


def make_dataset(dst: Path, scenes: int) -> Path:
    """The sample dataset with its scenes repeated to ``scenes`` scene folders."""
    shutil.copytree(SAMPLE, dst, ignore=shutil.ignore_patterns("review.json"))
    originals = sorted((dst / "scenes").iterdir())
    for k in range(len(originals), scenes):
        shutil.copytree(originals[k % len(originals)], dst / "scenes" / f"{k:06d}")
    return dst


def _picture_area(frame: np.ndarray) -> np.ndarray:
    """The left 60% of a frame: pictures only, whatever the panel's width."""
    return frame[:, : frame.shape[1] * 6 // 10]


def shown_at(page, cast: Screencast, pressed: float, timeout: float = 10.0) -> float:
    """Time of the first frame after ``pressed`` whose picture area is the one the page
    settles on (no new frame for 400 ms)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        # Waiting through Playwright, not time.sleep: frames arrive (and are acknowledged,
        # which lets the next one come) only while Playwright has control.
        page.wait_for_timeout(50)
        frames = cast.since(pressed)
        if frames and time.time() - frames[-1][0] > 0.4:
            final = _picture_area(frames[-1][1])
            for t, img in frames:
                if np.abs(_picture_area(img) - final).mean() < 2.0:
                    return t
    raise RuntimeError("the page did not settle within 10 s of the key")


def browser_switches(url: str) -> list[float]:
    """Key press to the new pictures on screen, in ms, for SWITCHES presses of J."""
    from playwright.sync_api import sync_playwright

    out = []
    with sync_playwright() as pw:
        browser = launch_chromium(pw)
        try:
            page = browser.new_page(viewport=VIEWPORT)
            page.add_init_script(KEY_CLOCK)
            page.goto(url)
            page.wait_for_selector("canvas", timeout=60000)
            page.get_by_text("Scene 000000").first.wait_for(timeout=60000)
            page.wait_for_timeout(3000)  # the first pictures arrive, viser's notices settle
            page.get_by_text("Scene 000000").first.click()  # keys go to the page
            cast = Screencast(page)
            page.wait_for_timeout(1000)
            for k in range(SWITCHES):
                page.wait_for_timeout(1000)  # a person looks at the scene; the next are prepared
                page.keyboard.press("j")
                page.get_by_text(f"Scene {k + 1:06d}").first.wait_for(timeout=10000)
                pressed = page.evaluate("window.__keys[window.__keys.length - 1]")
                out.append(1000.0 * (shown_at(page, cast, pressed) - pressed))
            cast.stop()
        finally:
            browser.close()
    return out


def server_switches(app: ReviewApp) -> tuple[float, list[float]]:
    """Preparing a scene cold, and the server-side work of a switch to a prepared scene
    (mosaic drawn for a 920x1000 canvas and encoded as the page gets it), in ms."""
    from viewer.mosaic import compose
    from viewer.pictures import picture_html
    from viewer.style import Look

    state = app.state
    t0 = time.perf_counter()
    app.prepared(state.ids[0], state.info(state.ids[0]))
    cold = 1000 * (time.perf_counter() - t0)
    times = []
    for sid in state.ids[1:]:
        info = state.info(sid)
        app.prefetch(sid)
        time.sleep(1.0)
        t0 = time.perf_counter()
        prep = app.prepared(sid, info)
        picture_html(compose(prep, Look.of(info), 920, 1000).image)
        times.append(1000 * (time.perf_counter() - t0))
    return cold, times


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        root = make_dataset(Path(tmp) / "ds", SWITCHES + 4)
        app = ReviewApp(root, host="127.0.0.1", port=free_port())
        try:
            times = browser_switches(app.url)
        finally:
            app.stop()
        med, worst = statistics.median(times), max(times)
        print(
            f"viewer in headless Chromium, sample scenes (2 x 1280x1024 + depth), {SWITCHES} "
            f"switches with J, key press to the new pictures on screen: median {med:.0f} ms, "
            f"worst {worst:.0f} ms (targets 300 / 600 ms: ratios {med / 300:.2f} / "
            f"{worst / 600:.2f})"
        )
        print(f"  each switch, ms: {', '.join(f'{t:.0f}' for t in times)}")
        shutil.rmtree(root)
        root = make_dataset(Path(tmp) / "ds", 6)
        app = ReviewApp(root, host="127.0.0.1", port=free_port())
        try:
            cold, server = server_switches(app)
        finally:
            app.stop()
    print(
        f"  server side: preparing a scene cold {cold:.0f} ms; a switch to a prepared scene "
        f"{', '.join(f'{t:.0f}' for t in server)} ms"
    )


if __name__ == "__main__":
    main()
