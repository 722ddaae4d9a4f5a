"""Bad input and faults: nothing lost, nothing hung, nothing wrong accepted.

Each test first sets up the situation that went wrong before, then checks what the user sees.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from annotator.cli import main
from annotator.dataset import load_dataset, read_poses
from annotator.dataset.review import Review, now_iso, poses_fingerprint, write_review
from annotator.io.atomic import atomic_folder, write_json


def _tree_digest(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        h.update(str(p.relative_to(root)).encode())
        if p.is_file():
            h.update(p.read_bytes())
    return h.hexdigest()


def _accept_all(root: Path, count: int | None = None) -> None:
    """Accept the first ``count`` scenes (all by default): exports take only those."""
    for sc in load_dataset(root).scenes()[:count]:
        fp = poses_fingerprint(read_poses(sc.annotation_path))
        write_review(sc.review_path, Review("accepted", {}, now_iso(), fp))


# ------------------------------------------------------------------------ 1. export safety


def test_refused_exports_leave_the_dataset_intact(sample_copy, tmp_path, capsys) -> None:
    _accept_all(sample_copy)
    before = _tree_digest(sample_copy)
    parent = sample_copy.parent
    cases = [
        (sample_copy, "is the input"),
        (sample_copy / "scenes", "lies inside the input"),
        (sample_copy / "new_export", "lies inside the input"),
        (parent, "contains the input"),
    ]
    for out, message in cases:
        for extra in ([], ["--overwrite"], ["--overwrite", "--include-pending"]):
            code = main(["export", str(sample_copy), str(out), "--format", "bop", *extra])
            err = capsys.readouterr().err.strip()
            assert code == 2 and message in err and len(err.splitlines()) == 1, (out, extra, err)
    assert _tree_digest(sample_copy) == before


@pytest.mark.slow
def test_overwrite_replaces_only_an_earlier_export(sample_copy, tmp_path, capsys) -> None:
    _accept_all(sample_copy, 1)
    foreign = tmp_path / "precious"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("years of work")
    code = main(["export", str(sample_copy), str(foreign), "--format", "bop", "--overwrite"])
    err = capsys.readouterr().err
    assert code == 2 and "no .annotator-output.json" in err
    assert (foreign / "thesis.tex").read_text() == "years of work"
    out = tmp_path / "bop"
    args = ["export", str(sample_copy), str(out), "--format", "bop", "--quiet"]
    assert main(args) == 0
    assert (
        json.loads((out / ".annotator-output.json").read_text())["written_by"] == "annotator export"
    )
    assert main(args) == 2  # not empty, no --overwrite
    assert main(args + ["--overwrite"]) == 0
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".bop.")]


@pytest.mark.slow
def test_interrupted_export_leaves_out_as_it_was(
    sample_copy, tmp_path, monkeypatch, capsys
) -> None:
    import annotator.export.bop as images  # the export's own write_png

    _accept_all(sample_copy)
    out = tmp_path / "bop"
    assert main(["export", str(sample_copy), str(out), "--format", "bop", "--quiet"]) == 0
    before = _tree_digest(out)
    calls = {"n": 0}
    real = images.write_png

    def flaky(path, img):
        calls["n"] += 1
        if calls["n"] == 5:
            raise KeyboardInterrupt
        real(path, img)

    monkeypatch.setattr(images, "write_png", flaky)
    code = main(["export", str(sample_copy), str(out), "--format", "bop", "--overwrite"])
    assert code == 130 and calls["n"] == 5
    assert _tree_digest(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bop", "ds"]


def _killed_while_building(out: Path) -> None:
    """Run atomic_folder(out) in another process and kill -9 it in the middle of the build."""
    code = (
        "import sys, time\n"
        "from annotator.io.atomic import atomic_folder\n"
        "with atomic_folder(sys.argv[1]) as tmp:\n"
        "    (tmp / 'half.png').write_bytes(b'x')\n"
        "    print('building', flush=True)\n"
        "    time.sleep(60)\n"
    )
    with subprocess.Popen([sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE) as proc:
        try:
            assert proc.stdout is not None and proc.stdout.readline() == b"building\n"
        finally:
            proc.kill()


def test_abandoned_temporary_folders_are_removed(tmp_path) -> None:
    out = tmp_path / "out"
    _killed_while_building(out)
    (stale,) = [p for p in tmp_path.iterdir() if p.name.startswith(".out.")]
    with atomic_folder(out) as tmp:
        (tmp / "f").write_text("ok")
        # A folder being built by another live process is left alone.
        with atomic_folder(tmp_path / "other") as _:
            pass
    assert not stale.exists() and (out / "f").read_text() == "ok"
    assert not (out / ".annotator-temporary").exists()


@pytest.mark.slow
def test_folders_named_like_ours_are_never_removed_or_renamed(sample_copy, tmp_path) -> None:
    """``.bop.backup`` and ``.bop.old.1`` are the user's: no export touches them."""
    _accept_all(sample_copy, 1)
    d = tmp_path / "d"
    for name in (".bop.backup", ".bop.old.1", ".bop.abc123"):
        (d / name).mkdir(parents=True)
        (d / name / "notes.txt").write_text(name)
    for _ in range(2):
        assert (
            main(
                [
                    "export",
                    str(sample_copy),
                    str(d / "bop"),
                    "--format",
                    "bop",
                    "--quiet",
                    "--overwrite",
                ]
            )
            == 0
        )
        assert sorted(p.name for p in d.iterdir()) == [
            ".bop.abc123",
            ".bop.backup",
            ".bop.old.1",
            "bop",
        ]
        for name in (".bop.backup", ".bop.old.1", ".bop.abc123"):
            assert (d / name / "notes.txt").read_text() == name
        assert (d / "bop" / ".annotator-output.json").exists()


