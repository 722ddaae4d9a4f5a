"""Issue 53's lost data: one writer per dataset (a second one refused naming the holder, or
waiting with --wait), a scene a reviewer decided on while ingest ran kept, no results file
of the user's replaced unasked, a killed writer's partial file named by check; and what
check now says of poses and meshes no bin can hold."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from cli_calls import one_error_line, run_cli
from test_ingest_recorders import _ros1_bag, ingest_new

from annotator.io.writer_lock import HOLDER_FILE, DatasetBusy, dataset_writer, holder_of

HOLD = """
import sys, time
from annotator.io.writer_lock import dataset_writer
with dataset_writer(sys.argv[1], command="annotator annotate"):
    print("held", flush=True)
    time.sleep(float(sys.argv[2]))
"""


@contextmanager
def _holder(root: Path, seconds: float) -> Iterator[subprocess.Popen]:
    """Another process holding ``root``'s writer lock for ``seconds`` (killed at the end)."""
    p = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(root), str(seconds)], stdout=subprocess.PIPE, text=True
    )
    assert p.stdout is not None
    try:
        assert p.stdout.readline().strip() == "held"
        yield p
    finally:
        p.kill()
        p.wait()
        p.stdout.close()


def test_a_second_writer_is_refused_naming_the_holder(sample_copy: Path, capsys) -> None:
    with _holder(sample_copy, 30) as holder:
        for command in (["annotate"], ["occlusion"], ["sites", "--dry-run"]):
            line = one_error_line([*command, str(sample_copy), "--quiet"], capsys)
            assert f"{sample_copy}: is being written by `annotator annotate` (pid " in line
            assert f"pid {holder.pid} " in line and "--wait" in line
        assert not (sample_copy / "scenes" / "000000" / "visibility.json").exists()
    # The kernel dropped the lock with the process; its description is stale, not a lock.
    code, _, err = run_cli(["annotate", str(sample_copy), "--quiet"], capsys)
    assert code == 0, err
    assert not (sample_copy / HOLDER_FILE).exists()


def test_wait_starts_when_the_holder_is_done(sample_copy: Path, capsys) -> None:
    with _holder(sample_copy, 1.5) as holder:
        t0 = time.monotonic()
        code, _, err = run_cli(["annotate", str(sample_copy), "--quiet", "--wait"], capsys)
        assert code == 0, err
        assert "waiting for `annotator annotate`" in err and time.monotonic() - t0 > 0.5
        assert holder.poll() is not None  # it had finished


