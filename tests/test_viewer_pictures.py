"""The pictures without a browser: pixel-exact contours, the mosaic's way back to camera
pixels, the zoom's one-pixel outline, picking an instance, unexplained depth in red and
"no pose here" marks."""

from __future__ import annotations

import dataclasses
import doctest
import time

import cv2
import numpy as np
import pytest

from annotator.dataset import load_dataset, read_poses
from annotator.dataset.figures import DepthRegion
from annotator.dataset.review import MissingPart, ReviewStatus
from devkit.polling import wait_until
from viewer.drawing.mosaic import Tile, compose, grid
from viewer.drawing.overlays import _outline, prepare, repose
from viewer.drawing.style import COLOURS, MISSING_COLOUR, UNEXPLAINED_COLOUR, Look
from viewer.drawing.zoom import inner_outline, zoom
from viewer.page import keyguard, pictures
from viewer.page.pictures import picture_html, zoom_html


@pytest.fixture(scope="module")
def scene(sample):
    ds = load_dataset(sample)
    sc = ds.scenes()[0]
    poses = read_poses(sc.annotation_path)
    return ds, sc, poses, prepare(ds, sc, poses)


def _rgb(bgr):
    return np.array(bgr[::-1])


def test_contours_follow_the_projected_silhouette(scene) -> None:
    ds, _, poses, prep = scene
    layer = prep.layers[0]
    cam = ds.rig.cameras[0]
    p = poses[0]
    # The contour hugs the projection of the mesh's vertices.
    M = cam.cam_T_rig @ p.T
    uv = cam.project(ds.objects[p.object].mesh.vertices @ M[:3, :3].T + M[:3, 3])
    contour = np.concatenate(layer.contours[0])
    lo, hi = contour.min(axis=0), contour.max(axis=0)
    assert np.all(uv.min(axis=0) >= lo - 1.5) and np.all(uv.max(axis=0) <= hi + 1.5)
    # Every contour point lies on the silhouette's edge (within the simplification).
    mask = (layer.instance == 0).astype(np.uint8)
    edge = cv2.distanceTransform(
        1 - inner_outline(mask.astype(bool)).astype(np.uint8), cv2.DIST_L2, 5
    )
    assert edge[contour[:, 1], contour[:, 0]].max() <= 1.0
    look = Look(states=((p.key, ReviewStatus.ACCEPTED),))
    picture = compose(prep, look, 1280, 1024)
    tile = picture.tiles[0]
    x, y = (round(v) for v in tile.to_picture(*contour[0]))
    window = picture.image[max(y - 2, 0) : y + 3, max(x - 2, 0) : x + 3].reshape(-1, 3)
    assert np.any(
        np.abs(window.astype(int) - _rgb(COLOURS[ReviewStatus.ACCEPTED])).sum(axis=1) < 60
    )
    assert [t.name for t in picture.tiles] == ["left", "right", "depth", "disagreement"]


def test_the_mosaic_fills_the_viewport_and_maps_back_to_camera_pixels(scene) -> None:
    _, _, _, prep = scene
    picture = compose(prep, Look(), 956, 1000)
    assert picture.image.shape == (1000, 956, 3)
    assert grid(4, 956, 1000, 1.25) == (2, 2) and grid(4, 2000, 400, 1.25) == (4, 1)
    for tile in picture.tiles:
        assert tile.x0 >= 0 and tile.x0 + tile.width <= 956 and tile.y0 + tile.height <= 1000
        u, v = tile.to_picture(640.0, 512.0)
        found, x, y = picture.locate(u, v)
        assert found == tile and abs(x - 640.0) < 1e-9 and abs(y - 512.0) < 1e-9
    assert picture.locate(-5, -5) is None
    # The same look and size is made once.
    assert compose(prep, Look(), 956, 1000) is picture


def test_picking_an_instance_by_a_pixel(scene) -> None:
    _, _, _, prep = scene
    layer = prep.layers[0]
    ys, xs = np.nonzero(layer.instance == 2)
    assert prep.instance_at("left", xs[0], ys[0]) == prep.keys[2]
    assert prep.instance_at("nowhere", xs[0], ys[0]) is None
    # Just outside an instance: found within a radius, not without.
    mask = (layer.instance >= 0).astype(np.uint8)
    ring = cv2.dilate(mask, np.ones((3, 3), np.uint8)) - mask
    yy, xx = np.nonzero(ring)
    assert prep.instance_at("left", xx[0], yy[0]) is None
    assert prep.instance_at("left", xx[0], yy[0], radius=3.0) is not None