def test_a_kill_between_the_two_renames_gives_the_old_folder_back(tmp_path, monkeypatch) -> None:
    """Killed after the old OUT was moved aside and before the new one took its name: the
    next run puts the old one back before anything else."""
    out = tmp_path / "out"
    with atomic_folder(out) as tmp:
        (tmp / "v").write_text("1")
    real_rename = Path.rename

    def dies_at_the_second_rename(self, target):
        if Path(target) == out:
            raise KeyboardInterrupt  # as a kill there would leave it, minus the clean-up
        return real_rename(self, target)

    monkeypatch.setattr(Path, "rename", dies_at_the_second_rename)
    import annotator.io.atomic as atomic

    monkeypatch.setattr(atomic.shutil, "rmtree", lambda *a, **k: None)  # the kill: no clean-up
    with pytest.raises(KeyboardInterrupt), atomic_folder(out) as tmp:
        (tmp / "v").write_text("2")
    monkeypatch.undo()
    assert not out.exists()
    # The folders it left are unlocked now (the descriptors were closed, as by a kill): the
    # next run, even one that fails, gives the old folder back first.
    with pytest.raises(RuntimeError), atomic_folder(out):
        raise RuntimeError("the next run fails too")
    assert (out / "v").read_text() == "1"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


@pytest.mark.slow
def test_a_symlinked_out_is_followed(sample_copy, tmp_path) -> None:
    _accept_all(sample_copy, 1)
    disk = tmp_path / "other_disk" / "bop"
    disk.mkdir(parents=True)
    link = tmp_path / "bop"
    link.symlink_to(disk)
    args = ["export", str(sample_copy), str(link), "--format", "bop", "--quiet"]
    assert main(args) == 0
    assert link.is_symlink() and (disk / "models" / "models_info.json").exists()
    assert main([*args, "--overwrite"]) == 0
    assert link.is_symlink() and (disk / ".annotator-output.json").exists()


@pytest.mark.slow
def test_unreadable_scenes_are_skipped_named_and_exit_1(sample_copy, tmp_path, capsys) -> None:
    _accept_all(sample_copy)
    scenes = load_dataset(sample_copy).scenes()
    (scenes[1].path / "left.png").write_bytes(b"\x89PNG\r\n\x1a\n broken")
    (scenes[2].path / "annotation.json").write_text("{not json")
    out = tmp_path / "bop"
    code = main(["export", str(sample_copy), str(out), "--format", "bop", "--quiet", "--json"])
    captured = capsys.readouterr()
    summary = json.loads(captured.out)
    assert code == 1 and summary["exported"] == 2
    assert set(summary["failures"]) == {scenes[1].id, scenes[2].id}
    assert "unreadable or corrupt image" in summary["failures"][scenes[1].id]
    assert len(json.loads((out / "test" / "scene_ids.json").read_text())) == 2
    assert "libpng" not in captured.err


# --------------------------------------------------------------------- 2. orphaned workers


def _children(pid: int) -> set[int]:
    out = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.add(int(stat.parent.name))
    return out


def _alive(pids: set[int]) -> set[int]:
    alive = set()
    for p in pids:
        try:
            state = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z":
            alive.add(p)
    return alive


@pytest.mark.slow  # real processes killed and waited for
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGKILL, -9)])
def test_no_worker_survives_its_parent(sample_copy, sig, code) -> None:
    scenes = sample_copy / "scenes"
    for k in range(4, 24):  # enough work for the batch to be running when the signal comes
        shutil.copytree(scenes / "000000", scenes / f"{k:06d}")
    for p in scenes.glob("*/annotation.json"):
        p.unlink()
    cmd = [sys.executable, "-m", "annotator", "annotate", str(sample_copy), "--workers", "2"]
    with subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE) as proc:
        _stop_in_the_middle(proc, sig, code)
    assert sum(1 for _ in scenes.glob("*/annotation.json")) < 24  # it really was stopped


def _stop_in_the_middle(proc: subprocess.Popen[bytes], sig: int, code: int) -> None:
    """Send ``sig`` once both workers run; the parent exits with ``code`` and takes them."""
    try:
        deadline = time.time() + 120
        workers: set[int] = set()
        while time.time() < deadline and len(workers) < 2 and proc.poll() is None:
            workers = _children(proc.pid)
            time.sleep(0.05)
        assert len(workers) == 2, "the workers never started"
        time.sleep(0.5)
        proc.send_signal(sig)
        assert proc.wait(timeout=30) == code
        time.sleep(2.0)
        assert not _alive(workers), "a worker outlived its parent"
    finally:
        if proc.poll() is None:
            proc.kill()


