"""One Ray task per scene: the driver's loop, the task, and the worker's private replica.

Driver (:func:`run_on_ray`): reads the dataset description once and puts it into the object
store once (with the job); then, keeping about two tasks per cluster CPU in flight, reads each
scene's inputs, puts them into the object store and submits the scene's task; as tasks
finish (``ray.wait``), it writes their outputs atomically, records the scene as done or
failed and advances the progress bar, exactly as the local runner does.

Task (:func:`_scene_task`): unpacks the description once per worker process into a private
temporary folder (cached by its digest, so that the dataset loader and its per-process cache
work unchanged), unpacks the scene's inputs beside it, runs the job there, one thread for
OpenCV and ray casting as in a local worker, and returns the files the job wrote. The same
code as on a local run writes the same bytes.

Faults:

- a :class:`~annotator.errors.UserError` (a bad scene: missing or corrupt image, no marker)
  fails the scene at once: the same input gives the same answer anywhere;
- any other exception is tried again, up to :data:`RETRIES` more times (it may belong to the
  node: a full disk, a broken install), then reported in the same one line as locally;
- a worker process or a node that dies is retried by Ray itself (``max_retries``, the same
  bound), then reported;
- Ctrl-C and SIGTERM cancel every outstanding task (their workers are killed) before the
  command exits; the outputs already written stay, so running the command again resumes.
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import logging
import shutil
import signal
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from annotator.dataset.model import SCENES_DIR
from annotator.errors import UserError
from annotator.io.atomic import remove_if_abandoned, temporary_folder
from annotator.runner.files import (
    Bundle,
    Files,
    Outputs,
    collect,
    materialise,
    read_files,
    relative,
    write_outputs,
)
from annotator.runner.heap import keep_freed_memory
from annotator.runner.job import RAY_WAIT_S
from annotator.runner.report import BatchReport, describe_failure, progress_bar
from annotator.runner.threads import one_thread

#: Further attempts of a scene after the first (exceptions other than UserError, dead
#: workers, dead nodes).
RETRIES = 2
#: Tasks in flight per CPU of the cluster: enough that no CPU waits for the driver, few
#: enough that the scenes' inputs do not pile up in the object store.
TASKS_PER_CPU = 2
#: ``ray.wait`` returns at least this often (s), so that Ctrl-C and SIGTERM are handled
#: promptly and nodes that join during a run are put to work.
POLL_S = 0.5
#: Seconds to wait for the cluster's head to accept a connection.
CONNECT_TIMEOUT_S = 5.0

INSTALL_HINT = "pip install 'bin-annotator[ray]'"


@dataclass(frozen=True)
class TaskOutcome:
    """What a scene's task sends back: the job's result and written files, or its error
    (one line, paths as on the driver) and whether another attempt might succeed."""

    scene_id: str
    result: dict[str, Any] | None
    error: str | None
    retry: bool
    outputs: Outputs


def run_on_ray(
    job: Any,
    scene_ids: Sequence[str],
    *,
    address: str,
    desc: str = "scenes",
    quiet: bool = False,
    retries: int = RETRIES,
    wait_s: float | None = None,
) -> BatchReport:
    """Run ``job`` (a :class:`~annotator.runner.DistributableJob`) on every scene id as tasks
    of the Ray cluster at ``address`` (``"auto"``: the running one); the same report as
    :func:`annotator.runner.run_batch`, with failures after ``retries`` further attempts.

    A cluster that has no CPU for the tasks (its worker nodes died, or none joined) is
    waited for ``wait_s`` seconds (default :data:`annotator.runner.RAY_WAIT_S`), with one
    line on stderr; then the run stops and every unfinished scene is reported failed.

    Joins the cluster unless this process already has (then it stays joined, as it was), and
    not at all when there is no scene to do. Raises UserError when Ray is not installed or
    the cluster cannot be reached.
    """
    ray = import_ray()
    missing = [
        name
        for name in ("shared_files", "scene_files", "output_files")
        if not callable(getattr(job, name, None))
    ]
    is_dataclass = dataclasses.is_dataclass(job)  # (not in the if: it would narrow job's type)
    if missing or not is_dataclass:
        raise TypeError(
            f"{type(job).__name__} cannot run on Ray: it must be a dataclass with a root field "
            f"and {', '.join(missing) or 'its'} file declarations (annotator.runner.job)"
        )
    if not scene_ids:
        return BatchReport()
    shared = Bundle.read(job.root, job.shared_files())
    joined = connect(address)
    try:
        wait = RAY_WAIT_S if wait_s is None else wait_s
        return _Driver(ray, job, shared, retries, address, wait).run(scene_ids, desc, quiet)
    finally:
        if joined:
            ray.shutdown()


def import_ray() -> Any:
    """The ``ray`` module, or a UserError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise UserError(f"--ray needs Ray, which is not installed: {INSTALL_HINT}") from None
    return ray