def test_the_zoom_crops_at_full_resolution_with_a_one_pixel_outline(scene) -> None:
    _, _, _, prep = scene
    key = prep.keys[1]
    z = zoom(prep, key, Look(), 956, 1000)
    assert z is not None and z.image.shape == (1000, 956, 3)
    colour = _rgb(COLOURS[ReviewStatus.PENDING])
    for tile, panel in zip(z.tiles, prep.panels):
        m = int(tile.scale)
        assert m >= 2 and tile.scale == m  # whole pixels, magnified
        ox, oy = int(tile.origin[0]), int(tile.origin[1])
        ch, cw = tile.height // m, tile.width // m
        mask = panel.layer.instance[oy : oy + ch, ox : ox + cw] == 1
        big = np.repeat(np.repeat(mask, m, 0), m, 1)
        expected = inner_outline(big)
        sub = z.image[tile.y0 : tile.y0 + tile.height, tile.x0 : tile.x0 + tile.width]
        drawn = np.all(sub == colour, axis=-1)
        # Drawn exactly on the silhouette's inner edge (the tile title may hide a little).
        assert (drawn & ~expected)[30:].sum() == 0
        assert (expected & drawn).sum() >= 0.95 * expected[30:].sum()
        # One pixel wide: no 2x2 block of outline.
        blocks = drawn[:-1, :-1] & drawn[1:, :-1] & drawn[:-1, 1:] & drawn[1:, 1:]
        assert blocks.sum() <= 0.01 * drawn.sum()
        # Outside the silhouette the crop is the image itself, pixel for pixel.
        if not panel.is_depth:
            img = panel.image[oy : oy + ch, ox : ox + cw]
            plain = np.repeat(np.repeat(img, m, 0), m, 1)
            outside = ~big
            outside[:30] = False
            assert np.array_equal(sub[outside][:, 0], plain[outside])
    # The rendered version differs only inside the silhouette; fill tints it.
    differs = np.any(z.rendered != z.image, axis=-1)
    filled = zoom(prep, key, Look(), 956, 1000, fill=True)
    assert differs.any() and np.any(filled.image != z.image)
    assert zoom(prep, "no/such", Look(), 956, 1000) is None
    # A click in the zoom comes back to the camera pixel under it.
    t = z.tiles[0]
    found, x, y = z.locate(*t.to_picture(t.origin[0] + 10, t.origin[1] + 7))
    assert found == t and (x, y) == (t.origin[0] + 10, t.origin[1] + 7)


def test_the_zoom_goes_to_the_page_in_layers_that_make_its_picture(scene) -> None:
    """Each crop at its own pixels (grey ones as one channel), magnified by the browser, and
    an SVG outline whose rectangles cover exactly the picture's outline."""
    import base64
    import re

    _, _, _, prep = scene
    key = prep.keys[1]
    z = zoom(prep, key, Look(), 956, 1000)
    html = zoom_html(z, layer=2)
    urls = re.findall(r'<img alt="" src="data:image/png;base64,([^"]+)"', html)
    assert len(urls) == len(z.parts) and "image-rendering:pixelated" in html
    for url, part in zip(urls, z.parts):
        back = cv2.imdecode(np.frombuffer(base64.b64decode(url), np.uint8), cv2.IMREAD_UNCHANGED)
        if back.ndim == 2:  # grey: one channel
            back = cv2.cvtColor(back, cv2.COLOR_GRAY2BGR)
        assert np.array_equal(back, part.shown)
    assert any(not p.panel.is_depth for p in z.parts)
    # The outline's rectangles, drawn, are the picture's outline pixels exactly.
    path = re.search(r'<path fill="rgb\(([0-9,]+)\)" d="([^"]*)"/></svg></div>$', html)
    assert path is not None
    assert tuple(map(int, path.group(1).split(","))) == tuple(_rgb(z.colour))
    drawn = np.zeros((1000, 956), bool)
    for x, y, w, h in re.findall(r"M(\d+) (\d+)h(\d+)v(\d+)h-\d+z", path.group(2)):
        drawn[int(y) : int(y) + int(h), int(x) : int(x) + int(w)] = True
    expected = np.zeros_like(drawn)
    for part in z.parts:
        t = part.tile
        expected[t.y0 : t.y0 + t.height, t.x0 : t.x0 + t.width] = inner_outline(
            np.repeat(np.repeat(part.mask, part.magnification, 0), part.magnification, 1)
        )
    assert drawn.sum() > 100 and np.array_equal(drawn, expected)
    # Fill mode: the crops are tinted, no outline.
    filled = zoom_html(zoom(prep, key, Look(), 956, 1000, fill=True))
    assert "<path fill" not in filled.split("</svg>")[-2]


