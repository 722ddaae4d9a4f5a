"""A throwaway Ray cluster on this machine, for the tests and the benchmark.

``ray start --head`` with its own temporary folder and port, bound to the loopback address
only (nothing listens on the network), stopped by killing exactly the processes it started:
``ray stop`` would stop every Ray cluster of the machine, and this one must not touch them.

    with LocalCluster(cpus=2) as cluster:
        subprocess.run(["annotator", "annotate", ds, "--ray", cluster.address], env=cluster.env)

Drivers must run with :attr:`LocalCluster.env`, or in this process within
:meth:`LocalCluster.environ` with Ray imported only then (Ray reads it on import): with it,
Ray uses the loopback address for this machine as the cluster does.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

#: Ray's switch for single-machine clusters on loopback (its default on macOS and Windows),
#: and no usage report.
LOOPBACK_ENV = {"RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0", "RAY_USAGE_STATS_ENABLED": "0"}


@dataclass
class LocalCluster:
    """``ray start --head --num-cpus cpus`` with its files in a new temporary folder, removed
    when it stops (see the module)."""

    cpus: int
    address: str = ""
    folder: Path | None = None
    _group: int | None = field(default=None, repr=False)

    @property
    def env(self) -> dict[str, str]:
        """The environment for a driver process of this cluster."""
        return {**os.environ, **LOOPBACK_ENV}

    @contextlib.contextmanager
    def environ(self) -> Iterator[None]:
        """This process's environment set for drivers of this cluster, meanwhile."""
        saved = {k: os.environ.get(k) for k in LOOPBACK_ENV}
        os.environ.update(LOOPBACK_ENV)
        try:
            yield
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v

    def start(self, timeout: float = 120.0) -> LocalCluster:
        """Start the head node and wait until it accepts drivers."""
        # Short: Ray's socket paths inside it must fit in 107 bytes.
        self.folder = Path(tempfile.mkdtemp(prefix="raycluster-"))
        # The workers' temporary files too (TMPDIR is inherited from the node): whatever a
        # killed worker leaves goes with the folder.
        (self.folder / "tmp").mkdir()
        port = _free_port()
        log = self.folder / "ray-start.log"
        with open(log, "wb") as out:
            # A session of its own: every daemon ray start leaves behind is in the process
            # group of this command, which stop() kills.
            proc = subprocess.Popen(
                [
                    _ray_command(),
                    "start",
                    "--head",
                    f"--num-cpus={self.cpus}",
                    "--num-gpus=0",
                    f"--temp-dir={self.folder}",
                    f"--port={port}",
                    "--node-ip-address=127.0.0.1",
                    "--include-dashboard=false",
                    "--disable-usage-stats",
                ],
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                env={**self.env, "TMPDIR": str(self.folder / "tmp")},
                start_new_session=True,
            )
        self._group = proc.pid
        try:
            rc = proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.stop()
            raise RuntimeError(f"ray start did not finish in {timeout:.0f} s (see {log})") from None
        if rc != 0:
            self.stop()
            raise RuntimeError(f"ray start failed (status {rc}): {log.read_text()[-2000:]}")
        self.address = f"127.0.0.1:{port}"
        # Should the caller never reach stop() (an exception, a test run cut short), the
        # cluster still goes when this process exits normally.
        atexit.register(self.stop)
        return self

    def stop(self, grace: float = 2.0) -> list[int]:
        """Kill the cluster's processes (SIGTERM, then SIGKILL after ``grace`` seconds) and
        the workers they started; returns the pids that were still alive after that (none,
        normally)."""
        if self._group is None:
            return []
        group, self._group = self._group, None
        atexit.unregister(self.stop)
        procs = _descendants_of_group(group)
        for sig, wait in ((signal.SIGTERM, grace), (signal.SIGKILL, 2.0)):
            for pid in procs:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.kill(pid, sig)
            deadline = time.monotonic() + wait
            while True:
                procs = [p for p in procs if _alive(p)]
                if not procs or time.monotonic() > deadline:
                    break
                time.sleep(0.1)
            if not procs:
                break
        if self.folder is not None and not procs:
            shutil.rmtree(self.folder, ignore_errors=True)
        return procs

    def __enter__(self) -> LocalCluster:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _ray_command() -> str:
    """The ``ray`` script of this interpreter's environment (else the one on PATH)."""
    here = Path(sys.executable).parent / "ray"
    found = str(here) if here.exists() else shutil.which("ray")
    if found is None:
        raise RuntimeError("the `ray` command is not installed: pip install 'bin-annotator[ray]'")
    return found


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _processes() -> list[tuple[int, int, int]]:
    """(pid, parent pid, process group) of every process."""
    out = subprocess.run(
        ["ps", "-A", "-o", "pid=,ppid=,pgid="], capture_output=True, text=True, check=True
    ).stdout
    rows = []
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 3:
            rows.append((int(parts[0]), int(parts[1]), int(parts[2])))
    return rows


def _descendants_of_group(group: int) -> list[int]:
    """The processes of process group ``group`` and all their descendants (Ray's workers
    start sessions of their own, but they are the raylet's children)."""
    rows = _processes()
    found = {pid for pid, _, pgid in rows if pgid == group}
    grew = True
    while grew:
        more = {pid for pid, ppid, _ in rows if ppid in found and pid not in found}
        found |= more
        grew = bool(more)
    found.discard(os.getpid())
    return sorted(found)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    # A zombie (killed, not yet reaped by its parent) is gone for our purpose.
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return True
