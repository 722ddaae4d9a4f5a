"""Markers glued by hand: ``annotator sites`` measures each instance's real marker sites.

The solver alone on exact synthetic observations (a part with markers on several faces, and
one with all its markers on one plane, whose in-plane motions nothing but the prior can fix),
then the command on rendered glued scenes against the truth ``synth --glue`` writes.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from annotator.cli import main
from annotator.dataset import load_dataset
from annotator.geometry.transforms import axis_angle, make_transform
from annotator.markers.glue import apply_corrections
from annotator.sites import InstanceData, MarkerView, solve_sites

pytestmark = pytest.mark.slow  # sites measured over many scenes

ANNOTATOR = str(Path(sys.executable).parent / "annotator")


def _square(centre, u, v, size=8.0) -> np.ndarray:
    """A site: corners TL, TR, BR, BL with ``u`` along the top edge and ``v`` down the left."""
    c, u, v, h = np.asarray(centre, float), np.asarray(u, float), np.asarray(v, float), size / 2
    return np.array([c - h * u - h * v, c + h * u - h * v, c + h * u + h * v, c - h * u + h * v])


def _observations(cameras, layout, truth, rng, views=8, noise_px=0.05):
    """Poses of the part in front of the rig and the true sites' corners seen in them."""
    poses, marks = [], []
    for s in range(views):
        axis = rng.normal(size=3)
        R = axis_angle(axis, rng.uniform(0.2, 0.7))
        T = make_transform(R, np.array([rng.uniform(-40, 40), rng.uniform(-40, 40), 480.0]))
        poses.append(T)
        for j, cam in enumerate(cameras):
            M = cam.cam_T_rig @ T
            for k, X in enumerate(truth):
                n = np.cross(X[3] - X[0], X[1] - X[0]) @ M[:3, :3].T
                centre = X.mean(0) @ M[:3, :3].T + M[:3, 3]
                if n @ centre >= 0:  # faces away from the camera
                    continue
                uv = cam.project(X @ M[:3, :3].T + M[:3, 3])
                marks.append(MarkerView(s, j, k, uv + rng.normal(0, noise_px, uv.shape)))
    # The annotated poses: near the truth, not on it.
    start = [
        make_transform(axis_angle(rng.normal(size=3), 0.004) @ T[:3, :3], T[:3, 3] + 0.3)
        for T in poses
    ]
    return InstanceData(layout, start, marks, [])


def _cube_layout() -> np.ndarray:
    """Sites on five faces of a 40 mm cube (normals outward)."""
    e = np.eye(3)
    sites = []
    for n in (e[0], -e[0], e[1], -e[1], e[2]):
        u = np.cross(n, e[2]) if abs(n[2]) < 0.5 else e[0]
        v = np.cross(n, u)  # so that (v x u) = n: outward
        for off in (-8, 8):
            sites.append(_square(20 * n + off * u, u, v))
    return np.array(sites)


def _plate_layout() -> np.ndarray:
    """Six sites on the top face of a plate (all on one plane, z = 0)."""
    u, v = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])  # outward normal -z: to the cameras
    return np.array([_square([x, y, 0], u, v) for x in (-20, 0, 20) for y in (-10, 10)])


@pytest.fixture(scope="module")
def cameras(sample):
    return load_dataset(sample).rig.cameras


def test_sites_on_several_faces_are_measured_exactly(cameras) -> None:
    rng = np.random.default_rng(1)
    layout = _cube_layout()
    glue = np.column_stack(
        [rng.normal(0, 0.7, (len(layout), 2)), np.radians(rng.normal(0, 2, len(layout)))]
    )
    truth = apply_corrections(layout, glue)
    sol = solve_sites(cameras, _observations(cameras, layout, truth, rng))
    measured = apply_corrections(layout, sol.corrections)
    seen = sol.seen >= 3
    rms = np.sqrt(np.mean(np.sum((measured - truth) ** 2, -1), axis=1))
    assert seen.sum() >= 6 and rms[seen].max() < 0.05, rms[seen]
    assert sol.unobservable == []
    assert sol.rms_after < 0.1 < sol.rms_before
    # The uncertainty it states is of the size of the errors (not ten times more or less).
    z = (np.abs(sol.corrections - glue) / sol.std)[seen]
    assert 0.1 < np.sqrt(np.mean(z**2)) < 5, z


