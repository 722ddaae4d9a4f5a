"""Shared fixtures: copies of the committed sample dataset (tests never write into it), the
browser, a rendered sequence. Modules that a developer's inner loop (``make test-fast``) leaves out mark
themselves ``slow`` (``pytestmark``): Ray clusters, calibration captures, sites measured over
many scenes, real browsers."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from annotator.cli import main

SAMPLE = Path(__file__).resolve().parent.parent / "sample_scenes"


@pytest.fixture(scope="session")
def bop_export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The sample exported to BOP as bop_toolkit was run on it (true poses, the left camera),
    read-only."""
    out = tmp_path_factory.mktemp("bop") / "bop"
    subprocess.run(
        [sys.executable, "-m", "annotator", "export", str(SAMPLE), str(out), "--format", "bop"]
        + ["--include-pending", "--poses", "gt", "--cameras", "left", "--quiet"],
        check=True,
        capture_output=True,
    )
    return out


@pytest.fixture(scope="session")
def bop_sensors_export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The sample exported to BOP's multi-sensor layout (``--sensors``: a sensor per rig
    camera, sensors.json), true poses, read-only."""
    out = tmp_path_factory.mktemp("bop_sensors") / "bop"
    subprocess.run(
        [sys.executable, "-m", "annotator", "export", str(SAMPLE), str(out), "--format", "bop"]
        + ["--include-pending", "--poses", "gt", "--sensors", "--quiet"],
        check=True,
    )
    return out


@pytest.fixture()
def sample_copy(tmp_path: Path) -> Path:
    """A private copy of sample_scenes/ (images, depth, gt.json, annotation.json)."""
    dst = tmp_path / "ds"
    shutil.copytree(SAMPLE, dst)
    return dst


@pytest.fixture(scope="session")
def sample() -> Path:
    """The committed sample dataset, read-only."""
    return SAMPLE


@pytest.fixture(scope="session")
def sequence(tmp_path_factory) -> Path:
    """A synthetic sequence of 6 frames (640x512, two cameras and depth, 4-6 parts),
    annotated; read-only (tests that write use a copy)."""
    root = tmp_path_factory.mktemp("sequence") / "ds"
    synth = ["synth", str(root), "--scenes", "1", "--frames", "6", "--size", "640x512"]
    synth += ["--supersample", "1", "--instances", "4-6", "--seed", "5", "--quiet"]
    assert main(synth) == 0
    assert main(["annotate", str(root), "--quiet"]) == 0
    return root


@pytest.fixture(scope="module")
def browser():
    """Debian's Chromium, headless, driven by Playwright (the browser tests' one browser)."""
    playwright = pytest.importorskip("playwright.sync_api")
    from devkit.headless import launch_chromium

    with playwright.sync_playwright() as pw:
        b = launch_chromium(pw)
        yield b
        b.close()