def connect(address: str) -> bool:
    """Join the Ray cluster at ``address`` (``"auto"``, ``host:port`` or ``ray://host:port``);
    False if this process had already joined one. One-line UserError if it cannot be reached
    (checked first: Ray itself would wait for minutes)."""
    ray = import_ray()
    if ray.is_initialized():
        return False
    _check_reachable(address)
    # ray.init installs its own SIGTERM handler (sys.exit): the command's, which turns
    # SIGTERM into a clean stop with status 143, must stay in place.
    main = threading.current_thread() is threading.main_thread()
    saved = signal.getsignal(signal.SIGTERM) if main else None
    try:
        ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False)
    except Exception as exc:  # Ray's errors for a refused or incompatible cluster vary
        raise UserError(f"cannot join the Ray cluster at {address!r}: {_first_line(exc)}") from None
    finally:
        if main:
            signal.signal(signal.SIGTERM, saved)
    return True


def _check_reachable(address: str) -> None:
    if "://" in address:  # Ray Client (ray://host:port)
        hostport: str | None = address.split("://", 1)[1]
    else:
        try:
            from ray._private.services import canonicalize_bootstrap_address
        except ImportError:  # a Ray without this helper: ray.init judges alone
            return
        try:
            hostport = canonicalize_bootstrap_address(address)
        except ConnectionError:
            raise UserError(
                f"--ray {address}: no running Ray cluster found (start one with "
                "`ray start --head`, or give the head's address host:port)"
            ) from None
        except ValueError:
            raise UserError(f"--ray {address}: not an address (host:port or 'auto')") from None
        except Exception:  # a private helper of Ray's, changed: ray.init judges alone
            return
    if not hostport:
        return  # "local": ray.init starts a private instance
    host, _, port = hostport.rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), CONNECT_TIMEOUT_S):
            pass
    except ValueError:
        raise UserError(f"--ray {address}: not an address (host:port or 'auto')") from None
    except OSError as exc:
        raise UserError(
            f"cannot reach the Ray cluster at {hostport} (--ray {address}): "
            f"{exc.strerror or exc or 'no answer'}"
        ) from None


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


@dataclass
class _Attempt:
    scene_id: str
    inputs: Any  # ObjectRef of the scene's input Files
    number: int = 1


class _Starved(Exception):
    """The cluster had no CPU for the tasks for longer than the run waits."""


