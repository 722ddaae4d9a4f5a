"""``synth --render pbr`` without Blender: the structured-light depth model, the materials and
their errors, the lens remap, the sensor, the missing extra, a Cycles failure in mid-run (a
stand-in interpreter plays the worker), and the exposure judged on the markers. The renders
by Blender itself are in test_pbr_cycles.py (mark ``pbr``)."""

from __future__ import annotations

import json
import stat
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from annotator.annotation.completeness import marker_exposure, quality_warnings
from annotator.cli import main
from annotator.dataset import load_dataset
from annotator.dataset.figures import ImageQuality
from annotator.dataset.materials import PRESETS, parse_material
from annotator.detection.aruco import MarkerDetector
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.synthesis.pbr import cycles_job
from annotator.synthesis.pbr.lens import wide_pinhole
from annotator.synthesis.pbr.render import PAPER_LIFT, marker_quads
from annotator.synthesis.pbr.sensor import SensorSettings, expose
from annotator.synthesis.pbr.structured_light import (
    Reflectance,
    StructuredLightSettings,
    returned_signal,
    structured_light_depth,
)
from annotator.synthesis.shading import Surface
from tests.cli_calls import one_error_line, run_cli

# ------------------------------------------------------------------ structured light


def _plane(h: int = 40, w: int = 60, z: float = 500.0, tilt: float = 0.0):
    """A plane at depth ``z`` seen by a camera with f = 500, tilted about the y axis."""
    u, v = np.meshgrid(np.arange(w) - w / 2, np.arange(h) - h / 2)
    rays = np.stack([u / 500.0, v / 500.0, np.ones_like(u, float)], axis=-1)
    n = np.array([np.sin(tilt), 0.0, -np.cos(tilt)])
    # The plane n . p = n . (0, 0, z): the ray's depth t with n . (t ray) = n . p0.
    t = (n @ np.array([0.0, 0.0, z])) / (rays @ n)
    points = rays * t[..., None]
    normals = np.broadcast_to(n, points.shape).copy()
    return points, normals


def _reflectance(shape, material):
    return Reflectance(
        np.full(shape, material.diffuse),
        np.full(shape, material.mirror),
        np.full(shape, material.roughness),
    )


def _depth(points, normals, material, *, lit=None, projector=(60.0, 0.0, 0.0), seed=0):
    hit = np.ones(points.shape[:2], bool)
    return structured_light_depth(
        points,
        normals,
        hit,
        hit if lit is None else lit,
        _reflectance(hit.shape, material),
        projector=np.array(projector),
        focal_px=500.0,
        rng=np.random.default_rng(seed),
    )


def test_a_matte_plane_is_measured_whole_with_noise_growing_with_distance() -> None:
    stds = []
    for z in (400.0, 800.0):
        points, normals = _plane(z=z)
        d = _depth(points, normals, PRESETS["painted_plastic"])
        assert np.isfinite(d).all()
        stds.append(float(np.std(d - points[..., 2])))
    # Triangulation: the error grows as z^2 (four times at twice the distance).
    assert 3.0 < stds[1] / stds[0] < 5.0


def test_shadowed_points_have_no_depth() -> None:
    points, normals = _plane()
    lit = np.ones(points.shape[:2], bool)
    lit[:, :20] = False
    d = _depth(points, normals, PRESETS["painted_plastic"], lit=lit)
    assert np.isnan(d[:, :20]).all() and np.isfinite(d[:, 20:]).all()


def test_metal_saturates_at_the_mirror_angle_and_reflects_away_elsewhere() -> None:
    steel = PRESETS["polished_steel"]
    projector = np.array([60.0, 0.0, 0.0])
    # Tilted so that the centre pixel mirrors the projector into the camera: glare.
    half = np.arctan2(60.0, 500.0) / 2
    points, normals = _plane(tilt=half)
    d = _depth(points, normals, steel)
    signal, _, _ = returned_signal(points, normals, projector, _reflectance(d.shape, steel))
    assert np.isnan(d[20, 30]) and signal[20, 30] > StructuredLightSettings().max_signal
    # Turned 30 degrees: its mirror sends the light away from the camera.
    points, normals = _plane(tilt=np.radians(30))
    assert np.isnan(_depth(points, normals, steel)).all()
    # Matte paint at the same angle is measured.
    assert np.isfinite(_depth(points, normals, PRESETS["painted_plastic"])).all()


