"""The annotator run as a user runs it (a whole process), and the pose errors of what it wrote.

For benchmarks that time commands and score their output against the truth of synthetic
scenes.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from annotator.dataset import load_dataset, read_poses
from annotator.evaluation.evaluate import per_instance_errors

#: The ``annotator`` command of this interpreter's environment.
EXE = str(Path(sys.executable).with_name("annotator"))


def run_annotator(*args: str, env: Mapping[str, str] | None = None) -> tuple[float, str]:
    """Run ``annotator ARGS`` (with the environment ``env``, e.g. :func:`code_at`'s): its
    wall time (s) and standard output; exit on a failure, printing its standard error."""
    t0 = time.perf_counter()
    proc = subprocess.run([EXE, *args], capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        sys.exit(f"annotator {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr}")
    return time.perf_counter() - t0, proc.stdout


@contextmanager
def code_at(rev: str) -> Iterator[dict[str, str]]:
    """An environment in which ``annotator`` is the package as commit ``rev`` of this
    repository had it (a detached git worktree, removed on leaving), the installed
    dependencies unchanged: to run the code an issue was measured on side by side with
    today's, on the same scenes."""
    repo = Path(__file__).resolve().parent.parent
    with tempfile.TemporaryDirectory(prefix="anchor-") as scratch:
        tree, shim = Path(scratch) / "tree", Path(scratch) / "path"
        git = ["git", "-C", str(repo), "worktree"]
        made = subprocess.run([*git, "add", "--detach", str(tree), rev], capture_output=True)
        if made.returncode != 0:
            sys.exit(f"{rev}: not a commit of {repo} ({made.stderr.decode().strip()})")
        try:
            shim.mkdir()
            (shim / "annotator").symlink_to(tree / "annotator")
            yield {**os.environ, "PYTHONPATH": str(shim)}
        finally:
            subprocess.run([*git, "remove", "--force", str(tree)], capture_output=True)


def relative_errors(root: Path) -> tuple[list[dict], np.ndarray, np.ndarray]:
    """Each annotated instance's row (:func:`per_instance_errors`), its error in % of the
    object's diameter, and whether it carries a flag."""
    errors = per_instance_errors(root)
    rel = np.array([e["error_mm"] / e["diameter_mm"] * 100 for e in errors])
    flagged = np.array([bool(e["flags"]) for e in errors])
    return errors, rel, flagged


def posed_of_visible(root: Path, errors: list[dict]) -> tuple[int, int]:
    """How many of the parts at most half hidden (in the truth) have a pose in ``errors``,
    and how many there are."""
    visible = posed = 0
    for sc in load_dataset(root).scenes():
        have = {e["instance"] for e in errors if e["scene"] == sc.id}
        for p in read_poses(sc.gt_path):
            if p.extra["occlusion"]["rate"] <= 0.5:
                visible += 1
                posed += p.key in have
    return posed, visible