def test_two_ingests_at_once_one_writes_and_the_other_is_told(tmp_path: Path) -> None:
    bag = _ros1_bag(tmp_path / "a.bag", n=30)
    ds = tmp_path / "ds"
    cmd = [sys.executable, "-m", "annotator", "ingest", str(ds), str(bag), "--scene", "s"]
    procs = [
        subprocess.Popen(
            [*cmd, "--rig-from-source", "--quiet"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]
    outcomes = sorted((p.returncode, err) for p in procs for _, err in [p.communicate()])
    (ok, _), (refused, err) = outcomes
    assert ok == 0 and refused == 2
    assert "is being written by `annotator ingest`" in err or "the scene exists" in err
    assert len(list((ds / "scenes" / "s" / "frames").iterdir())) == 30
    assert (ds / "dataset.yaml").is_file()


def test_the_lock_is_reentrant_and_refuses_a_second_process(tmp_path: Path) -> None:
    root = tmp_path / "new" / "ds"
    with dataset_writer(root, command="annotator ingest"):
        with dataset_writer(root, command="annotator ingest"):  # the same process again
            assert "annotator ingest" in holder_of(root)
        code = subprocess.run(
            [sys.executable, "-c", HOLD, str(root), "0"], capture_output=True, text=True
        )
        assert code.returncode == 1 and "DatasetBusy" in code.stderr
    assert not (tmp_path / "new").exists()  # the folders it made, left empty, are removed
    root.mkdir(parents=True)
    with _holder(root, 30), pytest.raises(DatasetBusy, match="written by `annotator annotate`"):
        with dataset_writer(root, command="annotator sites"):
            pass


def test_a_scene_reviewed_while_ingest_runs_is_kept(tmp_path: Path, capsys, monkeypatch) -> None:
    bag = _ros1_bag(tmp_path / "a.bag")
    ds = tmp_path / "ds"
    ingest_new(ds, bag, capsys)
    scene = ds / "scenes" / "s"
    import annotator.ingest.scene as ingest_scene

    real = ingest_scene._write_frames

    def reviewer_decides_meanwhile(*args, **kwargs):
        out = real(*args, **kwargs)
        (scene / "review.json").write_text('{"status": "accepted"}')
        return out

    monkeypatch.setattr(ingest_scene, "_write_frames", reviewer_decides_meanwhile)
    args = ["ingest", str(ds), str(bag), "--scene", "s", "--overwrite", "--quiet"]
    assert "holds a reviewer's decisions" in one_error_line(args, capsys)
    assert json.loads((scene / "review.json").read_text()) == {"status": "accepted"}
    assert len(list((scene / "frames").iterdir())) == 6
    assert [p.name for p in (ds / "scenes").iterdir()] == ["s"]  # no temporary folder left


def test_estimate_never_writes_over_a_results_file(tmp_path: Path, capsys) -> None:
    from annotator import SynthSettings, synthesize_scenes

    ds = tmp_path / "synth"
    synthesize_scenes(
        ds, SynthSettings(parts=("brick",), scenes=1, instances=(2, 2), size=(160, 128))
    )
    out = tmp_path / "ppf.csv"
    (tmp_path / "ppf.json").write_text("[] mine")
    line = one_error_line(["estimate", str(ds), str(out), "--quiet"], capsys)
    assert "ppf.json: OUT's COCO exists already (pass --overwrite" in line
    assert (tmp_path / "ppf.json").read_text() == "[] mine" and not out.exists()
    code, stdout, err = run_cli(["estimate", str(ds), str(out), "--quiet", "--overwrite"], capsys)
    assert code == 0, err
    assert f"COCO boxes and masks: {tmp_path / 'ppf.json'}" in stdout
    assert json.loads((tmp_path / "ppf.json").read_text()) != []
    line = one_error_line(["evaluate", str(ds), "--json", str(out)], capsys)
    assert "--json exists already (pass --overwrite" in line


KILLED_WRITER = """
import sys, time
from pathlib import Path
import annotator.io.atomic as atomic
def stall(fd):
    print("writing", flush=True)
    time.sleep(60)
atomic.os.fsync = stall
atomic.write_json(Path(sys.argv[1]), {"instances": []})
"""


def test_a_writer_killed_mid_write_leaves_a_file_check_names(sample_copy: Path, capsys) -> None:
    target = sample_copy / "scenes" / "000000" / "annotation.json"
    before = target.read_bytes()
    p = subprocess.Popen(
        [sys.executable, "-c", KILLED_WRITER, str(target)], stdout=subprocess.PIPE, text=True
    )
    assert p.stdout is not None and p.stdout.readline().strip() == "writing"
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    p.stdout.close()
    assert target.read_bytes() == before
    (partial,) = [q for q in target.parent.iterdir() if q.name.startswith(".annotation.json.")]
    (sample_copy / "scenes" / ".000001.x1y2z3").mkdir()  # a folder a killed ingest left
    (sample_copy / "scenes" / ".000001.x1y2z3" / ".annotator-temporary").write_text("")
    code, out, _ = run_cli(["check", str(sample_copy)], capsys)
    assert code == 0
    assert f"{partial}: warning: a partial file left by a command killed while writing it" in out
    assert ".000001.x1y2z3: warning: a partial folder left by a command killed" in out


def test_two_instances_at_one_place_are_a_problem(sample_copy: Path, capsys) -> None:
    path = sample_copy / "scenes" / "000000" / "gt.json"
    doc = json.loads(path.read_text())
    a, b = [i for i in doc["instances"] if i["object"] == "cylinder"][:2]
    b["cam_R_m2c"], b["cam_t_m2c"] = a["cam_R_m2c"], a["cam_t_m2c"]
    path.write_text(json.dumps(doc))
    code, out, _ = run_cli(["check", str(sample_copy)], capsys)
    assert code == 1
    assert f"'cylinder/{a['instance']}' and 'cylinder/{b['instance']}' are at the same place" in out


def test_a_mesh_with_no_volume_is_one_line_for_the_physics(sample_copy: Path, capsys) -> None:
    import trimesh

    ply = sample_copy / "objects" / "brick" / "model.ply"
    mesh = trimesh.load(ply)
    flat = mesh.vertices.copy()
    flat[:, 2] = 0.0
    mesh.vertices = flat
    mesh.export(ply)
    line = one_error_line(["check", str(sample_copy), "--physics", "--poses", "gt"], capsys)
    assert f"{ply}: the mesh has no volume" in line
    _, out, _ = run_cli(["check", str(sample_copy)], capsys)
    assert f"{ply}: warning: mesh has no volume" in out


@pytest.mark.parametrize("command", ["annotate", "occlusion", "sites", "ingest", "calibrate"])
def test_every_writer_documents_wait(command: str, capsys) -> None:
    from annotator.cli import main

    with pytest.raises(SystemExit):
        main([command, "--help"])
    assert "--wait" in capsys.readouterr().out


def test_a_file_given_as_the_dataset_is_one_line(sample_copy: Path, capsys) -> None:
    target = sample_copy / "dataset.yaml"
    line = one_error_line(["annotate", str(target), "--quiet"], capsys)
    assert line == f"annotator: error: {target}: is a file, not a dataset folder"
