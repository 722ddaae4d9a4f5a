"""The Python API: the README's example runs, and the commands give what the API gives."""

from __future__ import annotations

import importlib
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import annotator

ROOT = Path(__file__).resolve().parent.parent


def _readme_example() -> str:
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Python") :]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    assert match, "README: no python block under ## Python"
    return match.group(1)


@pytest.mark.slow
def test_the_readme_example_runs(sample: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    shutil.copytree(sample, tmp_path / "sample_scenes")
    monkeypatch.chdir(tmp_path)
    exec(compile(_readme_example(), "README.md", "exec"), {})
    out = capsys.readouterr().out
    assert re.search(r"^AP \d\.\d{4}$", out, re.M)
    assert "4 scenes exported" in out
    assert (tmp_path / "sample_bop" / "models" / "models_info.json").is_file()


def _own_doc(value: object) -> str:
    """The docstring written for ``value`` itself: not a dataclass's generated signature
    (``Name(a: int, b: str)``), nor one inherited from a base class or an enum's."""
    doc = (value.__dict__.get("__doc__") if isinstance(value, type) else value.__doc__) or ""
    if isinstance(value, type) and doc.startswith(f"{value.__name__}("):
        return ""
    return doc.strip()


def test_every_public_name_is_there_and_documented() -> None:
    for name in annotator.__all__:
        value = getattr(annotator, name)
        assert getattr(value, "__module__", "").startswith("annotator"), name
        assert len(_own_doc(value)) >= 20, f"annotator.{name} has no docstring of its own"


def test_every_public_name_shows_an_example() -> None:
    """Each public class and function has a runnable example in its docstring (run by
    ``--doctest-modules``), so that a newcomer sees it used."""
    missing = [n for n in annotator.__all__ if ">>>" not in _own_doc(getattr(annotator, n))]
    assert not missing, "public names without an example: " + ", ".join(missing)


def test_one_list_of_public_names_drives_the_imports_and_the_types() -> None:
    import ast

    stub = ast.parse((ROOT / "annotator" / "__init__.pyi").read_text())
    typed = {
        alias.asname: (node.module, alias.name)
        for node in stub.body
        if isinstance(node, ast.ImportFrom)
        for alias in node.names
    }
    homes = annotator._HOMES
    assert typed == {name: (module, name) for name, module in homes.items()}  # no renaming
    assert len(homes) > 60 and annotator.__all__ == sorted(homes)
    assert set(dir(annotator)) == set(homes)
    for name, module in homes.items():  # each name is defined (or re-exported) where it says
        assert getattr(importlib.import_module(module), name) is getattr(annotator, name)
    assert (ROOT / "annotator" / "py.typed").is_file()


def test_the_names_of_an_earlier_release_still_work_with_a_warning() -> None:
    for old, new in [
        ("Settings", "AnnotateSettings"),
        ("Options", "EvaluationSettings"),
        ("SynthConfig", "SynthSettings"),
        ("ingest_scene", "ingest_recording"),
    ]:
        with pytest.warns(DeprecationWarning, match=f"annotator.{old} is now annotator.{new}"):
            assert getattr(annotator, old) is getattr(annotator, new)
    with pytest.warns(DeprecationWarning, match="annotator.FLAGS"):
        assert annotator.FLAGS == tuple(annotator.Flag)


def _cli(*args: str) -> dict:
    run = subprocess.run(
        [sys.executable, "-m", "annotator", *args], capture_output=True, text=True, check=False
    )
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


@pytest.fixture(scope="module")
def copies(sample: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    base = tmp_path_factory.mktemp("api")
    a, b = base / "cli", base / "api"
    for dst in (a, b):
        shutil.copytree(sample, dst)
        for f in dst.glob("scenes/*/annotation.json"):
            f.unlink()
    return a, b


@pytest.mark.slow
def test_annotate_cli_is_the_api(copies: tuple[Path, Path]) -> None:
    cli, api = copies
    from_cli = _cli("annotate", str(cli), "--workers", "1", "--json", "--quiet")
    from_api = annotator.annotate_dataset(annotator.load_dataset(api), workers=1).to_json()
    assert from_cli == from_api
    for f in sorted(api.glob("scenes/*/annotation.json")):
        a = json.loads((cli / f.relative_to(api)).read_text())
        b = json.loads(f.read_text())
        a.pop("created_at"), b.pop("created_at")
        assert a == b


def test_evaluate_cli_is_the_api(copies: tuple[Path, Path], tmp_path: Path) -> None:
    _, api = copies  # annotated by the test above
    if not list(api.glob("scenes/*/annotation.json")):
        annotator.annotate_dataset(annotator.load_dataset(api), workers=1)
    report = tmp_path / "report.json"
    subprocess.run(
        [sys.executable, "-m", "annotator", "evaluate", str(api), "-n", "1", "3"]
        + ["--json", str(report)],
        check=True,
        capture_output=True,
    )
    gt = annotator.read_ground_truth(api)
    results = annotator.annotations_as_results(api, gt)
    from_api = annotator.evaluate(
        gt, results, annotator.EvaluationSettings(max_results=(1, 3))
    ).to_json()
    assert json.loads(report.read_text()) == json.loads(json.dumps(from_api))


@pytest.mark.slow
def test_export_cli_is_the_api(sample: Path, tmp_path: Path) -> None:
    from_cli = _cli(
        "export",
        str(sample),
        str(tmp_path / "cli"),
        "--format",
        "bop",
        "--include-pending",
        "--cameras",
        "left",  # one camera is enough to compare, and half the work
        "--json",
    ) | {"out": ""}
    ds = annotator.load_dataset(sample)
    summary = annotator.export_dataset(
        ds, tmp_path / "api", format="bop", include_pending=True, cameras=["left"]
    )
    assert from_cli == summary.to_json() | {"out": ""}
    for f in sorted((tmp_path / "api").rglob("*.json")):
        assert f.read_bytes() == (tmp_path / "cli" / f.relative_to(tmp_path / "api")).read_bytes()