class _Driver:
    """The driver's side of one batch."""

    def __init__(
        self, ray: Any, job: Any, shared: Bundle, retries: int, address: str, wait_s: float
    ) -> None:
        self.ray = ray
        self.job = job
        self.retries = retries
        self.address = address
        self.wait_s = wait_s
        self.report = BatchReport()
        self.task = ray.remote(_scene_task).options(
            num_cpus=1, max_retries=retries, retry_exceptions=False
        )
        self.job_ref = ray.put(job)
        # In a list, so that Ray hands the task the reference rather than the files: a worker
        # fetches them only the first time it meets this digest.
        self.shared = (shared.digest, [ray.put(shared.files)])
        self.pending: dict[Any, _Attempt] = {}
        self._window = (0.0, 0)
        self._cpus = (float("-inf"), 0.0)
        self._starved_since: float | None = None

    def run(self, scene_ids: Sequence[str], desc: str, quiet: bool) -> BatchReport:
        todo = iter(scene_ids)
        more = True
        bar = progress_bar(len(scene_ids), desc, quiet)
        try:
            while True:
                while more and len(self.pending) < self.window():
                    sid = next(todo, None)
                    if sid is None:
                        more = False
                    elif not self.submit(sid):
                        bar.update()  # its inputs could not be read: failed already
                if not self.pending:
                    break
                done, _ = self.ray.wait(list(self.pending), num_returns=1, timeout=POLL_S)
                for ref in done:
                    if self.settle(ref):
                        bar.update()
                if not done:
                    self.watch_cpus()
        except _Starved as why:
            unfinished = [a.scene_id for a in self.pending.values()] + list(todo)
            self.cancel()
            for sid in unfinished:
                self.report.failed[sid] = f"not run: {why}"
        except BaseException:
            self.cancel()
            raise
        finally:
            bar.close()
        return self.report

    def cluster_cpus(self) -> float:
        """CPUs of the cluster (looked up again at most every POLL_S)."""
        now = time.monotonic()
        if now - self._cpus[0] >= POLL_S:
            self._cpus = (now, float(self.ray.cluster_resources().get("CPU", 0.0)))
        return self._cpus[1]

    def watch_cpus(self) -> None:
        """While no task finishes: a cluster with no CPU for a task (each needs 1) is told
        once, then given up after ``wait_s`` seconds (raises :class:`_Starved`)."""
        cpus = self.cluster_cpus()
        if cpus >= 1:
            self._starved_since = None
            return
        now = time.monotonic()
        if self._starved_since is None:
            self._starved_since = now
            print(
                f"warning: the Ray cluster at {self.address} has {cpus:g} CPUs and each task "
                f"needs 1; waiting up to {self.wait_s:g} s for a node to join (--ray-wait)",
                file=sys.stderr,
            )
        elif now - self._starved_since >= self.wait_s:
            raise _Starved(
                f"the Ray cluster at {self.address} had no CPU for its tasks for "
                f"{self.wait_s:g} s (each needs 1 CPU; the cluster has {cpus:g}: start a "
                "worker node with `ray start --address HEAD:PORT`)"
            )

    def window(self) -> int:
        """Tasks to keep in flight: TASKS_PER_CPU per CPU of the cluster (looked up again
        every few seconds: nodes may join or leave during a run)."""
        now = time.monotonic()
        if now - self._window[0] > 5.0:
            self._window = (now, max(2, int(TASKS_PER_CPU * self.cluster_cpus())))
        return self._window[1]

    def submit(self, scene_id: str) -> bool:
        """Read the scene's inputs and submit its task; False (and the scene failed) if they
        cannot be read."""
        try:
            inputs = read_files(self.job.root, self.job.scene_files(scene_id))
        except UserError as exc:
            self.report.failed[scene_id] = str(exc)
            return False
        self.start(_Attempt(scene_id, self.ray.put(inputs)))
        return True

    def start(self, attempt: _Attempt) -> None:
        ref = self.task.remote(self.job_ref, self.shared, attempt.scene_id, attempt.inputs)
        self.pending[ref] = attempt

    def settle(self, ref: Any) -> bool:
        """Take a finished task's outcome: write its files, or record its failure, or try it
        again. True when the scene is finished (done or failed)."""
        attempt = self.pending.pop(ref)
        sid = attempt.scene_id
        try:
            outcome: TaskOutcome = self.ray.get(ref)
        except self.ray.exceptions.RayError as exc:  # a dead worker or node: Ray retried it
            self.report.failed[sid] = (
                f"{type(exc).__name__} on the Ray cluster: {_first_line(exc)} "
                f"(retried up to {self.retries} times)"
            )
            return True
        if outcome.error is None:
            try:
                write_outputs(_output_root(self.job), outcome.outputs)
            except (UserError, ValueError) as exc:  # ValueError: a path out of the dataset
                self.report.failed[sid] = str(exc)
            else:
                self.report.done[sid] = outcome.result or {}
            return True
        if outcome.retry and attempt.number <= self.retries:
            self.start(dataclasses.replace(attempt, number=attempt.number + 1))
            return False
        tries = f" ({attempt.number} attempts)" if attempt.number > 1 else ""
        self.report.failed[sid] = outcome.error + tries
        return True

    def cancel(self) -> None:
        """Cancel every outstanding task, killing the workers that run one. Tasks already
        finished are left alone: force-cancelling a task as it completes can trip an internal
        check of Ray's core worker, which then ends this process."""
        refs = list(self.pending)
        finished: set[Any] = set()
        with contextlib.suppress(Exception):
            finished = set(
                self.ray.wait(refs, num_returns=len(refs), timeout=0, fetch_local=False)[0]
            )
        for ref in refs:
            if ref not in finished:
                with contextlib.suppress(Exception):
                    self.ray.cancel(ref, force=True)
        self.pending.clear()