def test_a_repaired_pose_keeps_the_zoom_crop_while_it_fits(scene) -> None:
    ds, sc, poses, prep = scene
    key = prep.keys[1]
    z = zoom(prep, key, Look(), 956, 1000)
    k = prep.keys.index(key)
    moved = [dataclasses.replace(p, t=p.t + [1.0, 0.0, 0.0]) if p.key == key else p for p in poses]
    new = repose(ds, prep, moved, key)
    assert new.layers[0].boxes[k] != prep.layers[0].boxes[k]
    again = zoom(new, key, Look(), 956, 1000, keep=z)
    assert [(p.x0, p.y0) for p in again.parts] == [(p.x0, p.y0) for p in z.parts]
    # The outline moved with the pose; a zoom of another instance is not kept.
    assert not np.array_equal(again.image, z.image)
    other = zoom(new, prep.keys[0], Look(), 956, 1000, keep=z)
    assert [(p.x0, p.y0) for p in other.parts] == [
        (p.x0, p.y0) for p in zoom(new, prep.keys[0], Look(), 956, 1000).parts
    ]


def test_unexplained_depth_is_red_on_depth_panels_only(sample_copy) -> None:
    ds = load_dataset(sample_copy)
    sc = ds.scenes()[0]
    poses = read_poses(sc.annotation_path)
    cam = ds.rig.depth_camera
    mask = np.zeros((cam.height, cam.width), np.uint8)
    mask[900:1000, 40:200] = 255  # a corner of the bin, far from any part
    cv2.imwrite(str(sc.path / "unexplained.png"), mask)
    prep = prepare(ds, sc, poses)
    assert prep.unexplained is not None and prep.unexplained.sum() == 100 * 160
    region = DepthRegion((40, 900, 200, 1000), 16000, (500.0, 510.0))
    missing = MissingPart("right", (600.0, 500.0))
    picture = compose(prep, Look(regions=(region,), missing=(missing,)), 1280, 1024)
    red = np.all(np.abs(picture.image.astype(int) - _rgb(UNEXPLAINED_COLOUR)) < 60, axis=-1)
    cyan = np.all(np.abs(picture.image.astype(int) - _rgb(MISSING_COLOUR)) < 60, axis=-1)
    by_tile = {
        t.name: (
            red[t.y0 : t.y0 + t.height, t.x0 : t.x0 + t.width].sum(),
            cyan[t.y0 : t.y0 + t.height, t.x0 : t.x0 + t.width].sum(),
        )
        for t in picture.tiles
    }
    assert by_tile["depth"][0] > 500 and by_tile["disagreement"][0] > 500
    assert by_tile["left"][0] < 50 and by_tile["right"][0] < 50
    assert by_tile["right"][1] > 20 and by_tile["left"][1] == 0
    # Inside the region box, the depth panel is red where the mask says so.
    t: Tile = next(t for t in picture.tiles if t.name == "depth")
    u, v = (round(c) for c in t.to_picture(120, 950))
    assert red[v, u]
    # A mask of the wrong size is reported, not drawn.
    cv2.imwrite(str(sc.path / "unexplained.png"), mask[:10, :10])
    prep = prepare(ds, sc, poses)
    assert prep.unexplained is None and any("unexplained.png" in m for m in prep.messages)


def test_pictures_go_to_the_page_as_images_over_the_canvas() -> None:
    import base64
    import re

    img = np.zeros((40, 60, 3), np.uint8)
    img[10:20, 5:50] = (255, 220, 0)
    html = picture_html(img, exact=True, z=2)
    data = re.search(r'src="data:image/png;base64,([^"]+)"', html).group(1)
    back = cv2.imdecode(np.frombuffer(base64.b64decode(data), np.uint8), cv2.IMREAD_COLOR)
    assert np.array_equal(back[:, :, ::-1], img)  # PNG: pixel for pixel
    for css in (
        "position:fixed",
        "width:60px;height:40px",
        "anchor-size(width)",
        "pointer-events:none",
    ):
        assert css in html
    assert "animation" not in html and "animation:review-blink" in picture_html(img, blink=True)
    assert 'src="data:image/jpeg;base64,' in picture_html(img)


class _Html:
    def __init__(self) -> None:
        self.content, self.visible = "", True


class _Gui:
    def add_html(self, content: str, **_kw) -> _Html:
        return _Html()


