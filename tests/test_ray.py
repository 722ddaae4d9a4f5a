"""``--ray`` against a real Ray cluster on this machine (2 CPUs, its own folder and port, on
loopback), started once for the module and stopped after it, every process it started with it.

Covered: byte-identical outputs against the local runner (synth, annotate, occlusion); a
scene that raises is reported like locally and the rest is done; exceptions and dead workers
retried a bounded number of times; an interrupted run (Ctrl-C, SIGTERM) cancels its tasks and
resumes; one-line refusals.

This process joins the cluster once, so that the commands run in it share warm workers (as
a long batch does); the interrupted runs are separate processes that join and leave (with
``--ray ADDRESS`` and ``--ray auto``), as a user's commands do.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from annotator.cli import main
from annotator.dataset import load_dataset
from annotator.dataset.poses import read_pose_file
from annotator.dataset.review import Review, now_iso, poses_fingerprint, write_review
from annotator.errors import UserError
from annotator.runner.ray_cluster import run_on_ray
from devkit.local_cluster import LocalCluster, _free_port

pytestmark = [
    pytest.mark.slow,  # real Ray clusters
    pytest.mark.skipif(
        importlib.util.find_spec("ray") is None,
        reason="Ray is not installed (`make test` installs it: '.[dev,ray]')",
    ),
]

ANNOTATOR = str(Path(sys.executable).parent / "annotator")


@pytest.fixture(scope="module")
def cluster():
    """The cluster, joined by this process (whose environment is set for its drivers: Ray
    reads it when it is imported, which must not happen before)."""
    c = LocalCluster(cpus=2).start()
    try:
        with c.environ():
            assert "ray" not in sys.modules, "Ray was imported before the cluster's settings"
            import ray

            ray.init(address=c.address, logging_level="ERROR", log_to_driver=False)
            yield c
    finally:
        ray = sys.modules.get("ray")
        if ray is not None and ray.is_initialized():
            ray.shutdown()
        left = c.stop()
        assert not left, f"Ray processes survived the cluster's stop: {left}"


def _files(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def _without_created_at(data: bytes) -> dict[str, Any]:
    doc = json.loads(data)
    doc.pop("created_at")
    return doc


def _dataset(src: Path, dst: Path, scenes: int = 4) -> Path:
    """A copy of the sample without annotations, with ``scenes`` scenes (repeating the four)."""
    shutil.copytree(src, dst)
    for ann in dst.glob("scenes/*/annotation.json"):
        ann.unlink()
    for k in range(4, scenes):
        shutil.copytree(dst / "scenes" / f"{k % 4:06d}", dst / "scenes" / f"{k:06d}")
    return dst


def test_synth_writes_the_same_bytes_as_one_local_worker(cluster, tmp_path, capsys) -> None:
    args = ["--size", "320x256", "--instances", "3-4", "--scenes", "3", "--seed", "5", "--quiet"]
    assert main(["synth", str(tmp_path / "local"), *args, "--workers", "1"]) == 0
    assert main(["synth", str(tmp_path / "ray"), *args, "--ray", cluster.address]) == 0
    local, remote = _files(tmp_path / "local"), _files(tmp_path / "ray")
    assert len(local) > 10 and local.keys() == remote.keys()
    assert [k for k in local if local[k] != remote[k]] == []
    assert "3 scenes" in capsys.readouterr().out.splitlines()[-1]


def test_synth_sequences_write_the_same_bytes_as_one_local_worker(
    cluster, tmp_path, capsys
) -> None:
    """A job per scene (the drops) and then one per frame (``<scene>/<frame>``)."""
    args = ["--size", "320x256", "--instances", "3-4", "--scenes", "2", "--frames", "3"]
    args += ["--supersample", "1", "--motion-blur", "0.34", "--seed", "5", "--quiet"]
    assert main(["synth", str(tmp_path / "local"), *args, "--workers", "1"]) == 0
    assert main(["synth", str(tmp_path / "ray"), *args, "--ray", cluster.address]) == 0
    local, remote = _files(tmp_path / "local"), _files(tmp_path / "ray")
    assert "scenes/000001/frames/000002/left.png" in local and local.keys() == remote.keys()
    assert [k for k in local if local[k] != remote[k]] == []
    assert "2 sequences of 3 frames" in capsys.readouterr().out.splitlines()[-1]


def test_sequences_are_annotated_on_the_cluster_as_locally(cluster, tmp_path, capsys) -> None:
    """A sequence's three steps as tasks (frames read, the scene solved, frames seen), and
    occlusion per frame."""
    args = ["--size", "480x384", "--instances", "4-5", "--scenes", "1", "--frames", "4"]
    args += ["--supersample", "1", "--seed", "5", "--quiet"]
    assert main(["synth", str(tmp_path / "local"), *args, "--workers", "2"]) == 0
    shutil.copytree(tmp_path / "local", tmp_path / "ray")
    assert main(["annotate", str(tmp_path / "local"), "--workers", "1", "--quiet"]) == 0
    capsys.readouterr()
    assert (
        main(["annotate", str(tmp_path / "ray"), "--ray", cluster.address, "--json", "--quiet"])
        == 0
    )
    summary = json.loads(capsys.readouterr().out)
    assert summary["done"] == 1 and summary["failed"] == 0 and summary["instances_posed"] >= 3
    name = "scenes/000000/annotation.json"
    a, b = (tmp_path / "local" / name).read_bytes(), (tmp_path / "ray" / name).read_bytes()
    assert _without_created_at(a) == _without_created_at(b)
    for root in ("local", "ray"):
        flag = ["--ray", cluster.address] if root == "ray" else ["--workers", "1"]
        assert main(["occlusion", str(tmp_path / root), *flag, "--quiet"]) == 0
    name = "scenes/000000/visibility.json"
    assert (tmp_path / "local" / name).read_bytes() == (tmp_path / "ray" / name).read_bytes()


def test_twins_write_the_same_bytes_as_one_local_worker(cluster, sample_copy, tmp_path) -> None:
    """``synth --twin`` reads one dataset and writes another: the task writes into a folder
    of its own and the driver into the output folder."""
    ds = load_dataset(sample_copy)
    for scene in ds.scenes()[:2]:
        poses, _ = read_pose_file(scene.annotation_path)
        write_review(scene.review_path, Review("accepted", {}, now_iso(), poses_fingerprint(poses)))
    twin = ["synth", "--twin", str(sample_copy), "--seed", "3", "--quiet"]
    assert main([*twin[:1], str(tmp_path / "local"), *twin[1:], "--workers", "1"]) == 0
    assert main([*twin[:1], str(tmp_path / "ray"), *twin[1:], "--ray", cluster.address]) == 0
    local, remote = _files(tmp_path / "local"), _files(tmp_path / "ray")
    assert {k for k in local if k.startswith("scenes/")} == {
        f"scenes/00000{i}/{name}"
        for i in (0, 1)
        for name in ("left.png", "right.png", "depth.png", "depth_ideal.png", "gt.json")
    }
    assert local.keys() == remote.keys()
    assert [k for k in local if local[k] != remote[k] and k != ".annotator-output.json"] == []


def test_annotate_and_occlusion_write_the_same_json(cluster, sample, tmp_path, capsys) -> None:
    local = _dataset(sample, tmp_path / "local")
    remote = _dataset(sample, tmp_path / "ray")
    # A mask of an earlier run that no longer holds: deleted on the driver, as locally.
    for root in (local, remote):
        (root / "scenes" / "000002" / "unexplained.png").write_bytes(b"stale")
    assert main(["annotate", str(local), "--workers", "1", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["annotate", str(remote), "--ray", cluster.address, "--json", "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["done"] == 4 and summary["failed"] == 0 and summary["instances_posed"] > 20
    a, b = _files(local / "scenes"), _files(remote / "scenes")
    assert a.keys() == b.keys()
    for name in a:
        if name.endswith("annotation.json"):
            assert _without_created_at(a[name]) == _without_created_at(b[name]), name
        else:
            assert a[name] == b[name], name
    mask = remote / "scenes" / "000002" / "unexplained.png"
    if json.loads(b["000002/annotation.json"])["unexplained_mask"] is None:
        assert not mask.exists()
    else:
        assert mask.read_bytes().startswith(b"\x89PNG")

    assert main(["occlusion", str(local), "--workers", "1", "--quiet"]) == 0
    assert main(["occlusion", str(remote), "--ray", cluster.address, "--quiet"]) == 0
    for k in range(4):
        name = f"scenes/{k:06d}/visibility.json"
        assert (local / name).read_bytes() == (remote / name).read_bytes()


def _can_hide_folders() -> bool:
    """True if this process may make a private mount namespace (root on Linux)."""
    if shutil.which("unshare") is None:
        return False
    return subprocess.run(["unshare", "--mount", "true"], capture_output=True).returncode == 0


#: Runs the command $3... on a copy of the dataset $2 made in a tmpfs mounted on $1 in a mount
#: namespace of its own: the cluster's workers, outside it, cannot see that copy. The copy,
#: outputs included, is brought back into $2 at the end.
HIDDEN_RUN = """
mount -t tmpfs tmpfs "$1" && cp -a "$2" "$1/ds" || exit 99
hidden="$1"; shown="$2"; shift 2
"$@"; status=$?
cp -a "$hidden/ds/." "$shown/"
exit $status
"""


def test_a_failing_scene_is_reported_as_locally_and_the_rest_done(
    cluster, sample, tmp_path, capsys
) -> None:
    """The Ray run's dataset is, where this machine allows it, in a folder that the cluster's
    workers cannot see: nothing relies on a shared file system."""
    roots = {}
    for name in ("local", "ray"):
        root = roots[name] = _dataset(sample, tmp_path / name)
        (root / "scenes" / "000001" / "left.png").write_bytes(b"\x89PNG\r\n\x1a\n broken")
        (root / "scenes" / "000002" / "right.png").unlink()
    args = ["--scenes", "00000[123]", "--json"]
    assert main(["annotate", str(roots["local"]), *args, "--workers", "1"]) == 1
    a = json.loads(capsys.readouterr().out)
    if _can_hide_folders():
        hidden = tmp_path / "hidden"
        hidden.mkdir()
        driver_root = hidden / "ds"
        cmd = ["unshare", "--mount", "sh", "-c", HIDDEN_RUN, "sh", hidden, roots["ray"]]
    else:
        driver_root, cmd = roots["ray"], []
    run = subprocess.run(
        [*cmd, ANNOTATOR, "annotate", str(driver_root), *args, "--ray", cluster.address],
        env=cluster.env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 1, run.stderr
    assert not (tmp_path / "hidden" / "ds").exists()  # it was never visible out here
    b = json.loads(run.stdout)
    assert a["done"] == b["done"] == 1 and a["failed"] == b["failed"] == 2
    assert {sid: m.replace(str(roots["local"]), "ROOT") for sid, m in a["failures"].items()} == {
        sid: m.replace(str(driver_root), "ROOT") for sid, m in b["failures"].items()
    }
    assert (
        b["failures"]["000001"]
        == f"{driver_root}/scenes/000001/left.png: unreadable or corrupt image"
    )
    assert (roots["ray"] / "scenes" / "000003" / "annotation.json").exists()
    assert not (roots["ray"] / "scenes" / "000001" / "annotation.json").exists()


@dataclass(frozen=True)
class FaultyJob:
    """Writes ``scenes/<id>/out.txt``; scene ``raises`` raises a RuntimeError every time,
    ``bad`` a UserError, ``crash-once`` kills its worker process on its first attempt and
    ``crash`` on every one. Attempts are counted in ``log`` (this machine's disk: a test
    device, not something the runner relies on)."""

    root: str
    log: str

    def shared_files(self) -> list[str]:
        return []

    def scene_files(self, scene_id: str) -> list[str]:
        return [f"scenes/{scene_id}/in.txt"]

    def output_files(self, scene_id: str) -> list[str]:
        return [f"scenes/{scene_id}/out.txt"]

    def __call__(self, scene_id: str) -> dict[str, Any]:
        log = Path(self.log) / scene_id
        with open(log, "a") as f:
            f.write("x")
        attempts = len(log.read_text())
        if scene_id == "raises":
            raise RuntimeError("boom")
        if scene_id == "bad":
            raise UserError("bad input", path=Path(self.root) / "scenes" / scene_id)
        if scene_id == "crash" or (scene_id == "crash-once" and attempts == 1):
            os._exit(3)
        text = (Path(self.root) / "scenes" / scene_id / "in.txt").read_text()
        (Path(self.root) / "scenes" / scene_id / "out.txt").write_text(text.upper())
        return {"attempts": attempts}


class CountingBar:
    """Stands for the progress bar: counts its updates."""

    def __init__(self, total: int, desc: str, quiet: bool) -> None:
        self.total, self.count = total, 0
        BARS.append(self)

    def update(self, n: int = 1) -> None:
        self.count += n

    def close(self) -> None:
        pass


BARS: list[CountingBar] = []


def test_exceptions_and_dead_workers_are_retried_a_bounded_number_of_times(
    cluster, tmp_path, monkeypatch
) -> None:
    import ray

    import annotator.runner.ray_cluster as ray_runner

    monkeypatch.setattr(ray_runner, "progress_bar", CountingBar)

    # Classes of a test module are not importable on the workers: ship this one by value.
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    root, log = tmp_path / "ds", tmp_path / "log"
    log.mkdir()
    ids = ["ok", "raises", "bad", "crash-once", "crash"]
    for sid in ids:
        (root / "scenes" / sid).mkdir(parents=True)
        (root / "scenes" / sid / "in.txt").write_text(f"input of {sid}")
    job = FaultyJob(str(root), str(log))
    report = run_on_ray(job, ids, address=cluster.address, quiet=True, retries=2)
    assert sorted(report.done) == ["crash-once", "ok"]
    assert report.done["crash-once"] == {"attempts": 2}
    assert (root / "scenes" / "crash-once" / "out.txt").read_text() == "INPUT OF CRASH-ONCE"
    assert report.failed["raises"].startswith("RuntimeError: boom (at ")
    assert report.failed["raises"].endswith("(3 attempts)")
    assert report.failed["bad"] == f"{root}/scenes/bad: bad input"  # the driver's path, once
    assert "WorkerCrashedError" in report.failed["crash"]
    attempts = {sid: len((log / sid).read_text()) for sid in ids}
    assert attempts == {"ok": 1, "raises": 3, "bad": 1, "crash-once": 2, "crash": 3}
    assert not (root / "scenes" / "raises" / "out.txt").exists()
    # The progress bar counted each scene once, when it finished, as the local runner does.
    assert [(bar.total, bar.count) for bar in BARS] == [(5, 5)]


def _run_until(cmd: list[str], env: dict[str, str], ready, timeout: float = 60.0):
    # SIGINT as a terminal gives it: a pytest-xdist worker ignores SIGINT, and an ignored
    # signal stays ignored in its children (the run would then never see its Ctrl-C).
    proc = subprocess.Popen(
        cmd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + timeout
    while not ready() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    return proc


def test_an_interrupted_run_cancels_its_tasks_and_resumes(cluster, sample, tmp_path) -> None:
    import ray

    # Enough scenes that the signal lands before the run ends even when the machine is busy
    # and this loop gets the CPU late (8 could all be written before it looked again).
    scenes = 24
    root = _dataset(sample, tmp_path / "ds", scenes=scenes)
    cmd = [ANNOTATOR, "annotate", str(root), "--quiet", "--ray"]

    def annotated() -> int:
        return len(list(root.glob("scenes/*/annotation.json")))

    # Ctrl-C after the first scene, then SIGTERM after one more (this run finds the cluster
    # with `auto`, through RAY_ADDRESS, as after `ray start`).
    seen = 0
    for sig, status, word, address, env in (
        (signal.SIGINT, 130, "interrupted", cluster.address, cluster.env),
        (
            signal.SIGTERM,
            143,
            "terminated",
            "auto",
            {**cluster.env, "RAY_ADDRESS": cluster.address},
        ),
    ):
        before = annotated()
        proc = _run_until([*cmd, address], env, lambda b=before: annotated() > b)
        try:
            proc.send_signal(sig)
            out, err = proc.communicate(timeout=30)
        finally:
            proc.kill()
        assert proc.returncode == status, err
        assert err.strip().splitlines()[-1] == f"annotator: {word}", err
        seen = annotated()
        assert before < seen < scenes
        # Its tasks were cancelled: the cluster's CPUs are free again at once.
        deadline = time.monotonic() + 5
        while ray.available_resources().get("CPU", 0) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert ray.available_resources().get("CPU", 0) == 2
    done = subprocess.run(
        [*cmd, cluster.address, "--json"], env=cluster.env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["skipped"] == seen and summary["done"] == scenes - seen
    assert annotated() == scenes


def test_refusals_are_one_line(cluster, sample_copy, tmp_path, capsys, monkeypatch) -> None:
    nobody = f"127.0.0.1:{_free_port()}"
    run = subprocess.run(
        [ANNOTATOR, "annotate", str(sample_copy), "--force", "--ray", nobody],
        env=cluster.env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 2
    assert run.stderr.splitlines() == [
        f"annotator: error: cannot reach the Ray cluster at {nobody} (--ray {nobody}): "
        "Connection refused"
    ]
    assert main(["synth", str(tmp_path / "c"), "--calibration", "--ray", "auto"]) == 2
    assert "--ray does not apply" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "ray", None)  # as if Ray were not installed
    assert main(["occlusion", str(sample_copy), "--ray", "auto"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "annotator: error: --ray needs Ray, which is not installed: "
        "pip install 'bin-annotator[ray]'"
    ]


def test_a_cluster_without_cpus_is_given_up_with_the_unfinished_scenes_listed(
    sample, tmp_path
) -> None:
    """A head node with no CPU and no worker (as when the only worker node died): the run
    says so at once, waits --ray-wait seconds, then lists every scene as not run, exit 1."""
    root = _dataset(sample, tmp_path / "ds", scenes=5)
    with LocalCluster(cpus=0) as empty:
        started = time.monotonic()
        run = subprocess.run(
            [
                ANNOTATOR,
                "annotate",
                str(root),
                "--quiet",
                "--ray",
                empty.address,
                "--ray-wait",
                "3",
            ],
            env=empty.env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        took = time.monotonic() - started
    assert run.returncode == 1, run.stderr
    lines = run.stderr.strip().splitlines()
    assert lines[0].startswith(f"warning: the Ray cluster at {empty.address} has 0 CPUs")
    failed = [line for line in lines if line.startswith("failed: scene ")]
    assert len(failed) == 5 and all("had no CPU for its tasks for 3 s" in f for f in failed)
    assert "Traceback" not in run.stderr
    assert took < 60
    assert not list(root.glob("scenes/*/annotation.json"))


def test_estimate_gives_the_same_results_on_the_cluster(cluster, sample, tmp_path, capsys) -> None:
    """The results travel back as the task's value: the CSV is the one a local run writes
    (the time column aside)."""

    def rows(path: Path) -> list[list[str]]:
        return [line.split(",")[:-1] for line in path.read_text().splitlines()]

    local, remote = tmp_path / "local.csv", tmp_path / "remote.csv"
    base = ["estimate", str(sample), "--scenes", "00000[01]", "--quiet"]
    assert main([*base, str(local), "--workers", "1"]) == 0
    assert main([*base, str(remote), "--ray", cluster.address]) == 0, capsys.readouterr().err
    assert len(rows(local)) > 1 and rows(local) == rows(remote)