# ----------------------------------------------------------------------------- 4. modes


def test_files_and_folders_honour_the_umask(tmp_path) -> None:
    old = os.umask(0o022)
    try:
        write_json(tmp_path / "a.json", {"x": 1})
        assert (tmp_path / "a.json").stat().st_mode & 0o777 == 0o644
        with atomic_folder(tmp_path / "out") as tmp:
            write_json(tmp / "b.json", {})
        assert (tmp_path / "out").stat().st_mode & 0o777 == 0o755
        assert (tmp_path / "out" / "b.json").stat().st_mode & 0o777 == 0o644
        (tmp_path / "a.json").chmod(0o640)  # a replaced file keeps its mode
        write_json(tmp_path / "a.json", {"x": 2})
        assert (tmp_path / "a.json").stat().st_mode & 0o777 == 0o640
        os.umask(0o077)
        write_json(tmp_path / "c.json", {})
        assert (tmp_path / "c.json").stat().st_mode & 0o777 == 0o600
    finally:
        os.umask(old)


# ------------------------------------------------------------------- 5. up-to-date check


@pytest.mark.slow
def test_annotate_redoes_what_changed(sample_copy, capsys) -> None:
    args = [
        "annotate",
        str(sample_copy),
        "--scenes",
        "000001",
        "--workers",
        "1",
        "--json",
        "--quiet",
    ]

    def run() -> dict:
        assert main(args) == 0
        return json.loads(capsys.readouterr().out)

    # Whether the committed annotation counts as up to date depends on the checkout's file
    # times: make it so first.
    assert main(args + ["--force"]) == 0 and json.loads(capsys.readouterr().out)["done"] == 1
    assert run()["skipped"] == 1
    ann = sample_copy / "scenes" / "000001" / "annotation.json"
    ann.write_text('{"instances": [')  # corrupt
    assert run()["done"] == 1
    import trimesh

    mesh = sample_copy / "objects" / "brick" / "model.ply"
    m = trimesh.load(mesh, process=False)
    m.vertices *= 1.0005  # another mesh, in a file older than the annotation
    m.export(mesh)
    os.utime(mesh, (1, 1))
    assert run()["done"] == 1
    assert run()["skipped"] == 1


def test_a_bad_mesh_stops_annotate_before_any_scene(sample_copy, capsys) -> None:
    mesh = sample_copy / "objects" / "brick" / "model.ply"
    mesh.write_text("ply\nformat ascii 1.0\nelement vertex 0\nelement face 0\nend_header\n")
    code = main(["annotate", str(sample_copy), "--workers", "1", "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "model.ply" in err


# ------------------------------------------------------------------------- 6. small ones


def _edit_yaml(root: Path, edit) -> None:
    doc = yaml.safe_load((root / "dataset.yaml").read_text())
    edit(doc)
    (root / "dataset.yaml").write_text(yaml.safe_dump(doc))


def test_missing_K_is_called_missing_without_knock_on_lines(sample_copy, capsys) -> None:
    _edit_yaml(sample_copy, lambda d: d["rig"]["cameras"][0].pop("K"))
    assert main(["check", str(sample_copy)]) == 1
    lines = [x for x in capsys.readouterr().out.splitlines() if not x.startswith("check:")]
    assert lines == [f"{sample_copy / 'dataset.yaml'}: rig.cameras[0].K is missing"]


def test_yaml_syntax_errors_give_the_line(sample_copy, capsys) -> None:
    (sample_copy / "dataset.yaml").write_text("format: 1\nrig:\n  cameras: [a\n  b: c\n")
    assert main(["check", str(sample_copy)]) == 1
    assert "not valid YAML at line 4, column 4" in capsys.readouterr().out


def test_libpng_says_nothing_of_its_own(sample_copy, capfd) -> None:
    img = sample_copy / "scenes" / "000000" / "left.png"
    data = bytearray(img.read_bytes())
    data[5000:5100] = bytes(b ^ 0x55 for b in data[5000:5100])
    img.write_bytes(bytes(data))
    assert main(["check", str(sample_copy)]) == 1
    out, err = capfd.readouterr()
    assert "unreadable or corrupt image" in out
    assert "libpng" not in err and "WARN" not in err


def test_open_meshes_are_a_warning(sample_copy, capsys) -> None:
    import trimesh

    mesh = sample_copy / "objects" / "brick" / "model.ply"
    m = trimesh.load(mesh, process=False)
    trimesh.Trimesh(m.vertices, np.asarray(m.faces)[:-2], process=False).export(mesh)
    code = main(["check", str(sample_copy)])
    out = capsys.readouterr().out
    assert "warning: mesh is not watertight" in out and "1 warning" in out
    assert code == 0  # a warning, not a problem
