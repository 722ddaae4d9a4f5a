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
