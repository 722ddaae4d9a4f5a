"""The review server's memory under hostile pages: a real ``annotator review``
(child process, on a copy of sample_scenes) and pages that are scripts speaking viser's
websocket protocol (:mod:`viewer.wire`), no token needed on 127.0.0.1.

1. One page announcing a 30000 x 30000 canvas, reading all the server sends, for
   :data:`CONNECTED_SECONDS`; then it leaves (the connection dropped, as a killed browser).
2. Five such pages that never read anything; then they leave.

For each: the server's resident memory (VmRSS) before, at its peak while the pages are
connected, and once they have left (the lowest of :data:`SETTLE_SECONDS` of samples after
the last page left). Target: after the pages leave, within 0.5 GB of before.

    .venv/bin/python -m benchmarks.bench_viewer_memory
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

from devkit.served import ReviewProcess
from devkit.wire import drop, open_page

ROOT = Path(__file__).resolve().parent.parent

SAMPLE = ROOT / "sample_scenes"
HUGE = 30000
CONNECTED_SECONDS = 12.0
SETTLE_SECONDS = 8.0
TARGET_BYTES = 0.5e9
GB = 1e9


def _settled(server: ReviewProcess, seconds: float) -> int:
    """The server's memory once it has settled: the lowest of ``seconds`` of samples (a page
    that has just left is torn down within a second or two)."""
    low = server.rss_bytes()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        time.sleep(0.25)
        low = min(low, server.rss_bytes())
    return low


def _hostile(server: ReviewProcess, pages: int, read: bool) -> tuple[int, int, int]:
    """(before, peak while connected, after) for ``pages`` pages announcing a HUGE canvas."""
    before = _settled(server, 3.0)
    conns = [open_page(server.port, width=HUGE, height=HUGE) for _ in range(pages)]
    peak = server.rss_bytes()
    end = time.monotonic() + CONNECTED_SECONDS
    try:
        while time.monotonic() < end:
            for ws in conns:
                if read:
                    try:
                        ws.recv(timeout=0.05)
                    except TimeoutError:
                        pass
            if not read:
                time.sleep(0.1)
            peak = max(peak, server.rss_bytes())
    finally:
        for ws in conns:
            drop(ws)
    return before, peak, _settled(server, SETTLE_SECONDS)


def _report(what: str, before: int, peak: int, after: int) -> None:
    held = after - before
    print(
        f"{what}: before {before / GB:.2f} GB, connected (peak) {peak / GB:.2f} GB, "
        f"after it left {after / GB:.2f} GB: {held / GB:+.2f} GB held "
        f"(target <= {TARGET_BYTES / GB:.1f} GB: ratio {max(held, 0) / TARGET_BYTES:.2f})"
    )


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        dataset = Path(tmp) / "ds"
        shutil.copytree(SAMPLE, dataset)
        with ReviewProcess(dataset) as server:
            time.sleep(2.0)  # the first scene is prepared in the background at start
            _report(
                f"review server, one page announcing {HUGE}x{HUGE} and reading",
                *_hostile(server, 1, read=True),
            )
            _report(
                f"review server, five pages announcing {HUGE}x{HUGE} that never read",
                *_hostile(server, 5, read=False),
            )
            errors = [line for line in server.lines() if "Traceback" in line]
        status = server.proc.returncode if server.proc else None
    print(f"  server log: {len(errors)} tracebacks; stopped with SIGTERM: exit status {status}")


if __name__ == "__main__":
    main()