def test_grazing_surfaces_have_no_depth() -> None:
    points, normals = _plane(tilt=np.radians(88))
    assert np.isnan(_depth(points, normals, PRESETS["painted_plastic"])).all()


def test_pixels_fly_between_the_sides_of_a_depth_edge() -> None:
    points, normals = _plane()
    points[:, 30:] *= 600.0 / 500.0  # the right half 100 mm further
    d = _depth(points, normals, PRESETS["painted_plastic"])
    edge = d[:, 28:32]
    between = (edge > 505.0) & (edge < 595.0)
    assert between.any()
    assert not ((d[:, :27] > 505.0) | (d[:, 33:] < 595.0)).any()


# ------------------------------------------------------------------------ materials


def test_materials_from_a_preset_with_overrides() -> None:
    m = parse_material({"preset": "steel", "roughness": 0.1, "color": 0.5})
    assert (m.metallic, m.roughness, m.color) == (1.0, 0.1, (0.5, 0.5, 0.5))
    assert parse_material(None).name == "painted_plastic"
    assert PRESETS["steel"].diffuse == 0.0 and PRESETS["painted_plastic"].diffuse > 0.5


@pytest.mark.parametrize(
    "doc, says",
    [
        ("chrome", "unknown material 'chrome' (valid: aluminium, black_plastic"),
        ({"preset": "steel", "shine": 1}, "unknown keys ['shine']"),
        ({"preset": "steel", "roughness": 2}, "roughness must be a number in [0, 1]"),
        ([1, 2], "a preset name or a mapping"),
    ],
)
def test_a_bad_material_names_its_file(doc, says) -> None:
    with pytest.raises(UserError) as err:
        parse_material(doc, path="objects/x/object.yaml")
    assert str(err.value).startswith("objects/x/object.yaml: ") and says in str(err.value)


def test_check_names_the_object_yaml_of_an_unknown_material(sample_copy, capsys) -> None:
    path = sample_copy / "objects" / "bracket" / "object.yaml"
    doc = yaml.safe_load(path.read_text())
    doc["material"] = "chrome"
    path.write_text(yaml.safe_dump(doc))
    code, out, err = run_cli(["check", str(sample_copy)], capsys)
    text = out + err
    assert code != 0 and "Traceback" not in text
    line = next(x for x in text.splitlines() if "chrome" in x)
    assert "objects/bracket/object.yaml" in line and "valid: aluminium" in line
    doc["material"] = {"preset": "steel", "roughness": 0.2}
    path.write_text(yaml.safe_dump(doc))
    load_dataset(sample_copy)  # a good one is accepted


def test_an_unknown_material_option_is_one_line(tmp_path, capsys) -> None:
    line = one_error_line(
        ["synth", str(tmp_path / "o"), "--render", "pbr", "--material", "bracket=chrome"],
        capsys,
    )
    assert "--material bracket: unknown material 'chrome' (valid: aluminium" in line
    line = one_error_line(
        ["synth", str(tmp_path / "o"), "--render", "pbr", "--material", "gear=steel"], capsys
    )
    assert "no such part" in line


# ------------------------------------------------------------------- lens and sensor


def test_the_printed_corners_are_the_sites_on_flat_faces(sample) -> None:
    # The truth's sites are where the printed corners are: a sheet floating 0.05 mm above
    # them brought every pbr pose 0.05 mm nearer the camera than the truth.
    bracket = load_dataset(sample).objects["bracket"]
    sites = bracket.markers.corners
    T = np.eye(4)
    T[:3, 3] = [5.0, -3.0, 400.0]
    bits = np.zeros((len(sites), 4, 4), np.uint8)
    quads, tiles = marker_quads(Surface(bracket.mesh, T, 0.5, sites, bits))
    assert tiles.shape == (len(sites), 6, 6)
    world = sites + T[:3, 3]
    # The sheet's corners lie on lines through the sites' corners (the paper margin around
    # them) in a plane PAPER_LIFT above theirs.
    ex, ey = world[:, 1] - world[:, 0], world[:, 3] - world[:, 0]
    normal = np.cross(ey, ex)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    height = np.einsum("mkd,md->mk", quads - world[:, :1], normal)
    assert np.abs(height - PAPER_LIFT).max() < 1e-9
    centre = world.mean(axis=1, keepdims=True)
    grown = quads - height[..., None] * normal[:, None]
    assert np.allclose(grown - centre, (world - centre) * (1 + 2 / 4), atol=1e-9)


