"""ArUco detection on images whose corners are known exactly: ids, sub-pixel corners, and the
same result from 8-bit grey, 16-bit and colour images."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from annotator.detection import MarkerDetector
from annotator.detection.identify import Codebook, pack_bits
from annotator.markers.texture import marker_image

DICT = "DICT_4X4_1000"
SS = 4  # supersampling of the synthetic image


def _scene(rng, sizes=(50, 80), turns=(0, 0, 0, 0)) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """A 640x480 grey image with 4 perspective-warped markers, marker k turned by about
    ``turns[k]`` quarter turns; their true corners by id."""
    h, w = 480, 640
    acc = np.full((h * SS, w * SS), 230.0, np.float32)
    truth = {}
    for k, (cx, cy) in enumerate([(150, 130), (470, 140), (160, 350), (480, 360)]):
        mid = 7 + 31 * k
        size = rng.uniform(*sizes)
        ang = rng.uniform(-0.6, 0.6) + turns[k] * np.pi / 2
        square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * size / 2
        rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
        corners = square @ rot.T + [cx, cy] + rng.normal(0, 4, (4, 2))  # a perspective quad
        truth[mid] = corners
        p = 60
        img = marker_image(DICT, mid, p).astype(np.float32) * 0.8 + 20
        # Marker pixel (0, 0) covers [-0.5, 0.5]^2: its outer corner is (-0.5, -0.5).
        src = np.array([[-0.5, -0.5], [p - 0.5, -0.5], [p - 0.5, p - 0.5], [-0.5, p - 0.5]])
        dst = SS * (corners + 0.5) - 0.5
        H = cv2.getPerspectiveTransform(src.astype(np.float32), dst.astype(np.float32))
        warped = cv2.warpPerspective(img, H, (w * SS, h * SS), flags=cv2.INTER_NEAREST)
        inside = cv2.warpPerspective(
            np.ones_like(img), H, (w * SS, h * SS), flags=cv2.INTER_NEAREST
        )
        acc = np.where(inside > 0, warped, acc)
    small = acc.reshape(h, SS, w, SS).mean(axis=(1, 3))
    small = cv2.GaussianBlur(small, (0, 0), 0.6) + rng.normal(0, 1.5, small.shape)
    return np.clip(small, 0, 255).astype(np.uint8), truth


def _check(dets, truth, tol: float) -> float:
    assert sorted(d.id for d in dets) == sorted(truth)
    errs = [np.linalg.norm(d.corners - truth[d.id], axis=1) for d in dets]
    worst = float(np.max(errs))
    assert worst < tol, f"corner error {worst:.2f} px"
    return worst


def test_ids_and_subpixel_corners() -> None:
    img, truth = _scene(np.random.default_rng(0))
    dets = MarkerDetector(DICT).detect(img)
    for d in dets:
        assert d.corners.shape == (4, 2)
    _check(dets, truth, 0.35)


@pytest.mark.parametrize("kind", ["gray16", "colour"])
def test_16_bit_and_colour_images_give_the_same_markers(kind: str) -> None:
    img, truth = _scene(np.random.default_rng(1))
    if kind == "gray16":
        other = img.astype(np.uint16) * 257
    else:
        other = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    det = MarkerDetector(DICT)
    a = {d.id: d.corners for d in det.detect(img)}
    b = {d.id: d.corners for d in det.detect(other)}
    assert a.keys() == b.keys() == truth.keys()
    for i in a:
        assert np.abs(a[i] - b[i]).max() < 0.05


def test_edge_refinement_beats_opencv_subpixel_on_small_markers() -> None:
    # OpenCV's SUBPIX corners of 20-40 px markers sit a few tenths of a pixel inside the square.
    refined, raw = [], []
    for seed in range(3):
        img, truth = _scene(np.random.default_rng(seed), sizes=(22, 36))
        for opencv_only, out in ((False, refined), (True, raw)):
            for d in MarkerDetector(DICT, opencv_only=opencv_only).detect(img):
                assert d.id in truth
                out.append(np.sum((d.corners - truth[d.id]) ** 2, axis=1))
    assert len(refined) >= 10
    assert np.sqrt(np.mean(refined)) < 0.8 * np.sqrt(np.mean(raw))
    assert np.sqrt(np.mean(refined)) < 0.35


@pytest.mark.parametrize("seed", range(3))
def test_fast_identification_agrees_with_opencv_in_every_rotation(seed: int) -> None:
    # Same ids and same corner order as OpenCV's own dictionary search, whatever the in-plane
    # rotation of the marker.
    img, truth = _scene(np.random.default_rng(seed), turns=(0, 1, 2, 3))
    fast = {d.id: d.corners for d in MarkerDetector(DICT).detect(img)}
    ref = {d.id: d.corners for d in MarkerDetector(DICT, opencv_only=True).detect(img)}
    assert fast.keys() == ref.keys() == truth.keys()
    for i in fast:
        assert np.abs(fast[i] - ref[i]).max() < 1.0
        assert np.abs(fast[i] - truth[i]).max() < 0.35


def test_codebook_corrects_as_many_bits_as_opencv_allows() -> None:
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250)
    book = Codebook.of(d)
    assert book.max_correction >= 1
    bits = cv2.aruco.Dictionary.getBitsFromByteList(d.bytesList[42:43], 6)
    turned = np.rot90(bits, 1)
    flipped = turned.copy()
    flipped[2, 3] ^= 1
    far = turned.copy()
    far[:3, :] ^= 1  # 18 bits: no marker is that close
    ids, rot = book.lookup(pack_bits(np.stack([turned, flipped, far])))
    assert ids.tolist() == [42, 42, -1]
    assert rot[:2].tolist() == [1, 1]


def test_blank_image_has_no_markers() -> None:
    assert MarkerDetector(DICT).detect(np.full((200, 300), 128, np.uint8)) == []


def test_no_candidate_to_read_is_no_code_not_an_error() -> None:
    # A heavily blurred image can leave no candidate square large enough to read.
    assert pack_bits(np.zeros((0, 4, 4), bool)).shape == (0,)
    assert pack_bits(np.zeros((0, 2, 6, 6), bool)).shape == (0, 2)
    assert pack_bits(np.eye(4, dtype=bool)[None]).tolist() == [0b1000010000100001]


def test_the_edge_fit_reads_the_whole_image_blur_in_bands() -> None:
    """The edge fit's image, blurred a band of rows at a time where it samples, gives the
    samples that bilinear interpolation of a blur of the whole image gives, bit for bit
    (bands at the image's borders and inside it, joined and apart; points off the image
    clipped to it)."""
    import cv2

    from annotator.detection.corners import BLUR_SIGMA_PX, EdgeImage

    def bilinear(img: np.ndarray, pts: np.ndarray) -> np.ndarray:
        h, w = img.shape
        x = np.clip(pts[:, 0], 0, w - 1.001)
        y = np.clip(pts[:, 1], 0, h - 1.001)
        x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
        fx, fy = x - x0, y - y0
        return (
            img[y0, x0] * (1 - fx) * (1 - fy)
            + img[y0, x0 + 1] * fx * (1 - fy)
            + img[y0 + 1, x0] * (1 - fx) * fy
            + img[y0 + 1, x0 + 1] * fx * fy
        )

    rng = np.random.default_rng(5)
    gray = rng.integers(0, 256, (97, 133), dtype=np.uint8)
    whole = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), BLUR_SIGMA_PX)
    edges = EdgeImage(gray)
    for ys in ([0.0, 3.2], [40.5, 41.7], [95.9, 120.0], [10.0, 80.0], [-5.0, 2.0]):
        pts = np.column_stack([rng.uniform(-3, 136, 200), rng.uniform(*ys, 200)])
        np.testing.assert_array_equal(edges.sample(pts[:, 0], pts[:, 1]), bilinear(whole, pts))


def test_the_blur_estimate_is_the_full_models_best_width() -> None:
    """The blur estimate's fits through the model's thin SVD choose the width that the full
    model (A P Y P^T A^T against Y, per square and width) fits best."""
    from annotator.detection import deblur

    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_1000)
    image = np.full((200, 260), 255, np.uint8)
    quads = []
    for k, (x, y) in enumerate([(20, 20), (100, 30), (180, 40), (40, 110), (130, 120)]):
        side = 48 + 6 * k
        image[y : y + side, x : x + side] = cv2.aruco.generateImageMarker(d, k, side)
        quads.append(
            [
                [x - 0.5, y - 0.5],
                [x + side - 0.5, y - 0.5],
                [x + side - 0.5, y + side - 0.5],
                [x - 0.5, y + side - 0.5],
            ]
        )
    quads_a = np.array(quads, float)
    for sigma in (0.8, 1.7, 2.6):
        gray = cv2.GaussianBlur(image, (0, 0), sigma)
        size = deblur._cell_px(quads_a, 6)
        Y = deblur._samples(gray, quads_a, deblur._model(6, 1.0)[0], 6).astype(np.float64)
        cost = []
        for width in deblur.BLUR_GRID:
            total = 0.0
            for s, y in zip(size, Y):
                _, A, P = deblur._model(6, float(deblur._quantised(np.asarray(width / s))))
                total += float(np.mean((A @ (P @ y @ P.T) @ A.T - y) ** 2))
            cost.append(total)
        best = float(deblur.BLUR_GRID[int(np.argmin(cost))])
        assert deblur.estimate_blur(gray, quads_a, 6) == best
        assert abs(best - sigma) <= 0.5


def test_merging_candidates_compares_only_nearby_squares() -> None:
    """The second search's squares are merged as comparing every pair would: those within
    2 px of a first square, corner by corner in some rotation, are left out."""
    from annotator.detection.aruco import _merge_candidates

    rng = np.random.default_rng(3)
    first = rng.uniform(0, 200, (60, 1, 2)) + rng.uniform(5, 30) * np.array(
        [[0, 0], [1, 0], [1, 1], [0, 1]], float
    )
    near = np.roll(first[:40], rng.integers(0, 4), axis=1) + rng.uniform(-1.5, 1.5, (40, 4, 2))
    more = np.concatenate([near, rng.uniform(0, 230, (30, 4, 2))])
    same = np.zeros(len(more), bool)
    for r in range(4):
        d = np.linalg.norm(more[:, None] - np.roll(first, r, axis=1)[None], axis=3).max(axis=2)
        same |= (d < 2.0).any(axis=1)
    assert 0 < same.sum() < len(more)
    np.testing.assert_array_equal(
        _merge_candidates(first, more), np.concatenate([first, more[~same]])
    )


def test_otsu_thresholds_from_integer_sums_are_the_float_ones() -> None:
    """Otsu's thresholds from integer running sums are those from float32 ones, bit for bit
    (rows of any contrast, constant ones included)."""
    from annotator.detection.identify import _otsu_thresholds

    rng = np.random.default_rng(11)
    rows = rng.integers(0, 256, (200, 576)).astype(np.uint8)
    rows[:50] = np.clip(rows[:50] // 16 + rng.integers(0, 240, (50, 1)), 0, 255)
    rows[50:60] = rng.integers(0, 256, (10, 1))
    v = np.sort(rows, axis=1).astype(np.float32)
    c = np.cumsum(v, axis=1)
    k = np.arange(1, v.shape[1])
    w0 = k / v.shape[1]
    mu0, mu1 = c[:, :-1] / k, (c[:, -1:] - c[:, :-1]) / (v.shape[1] - k)
    i = np.argmax(w0 * (1 - w0) * (mu0 - mu1) ** 2, axis=1)
    expected = 0.5 * (v[np.arange(len(v)), i] + v[np.arange(len(v)), i + 1])
    got = _otsu_thresholds(rows)
    assert got.dtype == expected.dtype
    np.testing.assert_array_equal(got, expected)
