"""A seeded fuzz of every reader of outside files (issue 53): ROS bags, Azure Kinect MKVs,
Record3D exports, BOP result CSVs, COCO results, targets files and sensors.json, each
damaged many ways from a good file the test writes. Whatever the damage, the command run as
a user runs it ends within seconds, and either succeeds with a result that holds (depth that
is the recorded plane's, scores in [0, 1]) or exits non-zero with one line naming the
file: never a traceback, never a hang, never a dataset changed by a run that failed."""

from __future__ import annotations

import copy
import json
import os
import shutil
import subprocess
import sys
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from test_ingest_recorders import (
    K_KINECT_DEPTH,
    KC,
    KDH,
    KDW,
    _colour_T_depth,
    _mkv,
    _r3d,
    _ros1_bag,
    depth_frame,
    plane_depth,
)

from annotator.dataset import load_dataset

pytestmark = pytest.mark.slow  # about fifty whole processes

DATA = Path(__file__).parent / "data"
#: Past this a run counts as hung (a loaded CI machine included).
HANG_S = 30
#: Damaged variants per reader.
CASES = 7
#: The damage drawn (fixed, so that a run is repeatable; set ANNOTATOR_FUZZ_SEED to draw
#: other damage when looking for more).
SEED = int(os.environ.get("ANNOTATOR_FUZZ_SEED", "0"))
#: Values a damaged JSON or CSV field takes.
ODD = [None, -1, -7.5, 0.5, 1e308, 2**70, "x", "", [], {}, True, "NaN", [1, 2]]


def _tree(root: Path) -> dict[str, tuple[int, int]]:
    """Every file under ``root``: size and modification time (what a failed run must keep)."""
    out = {}
    for dirpath, _, files in os.walk(root):
        for f in files:
            p = Path(dirpath) / f
            st = p.stat()
            out[str(p.relative_to(root))] = (st.st_size, st.st_mtime_ns)
    return out


def _run(args: list[str], watched: Path | None) -> tuple[int, str, str]:
    """``annotator ARGS`` as a process: its exit, stdout and stderr; a failure (non-zero
    exit) must be one error line and leave ``watched`` as it was."""
    before = _tree(watched) if watched is not None and watched.exists() else None
    run = subprocess.run(
        [sys.executable, "-m", "annotator", *args],
        capture_output=True,
        text=True,
        timeout=HANG_S,
    )
    assert "Traceback" not in run.stderr, run.stderr
    if run.returncode != 0:
        errors = [ln for ln in run.stderr.splitlines() if ln.startswith("annotator: error: ")]
        others = [ln for ln in run.stderr.splitlines() if ln and not ln.startswith("annotator: ")]
        assert run.returncode in (1, 2) and len(errors) == 1 and not others, run.stderr
        if watched is not None:
            after = _tree(watched) if watched.exists() else None
            assert after == before, f"{args}: a failed run changed {watched}"
    return run.returncode, run.stdout, run.stderr