def test_the_wide_pinhole_remap_puts_each_point_where_the_lens_does() -> None:
    K = np.array([[400.0, 0, 161.3], [0, 400.4, 118.2], [0, 0, 1]])
    cam = Camera("c", 320, 240, K, np.array([-0.1, 0.05, 1e-3, -5e-4, -0.01]))
    wide = wide_pinhole(cam)
    assert wide.width > 320 and wide.height > 240
    point = np.array([[31.0, -17.0, 200.0]])
    u, v = cam.project(point)[0]
    # The same point in the wide pinhole image, drawn there as a dot.
    uw = wide.f * point[0, 0] / point[0, 2] + (wide.width - 1) / 2
    vw = wide.f * point[0, 1] / point[0, 2] + (wide.height - 1) / 2
    img = np.zeros((wide.height, wide.width), np.float32)
    cv2.circle(img, (round(uw * 16), round(vw * 16)), 3 * 16, 1.0, -1, shift=4)
    out = wide.remap(img)
    ys, xs = np.nonzero(out > 0.5)
    assert abs(xs.mean() - u) < 0.3 and abs(ys.mean() - v) < 0.3


def test_shot_and_read_noise() -> None:
    s = SensorSettings(full_well=1000.0, read_noise=5.0)
    flat = np.full((200, 200), 0.5)
    img = expose(flat, s, scale=1.0, rng=np.random.default_rng(1)).astype(float)
    # Poisson on 500 electrons plus 5 of read noise, in 255ths of 1000 electrons.
    want = np.sqrt(500.0 + 25.0) / 1000.0 * 255.0
    assert abs(img.mean() - 127.5) < 0.5 and abs(img.std() - want) / want < 0.1
    quiet = expose(flat, SensorSettings(noise=False), scale=1.0, rng=np.random.default_rng(1))
    assert quiet.std() == 0.0


# ------------------------------------------------------------------ the missing extra


@pytest.fixture()
def no_bpy(monkeypatch, tmp_path):
    """An interpreter without bpy named as bpy's."""
    monkeypatch.setenv(cycles_job.BPY_PYTHON_ENV, sys.executable)
    cycles_job._bpy_python.cache_clear()
    yield
    cycles_job._bpy_python.cache_clear()


def test_render_pbr_without_the_extra_is_one_line_with_the_pip_command(
    no_bpy, tmp_path, capsys
) -> None:
    line = one_error_line(
        ["synth", str(tmp_path / "o"), "--render", "pbr", "--scenes", "1"], capsys
    )
    assert "cannot import bpy" in line and "pip install 'bin-annotator[pbr]'" in line
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------- Cycles failing mid-run

_FAKE_WORKER = """
import json, sys
from pathlib import Path
import numpy as np
job_path = Path(sys.argv[1])
job = json.loads(job_path.read_text())
if job["seed"] % 100003 == 1:
    print("Error: Cycles ran out of memory", flush=True)
    sys.exit(3)
for cam in job["cameras"]:
    img = np.full((cam["height"], cam["width"], 3), 0.3, np.float32)
    img[::7] = 0.9
    np.save(job_path.parent / cam["out"], img)
    print(f"PROGRESS {cam['name']} 1 1", flush=True)
"""


