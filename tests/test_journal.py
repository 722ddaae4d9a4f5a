"""Files written together (``annotator sites``' object.yaml files) and the journal a killed
writer leaves (issue 44: faults, round five): replayed only over the files it started
from, readable on a copy that cannot be written, never through a link out of the dataset,
rolled back when the user stops the writer, and never an error because a reader finished
it first."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from annotator.cli import main
from annotator.errors import Terminated, UserError
from annotator.io import atomic
from annotator.io.atomic import WriteError


class _Killed(BaseException):
    """A kill nobody can catch (SIGKILL, the OOM killer), as far as the writer goes."""


def _paths(root: Path) -> list[Path]:
    return [root / "objects" / o / "object.yaml" for o in ("brick", "cylinder")]


def _killed_half_way(root: Path, monkeypatch, exc: BaseException) -> tuple[list[str], dict]:
    """``write_together`` of two object.yaml files stopped by ``exc`` after the first."""
    paths = _paths(root)
    before = [p.read_text() for p in paths]
    texts = {p: t + "# measured\n" for p, t in zip(paths, before)}
    real = atomic.write_text
    calls = []

    def dies_on_the_second(path, text):
        calls.append(path)
        if len(calls) == 2:  # the first file written, then stopped
            raise exc
        real(path, text)

    monkeypatch.setattr(atomic, "write_text", dies_on_the_second)
    with pytest.raises(type(exc)):
        atomic.write_together(root, texts)
    monkeypatch.setattr(atomic, "write_text", real)
    return before, texts


def test_a_killed_writers_journal_is_finished_by_the_next_reader(sample_copy, monkeypatch):
    before, texts = _killed_half_way(sample_copy, monkeypatch, _Killed())
    paths = _paths(sample_copy)
    assert [p.read_text() for p in paths] == [texts[paths[0]], before[1]]
    assert main(["check", str(sample_copy)]) == 0
    assert [p.read_text() for p in paths] == [texts[p] for p in paths]
    assert not (sample_copy / atomic.JOURNAL).exists()


def test_files_restored_and_edited_since_are_never_written_over(sample_copy, monkeypatch, capsys):
    before, texts = _killed_half_way(sample_copy, monkeypatch, _Killed())
    paths = _paths(sample_copy)
    mine = before[0] + "# my own edit\n"
    paths[0].write_text(mine)  # restored from a copy, then edited
    assert main(["check", str(sample_copy)]) == 1  # check lists it as the problem it is
    assert "has been changed since" in capsys.readouterr().out
    assert main(["evaluate", str(sample_copy)]) == 2  # the others stop with one line
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and atomic.JOURNAL in err[0], err
    assert "objects/brick/object.yaml" in err[0] and "has been changed since" in err[0]
    assert f"delete {sample_copy / atomic.JOURNAL}" in err[0]
    assert paths[0].read_text() == mine and paths[1].read_text() == before[1]  # untouched
    assert (sample_copy / atomic.JOURNAL).exists()
    (sample_copy / atomic.JOURNAL).unlink()  # as the line says: then all is read as it is
    assert main(["check", str(sample_copy)]) == 0
    assert paths[0].read_text() == mine


def test_a_copy_that_cannot_be_written_is_read_with_one_line(sample_copy, monkeypatch, capsys):
    before, texts = _killed_half_way(sample_copy, monkeypatch, _Killed())

    def refuse(path, text):
        raise WriteError("cannot write (Read-only file system)", path=path)

    monkeypatch.setattr(atomic, "write_text", refuse)
    assert main(["check", str(sample_copy)]) == 0
    err = capsys.readouterr().err
    notes = [line for line in err.splitlines() if line.startswith("annotator: warning: ")]
    assert len(notes) == 1 and atomic.JOURNAL in notes[0] and "read as they are" in notes[0]
    assert "Traceback" not in err
    assert main(["evaluate", str(sample_copy)]) == 0
    assert "journal" in capsys.readouterr().err
    assert (sample_copy / atomic.JOURNAL).exists()  # still there, for a writable copy


def test_a_journal_never_writes_through_a_link_out_of_the_dataset(sample_copy, tmp_path, capsys):
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "object.yaml").write_text("theirs\n")
    (sample_copy / "objects" / "evil").symlink_to(outside)
    journal = {"files": {"objects/evil/object.yaml": "ours\n"}, "before": {}}
    atomic.write_json(sample_copy / atomic.JOURNAL, journal)
    assert main(["evaluate", str(sample_copy)]) == 2
    err = capsys.readouterr().err.strip()
    assert "not inside the dataset" in err and len(err.splitlines()) == 1
    assert main(["check", str(sample_copy)]) == 1
    assert (outside / "object.yaml").read_text() == "theirs\n"


def test_a_writer_refuses_a_file_outside_the_dataset_in_one_line(sample_copy, tmp_path):
    with pytest.raises(UserError, match="lies outside the dataset"):
        atomic.write_together(sample_copy, {tmp_path / "x.yaml": "x"})


@pytest.mark.parametrize("stop", [Terminated, KeyboardInterrupt])
def test_a_writer_stopped_by_the_user_puts_every_file_back(sample_copy, monkeypatch, stop):
    before, _ = _killed_half_way(sample_copy, monkeypatch, stop())
    assert [p.read_text() for p in _paths(sample_copy)] == before
    assert not (sample_copy / atomic.JOURNAL).exists()  # nothing to complete later


def test_a_reader_finishing_the_journal_first_is_no_error(sample_copy, monkeypatch):
    paths = _paths(sample_copy)
    texts = {p: p.read_text() + "# measured\n" for p in paths}
    real = atomic.write_text
    monkeypatch.setattr(atomic, "JOURNAL_WAIT_S", 0.2)
    seen = []

    def with_a_reader(path, text):
        real(path, text)
        # Another process reads the dataset meanwhile: the journal is locked, so it is not
        # played under the writer's feet; then it is gone (as if that reader finished it).
        seen.append(atomic.finish_interrupted(sample_copy))
        if path == paths[-1]:
            os.unlink(sample_copy / atomic.JOURNAL)

    monkeypatch.setattr(atomic, "write_text", with_a_reader)
    atomic.write_together(sample_copy, texts)  # no "journal: cannot remove it"
    assert seen == [[], []]
    assert [p.read_text() for p in paths] == [texts[p] for p in paths]