def test_the_gauge_is_fixed_whatever_the_start(cameras) -> None:
    rng = np.random.default_rng(2)
    layout = _cube_layout()
    truth = apply_corrections(layout, np.column_stack([rng.normal(0, 0.7, (10, 2)), np.zeros(10)]))
    data = _observations(cameras, layout, truth, rng)
    a = solve_sites(cameras, data)
    start = np.column_stack([rng.normal(0, 1.0, (10, 2)), np.radians(rng.normal(0, 3, 10))])
    b = solve_sites(cameras, data, start=start)
    assert np.abs(a.corrections - b.corrections)[a.seen > 0].max() < 1e-3


def test_markers_all_on_one_plane_report_what_cannot_be_seen(cameras) -> None:
    rng = np.random.default_rng(3)
    layout = _plate_layout()
    glue = np.column_stack([rng.normal(0, 0.7, (6, 2)), np.radians(rng.normal(0, 2, 6))])
    glue[:, 0] += 0.8  # every sticker 0.8 mm to the right as well: a motion of all of them
    truth = apply_corrections(layout, glue)
    sol = solve_sites(cameras, _observations(cameras, layout, truth, rng))
    assert set(sol.unobservable) == {"shift along x", "shift along y", "turn about z"}
    # The common shift is not invented: the prior keeps the layout's placement...
    assert abs(sol.corrections[:, 0].mean()) < 0.1
    # ...while the sites' placement relative to each other is measured: up to one shift and
    # one turn in the plane, the measured corners are the true ones.
    a = apply_corrections(layout, sol.corrections)[..., :2].reshape(-1, 2)
    b = truth[..., :2].reshape(-1, 2)
    U, _, Vt = np.linalg.svd((a - a.mean(0)).T @ (b - b.mean(0)))
    aligned = (a - a.mean(0)) @ (U @ Vt) + b.mean(0)
    assert np.abs(aligned - b).max() < 0.05


# ------------------------------------------------------------------ the command, end to end