def _damaged_bytes(good: Path, out: Path, rng: np.random.Generator) -> Path:
    """``good`` with random bytes written over a stretch of it, bytes flipped here and
    there, or cut short."""
    data = bytearray(good.read_bytes())
    how = rng.integers(3)
    if how == 0:
        at = int(rng.integers(len(data) // 10, len(data)))
        n = int(rng.integers(1, max(2, len(data) // 20)))
        data[at : at + n] = rng.integers(0, 256, min(n, len(data) - at), dtype=np.uint8).tobytes()
    elif how == 1:
        for at in rng.integers(0, len(data), 30):
            data[at] ^= int(rng.integers(1, 256))
    else:
        data = data[: int(len(data) * rng.uniform(0.3, 0.95))]
    out.write_bytes(bytes(data))
    return out


def _odd(rng: np.random.Generator) -> object:
    return copy.deepcopy(ODD[int(rng.integers(len(ODD)))])


def _ingest_cases(
    tmp_path: Path, make: Callable[[Path], Path], damage: Callable, plane: np.ndarray
) -> None:
    """Ingest each damaged variant into a dataset of its own, then once more into the
    dataset the first good run made (which a failure must leave as it was)."""
    good = make(tmp_path / "good")
    shared = tmp_path / "shared"
    args = ["ingest", str(shared), str(good), "--scene", "s0", "--rig-from-source", "--quiet"]
    assert _run(args, None)[0] == 0
    lo, hi = plane[plane > 0].min() - 5, plane[plane > 0].max() + 5
    rng = np.random.default_rng(53 + SEED)
    for k in range(CASES):
        bad = damage(good, tmp_path / f"bad{k}{good.suffix}", rng)
        for ds, extra in ((tmp_path / f"new{k}", ["--rig-from-source"]), (shared, [])):
            args = ["ingest", str(ds), str(bad), "--scene", f"s{k + 1}", "--quiet", *extra]
            code, _, _ = _run(args, shared if ds == shared else None)
            if code != 0:
                continue
            loaded = load_dataset(ds)
            frames = loaded.scene(f"s{k + 1}").frames()
            assert frames
            for frame in frames:  # what was written holds: the plane, not noise
                depth = frame.read_depth(loaded.rig)
                if depth is not None and np.isfinite(depth).any():
                    ok = np.isfinite(depth)
                    assert lo <= depth[ok].min() and depth[ok].max() <= hi, (bad, frame)


def test_damaged_bags(tmp_path: Path) -> None:
    plane = plane_depth(KC, 160, 120, np.eye(4))
    _ingest_cases(tmp_path, lambda p: _ros1_bag(p.with_suffix(".bag")), _damaged_bytes, plane)


def test_damaged_kinect_recordings(tmp_path: Path) -> None:
    plane = depth_frame(_colour_T_depth(2.0, (-32.0, -2.0, 4.0)), K_KINECT_DEPTH, KDW, KDH)
    _ingest_cases(tmp_path, lambda p: _mkv(p.with_suffix(".mkv"), n=6), _damaged_bytes, plane)


def _damaged_r3d(good: Path, out: Path, rng: np.random.Generator) -> Path:
    """A Record3D export with an odd metadata value, or a frame's bytes damaged."""
    with zipfile.ZipFile(good) as z:
        items = {n: z.read(n) for n in z.namelist()}
    meta = json.loads(items["metadata"])
    if rng.random() < 0.6:
        key = sorted(meta)[int(rng.integers(len(meta)))]
        meta[key] = _odd(rng)
        items["metadata"] = json.dumps(meta).encode()
    else:
        name = sorted(n for n in items if n != "metadata")[int(rng.integers(len(items) - 1))]
        blob = bytearray(items[name])
        for at in rng.integers(0, len(blob), 20):
            blob[at] ^= 0x5A
        items[name] = bytes(blob)
    with zipfile.ZipFile(out, "w") as z:
        for name, blob in items.items():
            z.writestr(name, blob)
    return out


def test_damaged_record3d_exports(tmp_path: Path) -> None:
    kd = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    plane = plane_depth(kd, 64, 48, np.eye(4))
    _ingest_cases(tmp_path, lambda p: _r3d(p.with_suffix(".r3d")), _damaged_r3d, plane)


def _scores_hold(report: Path) -> None:
    """Every score of a successful run's ``--json`` report is finite, and every AP, AR and
    mAP lies in [0, 1] or is -1 (nothing to score)."""

    def walk(doc: object, key: str = "") -> None:
        if isinstance(doc, dict):
            for k, v in doc.items():
                walk(v, str(k))
        elif isinstance(doc, list):
            for v in doc:
                walk(v, key)
        elif isinstance(doc, float):
            assert np.isfinite(doc), (key, doc)
            if key.startswith(("AP", "AR", "bop24_mAP", "bop25_mAP")):
                assert doc == -1 or 0 <= doc <= 1, (key, doc)

    walk(json.loads(report.read_text()))


def _evaluate(args: list[str], watched: Path, report: Path) -> None:
    """``evaluate ARGS --json REPORT``; the scores of a successful run hold."""
    code, _, _ = _run([*args, "--json", str(report), "--overwrite"], watched)
    if code == 0:
        _scores_hold(report)


def _json_variants(doc: object, rng: np.random.Generator) -> str:
    """``doc`` with one value made odd, a key dropped, or its text cut short."""
    doc = copy.deepcopy(doc)
    how = rng.integers(3)
    if how == 2:
        text = json.dumps(doc)
        return text[: int(len(text) * rng.uniform(0.1, 0.95))]
    entries = doc if isinstance(doc, list) else [doc]
    entry = entries[int(rng.integers(len(entries)))]
    if isinstance(entry, dict) and entry:
        key = sorted(entry)[int(rng.integers(len(entry)))]
        if how == 0:
            entry[key] = _odd(rng)
        else:
            del entry[key]
    return json.dumps(doc)


def test_damaged_coco_results(bop_export: Path, tmp_path: Path) -> None:
    good = json.loads((DATA / "coco_results.json").read_text())
    rng = np.random.default_rng(7 + SEED)
    for k in range(CASES + 3):
        path = tmp_path / f"coco{k}.json"
        if k % 3 == 0:  # a mask's runs damaged
            doc = copy.deepcopy(good)
            seg = doc[int(rng.integers(len(doc)))]["segmentation"]
            c = list(seg["counts"])
            for at in rng.integers(0, len(c), 3):
                c[at] = chr(int(rng.integers(33, 127)))
            seg["counts"] = "".join(c)
            path.write_text(json.dumps(doc))
        else:
            path.write_text(_json_variants(good, rng))
        args = ["evaluate", str(bop_export), "--coco-results", str(path)]
        _evaluate(args, bop_export, tmp_path / "report.json")


def test_damaged_bop_results(bop_export: Path, tmp_path: Path) -> None:
    lines = (DATA / "bop24_results.csv").read_text().splitlines()
    rng = np.random.default_rng(11 + SEED)
    for k in range(CASES):
        rows = [ln.split(",") for ln in lines]
        i = int(rng.integers(1, len(rows)))
        if rng.random() < 0.8:
            rows[i][int(rng.integers(len(rows[i])))] = str(_odd(rng))
        else:
            rows[i] = rows[i][: int(rng.integers(1, len(rows[i])))]
        path = tmp_path / f"r{k}.csv"
        path.write_text("\n".join(",".join(r) for r in rows) + "\n")
        args = ["evaluate", str(bop_export), "--results", str(path), "--bop24"]
        _evaluate(args, bop_export, tmp_path / "report.json")


@pytest.mark.parametrize("name", ["test_targets_bop24.json", "test_targets_bop19.json"])
def test_damaged_targets(bop_export: Path, tmp_path: Path, name: str) -> None:
    good = json.loads((bop_export / name).read_text())
    rng = np.random.default_rng(13 + SEED)
    for k in range(3):
        data = tmp_path / f"bop{k}"
        shutil.copytree(bop_export, data)
        (data / name).write_text(_json_variants(good, rng))
        args = ["evaluate", str(data), "--results", str(DATA / "bop24_results.csv"), "--bop24"]
        _evaluate(args, data, tmp_path / "report.json")


def test_damaged_sensors_json(bop_sensors_export: Path, tmp_path: Path) -> None:
    good = json.loads((bop_sensors_export / "sensors.json").read_text())
    rng = np.random.default_rng(17 + SEED)
    for k in range(4):
        data = tmp_path / f"bop{k}"
        shutil.copytree(bop_sensors_export, data)
        (data / "sensors.json").write_text(_json_variants(good, rng))
        args = ["evaluate", str(data), "--results", str(DATA / "bop24_results.csv"), "--bop24"]
        _evaluate(args, data, tmp_path / "report.json")
