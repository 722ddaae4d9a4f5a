"""``export --remove-markers`` checked with OpenCV's own ArUco detector at several settings,
on a fixed rig and on a sequence rendered twice (with and without markers, same seed): the
detector finds many markers in the plain export and, in the filled images, nothing the
render without markers does not also give it (its false readings of the parts' edges); no
ink is left outside the masks, markers seen edge-on included."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from devkit.aruco_settings import SETTINGS, detections, detector, new_in
from devkit.marker_twins import export_twins, render_twins

pytestmark = pytest.mark.slow  # scenes rendered twice and exported first

COMMON = ["--parts", "bracket,brick,gear,cup,cylinder,ball", "--instances", "14-22"]
COMMON += ["--size", "640x512", "--supersample", "1", "--no-depth", "--workers", "1", "--quiet"]
#: Seed 41's second scene has a cup's marker seen edge-on over the cup's own inner wall, its
#: plane turned a hair away from the camera: its ink was left unfilled.
RIGS = {
    "fixed": ["--scenes", "2", "--seed", "41"],
    "sequence": ["--scenes", "1", "--frames", "4", "--seed", "41"],
}


@pytest.fixture(
    scope="module",
    params=["fixed", pytest.param("sequence", marks=pytest.mark.slow)],  # 4 frames x 2 twins
)
def twins(request, tmp_path_factory) -> Path:
    """Plain, bare and --remove-markers BOP exports of one rig's scenes."""
    base = tmp_path_factory.mktemp(request.param)
    return export_twins(render_twins(base, [*COMMON, *RIGS[request.param]]))


def _read(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    return img


def _images(base: Path) -> list[dict[str, np.ndarray]]:
    """Per exported intensity image: the plain one, the bare render's, the filled one and
    its mask."""
    out = []
    for f in sorted((base / "plain" / "test").glob("*/gray_*/*.png")):
        rel = f.relative_to(base / "plain")
        masks = rel.parents[1] / rel.parent.name.replace("gray", "mask_markers", 1) / rel.name
        out.append(
            {
                "plain": _read(f),
                "bare": _read(base / "bare_bop" / rel),
                "filled": _read(base / "removed" / rel),
                "mask": _read(base / "removed" / masks) > 0,
            }
        )
    return out


def test_opencv_finds_no_marker_after_removal(twins) -> None:
    images = _images(twins)
    assert len(images) >= 4
    for setting in SETTINGS:
        det = detector(setting)
        before = after = 0
        for im in images:
            bare = detections(det, im["bare"])
            before += len(new_in(detections(det, im["plain"]), bare))
            after += len(new_in(detections(det, im["filled"]), bare))
        assert before >= 15, (setting, before)  # markers are small at 640x512
        assert after == 0, (setting, after)


def test_no_ink_outside_the_masks(twins) -> None:
    """Every pixel where the marked render differs from the bare one is in the mask; the
    masks are 0 or 255, and outside them the filled image is the plain one, byte for byte."""
    for im in _images(twins):
        mask = im["mask"]
        assert np.array_equal(im["filled"][~mask], im["plain"][~mask])
        ink = im["plain"] != im["bare"]
        assert ink.any()
        assert not (ink & ~mask).any(), np.argwhere(ink & ~mask)[:5].tolist()


def _opencv_finds(folder: Path, dictionary: int) -> dict[str, int]:
    """Per exported intensity image, the markers OpenCV finds at any of its settings."""
    found: dict[str, int] = {}
    dets = [detector(s, dictionary) for s in SETTINGS]
    for f in sorted(folder.glob("test/*/gray*/*.png")) + sorted(folder.glob("test/*/rgb*/*.png")):
        img = _read(f)
        found[str(f)] = max(len(detections(d, img)) for d in dets)
    return found


def test_markers_are_masked_wherever_the_poses_put_them(sample_copy: Path, tmp_path) -> None:
    """Issue 54: an annotation whose poses are off (one part 8 mm and 6 degrees away, one
    flagged part moved in front of another) still leaves no marker OpenCV can find, because
    every marker a detector finds is masked whatever the poses say."""
    import json

    from annotator.cli import main
    from annotator.geometry.lie import rotvec_to_matrix

    for sid, shift in (("000000", (8.0, 0.0, 0.0)), ("000002", (0.0, 25.0, -40.0))):
        path = sample_copy / "scenes" / sid / "annotation.json"
        doc = json.loads(path.read_text())
        inst = doc["instances"][-1]
        R = np.asarray(inst["cam_R_m2c"], float).reshape(3, 3) @ rotvec_to_matrix(
            np.radians([6.0, 0, 0])
        )
        inst["cam_R_m2c"] = R.reshape(-1).tolist()
        inst["cam_t_m2c"] = (np.asarray(inst["cam_t_m2c"], float) + shift).tolist()
        inst["flags"] = sorted({*inst.get("flags", []), "high_uncertainty"})
        path.write_text(json.dumps(doc))
    plain, filled = tmp_path / "plain", tmp_path / "filled"
    export = [str(sample_copy), "--format", "bop", "--include-pending", "--quiet"]
    assert main(["export", export[0], str(plain), *export[1:]]) == 0
    assert main(["export", export[0], str(filled), *export[1:], "--remove-markers"]) == 0
    dictionary = cv2.aruco.DICT_4X4_1000
    before = _opencv_finds(plain, dictionary)
    after = _opencv_finds(filled, dictionary)
    assert sum(before.values()) > 50
    assert after and all(n == 0 for n in after.values()), after
