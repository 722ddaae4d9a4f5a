"""``annotator review`` in a child process, for the tests and benchmarks that need a server
of their own (its memory, its log, its exit status): started on 127.0.0.1 at a free port,
waited for until it prints its address, its resident memory read from ``/proc`` (Linux), and
stopped with SIGTERM, then killed if it is still there, within bounded times.
:func:`free_port` picks the port.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

#: Bounds on the server's start-up (loading the dataset, importing viser and open3d) and stop.
START_SECONDS = 60.0
STOP_SECONDS = 10.0


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now (the server's, unless
    another process takes it first: tests and benchmarks only)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ReviewProcess:
    """``annotator review DATASET --port PORT`` running in a child process; a context
    manager that stops it on leaving."""

    def __init__(self, dataset: str | Path, *args: str, port: int | None = None) -> None:
        self.port = port if port is not None else free_port()
        self.argv = [
            sys.executable,
            "-m",
            "annotator",
            "review",
            str(dataset),
            "--port",
            str(self.port),
            *args,
        ]
        self.proc: subprocess.Popen[str] | None = None
        self.out: list[str] = []  # its stdout and stderr lines, as they come
        self._reader: threading.Thread | None = None
        self._lock = threading.Lock()

    def start(self, timeout: float = START_SECONDS) -> ReviewProcess:
        """Start it and wait until it serves (it has printed its address)."""
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen(
            self.argv,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
        )
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        end = time.monotonic() + timeout
        while not any(line.startswith("review:") and " at http" in line for line in self.lines()):
            if self.proc.poll() is not None:
                raise RuntimeError(f"the server exited ({self.proc.returncode}): {self.lines()}")
            if time.monotonic() > end:
                self.stop()
                raise RuntimeError(f"the server did not start within {timeout:.0f} s")
            time.sleep(0.05)
        return self

    def _read(self) -> None:
        assert self.proc is not None and self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._lock:
                self.out.append(line.rstrip("\n"))

    def lines(self) -> list[str]:
        with self._lock:
            return list(self.out)

    def rss_bytes(self) -> int:
        """Its resident memory now (VmRSS)."""
        assert self.proc is not None
        with open(f"/proc/{self.proc.pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
        raise RuntimeError("no VmRSS in /proc")

    def stop(self, timeout: float = STOP_SECONDS) -> int | None:
        """SIGTERM, then SIGKILL after ``timeout``; its exit status."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout)
        if self._reader is not None:
            self._reader.join(timeout)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        return self.proc.returncode

    def __enter__(self) -> ReviewProcess:
        return self.start() if self.proc is None else self

    def __exit__(self, *exc: object) -> None:
        self.stop()