@pytest.fixture(scope="module")
def glued(tmp_path_factory) -> Path:
    """Six rendered scenes of bracket and brick copies whose markers are glued by hand,
    annotated."""
    root = tmp_path_factory.mktemp("glued") / "ds"
    for args in (
        [
            "synth",
            str(root),
            "--parts",
            "brick,bracket",
            "--scenes",
            "6",
            "--instances",
            "4-5",
            "--glue",
            "0.7,2",
            "--seed",
            "3",
            "--quiet",
            "--workers",
            "2",
        ],
        ["annotate", str(root), "--quiet", "--workers", "2"],
    ):
        run = subprocess.run([ANNOTATOR, *args], capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
    return root


def _report(root: Path, *extra: str) -> dict:
    run = subprocess.run(
        [ANNOTATOR, "sites", str(root), "--json", "--quiet", *extra], capture_output=True, text=True
    )
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


def test_measured_sites_match_the_glued_truth_and_annotate_uses_them(glued, tmp_path) -> None:
    root = tmp_path / "ds"
    shutil.copytree(glued, root)
    truth = json.loads((root / "glued_sites.json").read_text())
    report = _report(root, "--yes")
    assert len(report["written"]) == 2
    ds = load_dataset(root)
    errors, before = [], []
    for rec in report["instances"]:
        obj, inst = rec["instance"].split("/")
        true = np.asarray(truth[obj][inst])
        for m in rec["markers"]:
            if m["scenes"] >= 3:
                k = m["site"]
                errors.append(
                    np.mean(np.sum((ds.objects[obj].site_corners(inst)[k] - true[k]) ** 2, -1))
                )
                before.append(
                    np.mean(np.sum((ds.objects[obj].markers.corners[k] - true[k]) ** 2, -1))
                )
    # object.yaml says from how many scenes each site was measured (annotate's trust in it).
    for rec in report["instances"]:
        obj, inst = rec["instance"].split("/")
        counts = ds.objects[obj].instance(inst).site_scenes
        assert counts is not None and [counts[m["site"]] for m in rec["markers"]] == [
            m["scenes"] for m in rec["markers"]
        ]
    gain = [r["corner_rms_px"][1] / r["corner_rms_px"][0] for r in report["instances"]]
    assert np.median(gain) < 0.5, gain
    assert len(errors) >= 10
    assert np.sqrt(np.mean(errors)) < 0.25 < np.sqrt(np.mean(before)), (errors, before)
    # check validates the instances' sites; annotate redoes every scene with them.
    assert main(["check", str(root)]) == 0
    run = subprocess.run(
        [ANNOTATOR, "annotate", str(root), "--json", "--quiet"], capture_output=True, text=True
    )
    assert json.loads(run.stdout)["done"] == 6
    # One command was enough: it annotated again with its sites until they settled, so
    # measuring again from annotate's new poses moves them by little more than that.
    assert report["rounds"] >= 2 and len(report["round_moves_mm"]) == report["rounds"] - 1
    again = _report(root, "--dry-run")
    first = {(r["instance"], m["site"]): m for r in report["instances"] for m in r["markers"]}
    shift = [
        (m["du_mm"] - first[(r["instance"], m["site"])]["du_mm"]) ** 2
        + (m["dv_mm"] - first[(r["instance"], m["site"])]["dv_mm"]) ** 2
        for r in again["instances"]
        for m in r["markers"]
        if m["scenes"] >= 3 and (r["instance"], m["site"]) in first
    ]
    assert len(shift) >= 10 and np.sqrt(np.mean(shift)) < 0.05, np.sqrt(np.mean(shift))


def test_a_marker_glued_on_the_wrong_site_is_flagged(glued, tmp_path) -> None:
    root = tmp_path / "ds"
    shutil.copytree(glued, root)
    path = root / "objects" / "bracket" / "object.yaml"
    doc = yaml.safe_load(path.read_text())
    ids = doc["instances"][0]["marker_ids"]
    report = _report(glued, "--dry-run")
    used = max(
        (m for r in report["instances"] if r["instance"] == "bracket/01" for m in r["markers"]),
        key=lambda m: m["scenes"],
    )
    far = max(
        range(len(ids)),
        key=lambda k: np.linalg.norm(
            np.mean(doc["markers"]["sites"][k], 0)
            - np.mean(doc["markers"]["sites"][used["site"]], 0)
        ),
    )
    k = used["site"]
    ids[k], ids[far] = ids[far], ids[k]  # the two stickers swapped: each on the other's site
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    assert main(["annotate", str(root), "--quiet", "--workers", "1"]) == 0
    report = _report(root, "--dry-run")
    rec = next(r for r in report["instances"] if r["instance"] == "bracket/01")
    flagged = {m["site"]: m["flag"] for m in rec["markers"] if m["flag"]}
    assert k in flagged and "glued on another site" in flagged[k]
    assert report["written"] == []


def test_exact_sites_get_corrections_within_noise(sample_copy) -> None:
    report = _report(sample_copy, "--dry-run")
    moves = [
        m["du_mm"] ** 2 + m["dv_mm"] ** 2
        for r in report["instances"]
        for m in r["markers"]
        if m["scenes"] >= 2
    ]
    assert len(moves) >= 10 and np.sqrt(np.mean(moves)) < 0.1
    assert report["flagged_markers"] == 0


def test_sites_needs_annotated_scenes(sample_copy, capsys) -> None:
    for ann in sample_copy.glob("scenes/*/annotation.json"):
        ann.unlink()
    assert main(["sites", str(sample_copy)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "run `annotator annotate" in err


def test_check_validates_the_instances_sites(sample_copy, capsys) -> None:
    path = sample_copy / "objects" / "brick" / "object.yaml"
    doc = yaml.safe_load(path.read_text())
    sites = np.asarray(doc["markers"]["sites"], float)
    sites[1] += [0, 0, 5.0]  # 5 mm off the surface
    doc["instances"][0]["sites"] = sites.tolist()
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    assert main(["check", str(sample_copy)]) == 1
    out = capsys.readouterr().out
    name = doc["instances"][0]["name"]
    assert f"instance '{name}': sites[1] is" in out and "off the mesh surface" in out
    doc["instances"][0]["sites"] = sites[:2].tolist()  # not the layout's shape
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    assert main(["check", str(sample_copy)]) == 1
    assert "instances[0].sites must have" in capsys.readouterr().out
    doc["instances"][0]["sites"] = sites.tolist()
    doc["instances"][0]["site_scenes"] = [1, 2]  # not one per site
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    assert main(["check", str(sample_copy)]) == 1
    out = capsys.readouterr().out
    assert f"instances[0].site_scenes must be {len(sites)} non-negative integers" in out
