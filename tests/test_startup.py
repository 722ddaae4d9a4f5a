"""Commands import only what they need: the heavy libraries (open3d, scipy.spatial, mujoco,
trimesh, matplotlib) cost a second of start-up, so a command that does not use them must not
import them. Each case runs the command in a fresh interpreter and lists the modules loaded
when it returns (the figures are in benchmarks/bench_startup.py, not here)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("open3d", "scipy.spatial", "mujoco", "trimesh", "matplotlib")

_PROBE = """
import json, sys
from annotator.cli import main
try:
    code = main(sys.argv[1:])
except SystemExit as stop:  # --help
    code = stop.code
print("\\n" + json.dumps({"code": code, "modules": sorted(sys.modules)}))
"""


def _loaded(*argv: str) -> tuple[int, set[str]]:
    """The exit status and the modules loaded by ``annotator ARGV`` in a fresh interpreter."""
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, *argv],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
        check=False,
    )
    doc = json.loads(out.stdout.strip().splitlines()[-1])
    return doc["code"], set(doc["modules"])


def _heavy(modules: set[str]) -> list[str]:
    return [h for h in HEAVY if h in modules or any(m.startswith(h + ".") for m in modules)]


def test_plain_check_imports_no_heavy_module() -> None:
    code, modules = _loaded("check", str(ROOT / "sample_scenes"))
    assert code == 0
    assert "open3d" not in modules
    assert _heavy(modules) == []


@pytest.mark.parametrize(
    "argv",
    [
        ("--help",),
        ("check", "--help"),
        ("annotate", "--help"),
        ("evaluate", "--help"),
        ("export", "--help"),
        ("review", "--help"),
        ("estimate", "--help"),
    ],
)
def test_help_imports_no_heavy_module(argv: tuple[str, ...]) -> None:
    code, modules = _loaded(*argv)
    assert code in (0, 2)  # argparse's --help exits 0; the bare command prints help, 2
    assert _heavy(modules) == []