@pytest.fixture()
def failing_cycles(monkeypatch, tmp_path):
    """A stand-in for bpy's interpreter that renders stripes, and fails on scene 1."""
    worker = tmp_path / "fake_worker.py"
    worker.write_text(_FAKE_WORKER)
    python = tmp_path / "fake_python"
    python.write_text(
        f'#!/bin/sh\nif [ "$1" = "-c" ]; then exit 0; fi\nshift\nexec {sys.executable} {worker} "$@"\n'
    )
    python.chmod(python.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setenv(cycles_job.BPY_PYTHON_ENV, str(python))
    cycles_job._bpy_python.cache_clear()
    yield
    cycles_job._bpy_python.cache_clear()


def test_a_cycles_failure_leaves_the_other_scenes_whole_and_no_half_scene(
    failing_cycles, tmp_path, capsys
) -> None:
    out = tmp_path / "o"
    args = ["synth", str(out), "--render", "pbr", "--scenes", "3", "--instances", "2-2"]
    args += ["--parts", "brick", "--size", "160x128", "--quiet", "--material", "brick=steel"]
    code, stdout, err = run_cli(args, capsys)
    assert code == 1 and "Traceback" not in stdout + err
    failure = [x for x in (stdout + err).splitlines() if "000001" in x]
    assert len(failure) == 1 and "Cycles exited with status 3" in failure[0], stdout + err
    assert sorted(p.name for p in (out / "scenes").iterdir()) == ["000000", "000002"]
    for sid in ("000000", "000002"):
        files = {p.name for p in (out / "scenes" / sid).iterdir()}
        assert files == {"left.png", "right.png", "depth.png", "depth_ideal.png", "gt.json"}
    obj = yaml.safe_load((out / "objects" / "brick" / "object.yaml").read_text())
    assert obj["material"] == "steel"
    synth = yaml.safe_load((out / "dataset.yaml").read_text())["synth"]
    assert synth["render"] == "pbr" and synth["pbr"]["depth_model"] == "structured_light"


def test_pbr_truth_is_the_default_renders_truth(failing_cycles, tmp_path, capsys) -> None:
    common = ["--scenes", "1", "--instances", "3-3", "--parts", "brick", "--size", "160x128"]
    common += ["--quiet", "--seed", "4"]
    assert main(["synth", str(tmp_path / "a"), *common]) == 0
    assert main(["synth", str(tmp_path / "b"), *common, "--render", "pbr"]) == 0
    capsys.readouterr()
    scene = Path("scenes") / "000000"
    for name in ("gt.json", "depth_ideal.png"):
        assert (tmp_path / "a" / scene / name).read_bytes() == (
            tmp_path / "b" / scene / name
        ).read_bytes(), name
    assert json.loads((tmp_path / "b" / scene / "gt.json").read_text())["instances"]


# ---------------------------------------------------------------- exposure on markers


def _sample_image(sample: Path) -> np.ndarray:
    ds = load_dataset(sample)
    return cv2.imread(str(ds.scenes()[0].image_path("left")), cv2.IMREAD_GRAYSCALE)


def _kinds(img: np.ndarray, detector: MarkerDetector) -> list[str]:
    reading = detector.read(img)
    levels = marker_exposure(img, [m.corners for m in reading.markers])
    q = ImageQuality(
        reading.blur_px,
        float(np.median(img)),
        float(np.mean(img >= 250)),
        marker_white=None if levels is None else levels[0],
        marker_black=None if levels is None else levels[1],
    )
    return [w.kind for w in quality_warnings({"left": q})]


def test_a_dark_floor_with_well_exposed_markers_is_not_under_exposed(sample) -> None:
    img = _sample_image(sample)
    detector = MarkerDetector(load_dataset(sample).dictionary)
    reading = detector.read(img)
    white, black = marker_exposure(img, [m.corners for m in reading.markers])
    assert white > 150 and black < 60
    # Everything but the markers darkened: the median drops far below the old threshold.
    keep = np.zeros(img.shape, np.uint8)
    for m in reading.markers:
        cv2.fillConvexPoly(keep, np.round(m.corners).astype(np.int32), 255)
    keep = cv2.dilate(keep, np.ones((9, 9), np.uint8)) > 0
    dark = np.where(keep, img, (img * 0.08).astype(np.uint8))
    assert np.median(dark) < 25
    assert "under_exposed" not in _kinds(dark, detector)


def test_dim_markers_are_under_exposed(sample) -> None:
    img = _sample_image(sample)
    detector = MarkerDetector(load_dataset(sample).dictionary)
    dim = (img * 0.18).astype(np.uint8)
    assert detector.read(dim).markers  # still read, but their white is dim
    assert "under_exposed" in _kinds(dim, detector)


def test_image_quality_carries_the_marker_levels(sample) -> None:
    q = ImageQuality(1.0, 30.0, 0.0, marker_white=180.0, marker_black=20.0)
    doc = q.to_json()
    assert doc["marker_white"] == 180.0 and ImageQuality.from_json(doc) == q
    assert "marker_white" not in ImageQuality(1.0, 30.0, 0.0).to_json()