# --- worker side --------------------------------------------------------------------------

#: This worker process's private folder (``annotator-ray-worker-*`` in the temporary folder,
#: flock-ed while the process lives), and the description replicas in it by digest, with
#: the names of their files.
_BASE: Path | None = None
_REPLICAS: dict[str, tuple[Path, frozenset[str]]] = {}
_PREFIX = "annotator-ray-worker-"


def _scene_task(
    job: Any, shared: tuple[str, list[Any]], scene_id: str, inputs: Files
) -> TaskOutcome:
    """Run ``job`` on one scene in this worker's replica; the files it wrote, as bytes.

    Errors come back as values, in the driver's terms (its dataset path, not the replica's):
    a UserError is final, anything else is worth another attempt."""
    separate = _writes_elsewhere(job)
    root: Path | None = None
    out: Path | None = None
    keep: frozenset[str] = frozenset()
    try:
        root, keep = _replica(*shared)
        out = root.parent / f"{root.name}.out" if separate else root
        if separate:  # empty: everything in it is this scene's output
            shutil.rmtree(out, ignore_errors=True)
        materialise(root, inputs)
        (root / SCENES_DIR / scene_id).mkdir(parents=True, exist_ok=True)
        changes: dict[str, str] = {"root": str(root)}
        if separate:
            changes["out"] = str(out)
        result = dataclasses.replace(job, **changes)(scene_id)
        outputs = collect(out, job.output_files(scene_id))
    except UserError as exc:
        return TaskOutcome(scene_id, None, _as_driver(str(exc), job, root, out), False, {})
    except Exception as exc:
        error = _as_driver(describe_failure(exc), job, root, out)
        return TaskOutcome(scene_id, None, error, True, {})
    finally:
        if root is not None:  # the next scene must not see this one's files
            for rel in inputs:
                if rel not in keep:
                    relative(root, rel).unlink(missing_ok=True)
            shutil.rmtree(root / SCENES_DIR, ignore_errors=True)
            if separate and out is not None:
                shutil.rmtree(out, ignore_errors=True)
    return TaskOutcome(scene_id, result, None, False, outputs)


def _writes_elsewhere(job: Any) -> bool:
    """Whether the job writes into its own ``out`` folder rather than into ``root``."""
    return any(f.name == "out" for f in dataclasses.fields(job))


def _output_root(job: Any) -> str:
    return str(job.out) if _writes_elsewhere(job) else str(job.root)


def _as_driver(message: str, job: Any, root: Path | None, out: Path | None) -> str:
    """``message`` with the task's folders named as the driver's (its dataset, its output)."""
    if out is not None and out != root:  # first: the output folder is named after the replica
        message = message.replace(str(out), str(Path(job.out)))
    return message if root is None else message.replace(str(root), str(Path(job.root)))


def _replica(digest: str, box: list[Any]) -> tuple[Path, frozenset[str]]:
    """This process's folder holding the description with ``digest`` (unpacked once), and
    the names of its files."""
    hit = _REPLICAS.get(digest)
    if hit is None:
        import ray

        if not _REPLICAS:
            one_thread()  # as in a local worker: same speed per core, same numbers
            keep_freed_memory()
        files = ray.get(box[0])
        root = _base() / digest[:16]
        shutil.rmtree(root, ignore_errors=True)
        materialise(root, files)
        hit = _REPLICAS[digest] = (root, frozenset(files))
    return hit


def _base() -> Path:
    global _BASE
    if _BASE is None:
        tmp = Path(tempfile.gettempdir())
        _sweep(tmp)
        # Made under another name and locked before it takes its final name, so that a
        # sweeping neighbour never sees it unlocked.
        folder, lock = temporary_folder(tmp, f".{_PREFIX}")
        if lock is not None:
            _LOCKS.append(lock)
        final = tmp / folder.name[1:]
        folder.rename(final)
        atexit.register(shutil.rmtree, final, True)
        _BASE = final
    return _BASE


_LOCKS: list[int] = []  # descriptors kept open for the life of the process


def _sweep(tmp: Path) -> None:
    """Remove the private folders of worker processes that died without cleaning up (their
    lock is free); the folders of live workers, on this node or in another container sharing
    the folder, stay locked and are left alone."""
    for cand in tmp.glob(f"{_PREFIX}*"):
        if cand.is_dir() and not cand.is_symlink():
            remove_if_abandoned(cand)