class _Scene:
    """Records when the canvas's copy of the picture was sent (None: cleared)."""

    def __init__(self) -> None:
        self.sent: list[tuple[float, object]] = []

    def set_background_image(self, image, **_kw) -> None:
        self.sent.append((time.monotonic(), None if image is None else image.shape))


@pytest.fixture()
def quick(monkeypatch):
    """Pictures with short waits (the same rules, a test's time)."""
    monkeypatch.setattr(pictures, "BACKGROUND_DELAY", 0.05)
    monkeypatch.setattr(pictures, "BACKGROUND_QUIET", 0.6)
    scene = _Scene()
    p = pictures.Pictures(_Gui(), scene)  # type: ignore[arg-type]
    yield p, scene
    p.close()


@pytest.mark.slow
def test_the_canvas_copy_waits_until_the_pictures_and_keys_are_still(quick) -> None:
    p, scene = quick
    image = np.zeros((40, 60, 3), np.uint8)
    start = time.monotonic()
    for _ in range(5):  # a picture every 0.15 s: nothing is drawn on the canvas meanwhile
        p.show_mosaic(image)
        p.send_background_soon()
        time.sleep(0.15)
    assert scene.sent == []
    p.postpone()  # a key came: its answer must not wait for the copy either
    assert wait_until(lambda: len(scene.sent) == 1, timeout=3)
    (at, shape), last_change = scene.sent[0], start + 0.6
    assert shape == (40, 60, 3)
    assert at - last_change >= 0.6 + 0.1  # the quiet counted from the key, not the picture
    time.sleep(0.8)
    assert len(scene.sent) == 1  # sent once, and not again while nothing changes


def test_a_collapsed_panel_gets_the_copy_at_once(quick) -> None:
    p, scene = quick
    image = np.zeros((40, 60, 3), np.uint8)
    p.canvas_resized(916, 1000)
    p.canvas_resized(1360, 1000)  # the docked panel collapsed: the canvas widened
    t0 = time.monotonic()
    p.show_mosaic(image)
    p.send_background_soon()
    assert wait_until(lambda: len(scene.sent) == 1, timeout=3)
    assert scene.sent[0][0] - t0 < 0.45  # the short wait, not the quiet one
    p.canvas_resized(916, 1000)  # open again: back to the long wait
    t1 = time.monotonic()
    p.show_mosaic(image[:20])
    p.send_background_soon()
    assert wait_until(lambda: len(scene.sent) == 2, timeout=3)
    assert scene.sent[1][0] - t1 >= 0.6


def test_the_3d_view_clears_the_canvas_copy_at_once(quick) -> None:
    p, scene = quick
    p.show_mosaic(np.zeros((40, 60, 3), np.uint8))
    p.hide(True)
    p.send_background()
    assert [s for _, s in scene.sent] == [None]


def test_every_picture_carries_the_mark_the_key_guard_looks_for(scene) -> None:
    _, _, poses, prep = scene
    look = Look()
    z = zoom(prep, poses[0].key, look, 900, 700)
    assert z is not None
    for layer in pictures.zoom_layers(z):
        assert layer.count(f"<div {keyguard.PICTURE_MARK} ") == 1
    assert f'<img alt="" {keyguard.PICTURE_MARK} ' in picture_html(np.zeros((8, 8, 3), np.uint8))
    # The guard's script is an attribute of an empty image: quotes escaped, nothing else.
    guard = keyguard.guard_html(["A", "Y", "1"])
    assert guard.count("<") == 1 and '"KeyA"' not in guard
    assert "&quot;KeyA&quot;" in guard and "[&quot;1&quot;, &quot;a&quot;, &quot;y&quot;]" in guard


def test_the_docstring_examples_run() -> None:
    assert doctest.testmod(pictures).failed == 0
    assert doctest.testmod(keyguard).failed == 0


def test_an_outline_s_box_and_centre_are_those_of_its_pixels() -> None:
    """The box and centre come from OpenCV and the row and column counts (quicker on large
    parts): they are exactly those of the pixels themselves, on 300 random masks."""
    rng = np.random.default_rng(0)
    for _ in range(300):
        h, w = (int(v) for v in rng.integers(1, 80, 2))
        instance = np.where(rng.random((h, w)) < rng.random() * 0.4, 5, -1).astype(np.int16)
        _, box, centre = _outline(instance, 5, (0, 0, w, h))
        ys, xs = np.nonzero(instance == 5)
        if not len(xs):
            assert box is None and centre is None
            continue
        assert box == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)
        assert centre == (int(xs.mean()), int(ys.mean()))
