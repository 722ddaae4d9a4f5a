"""Finding the chessboard corners of a calibration board in one image, and in every image of
a captures folder (:func:`detect_captures`).

ChArUco boards: ``cv2.aruco.CharucoDetector`` (OpenCV 4.7+ and 5.x) finds the markers, looks
again for missed ones where the board says they must be (``tryRefineMarkers``), interpolates
the chessboard corners between them and refines each with ``cornerSubPix``. A corner is kept
only if both markers next to it were found (``minMarkers = 2``), so no corner is guessed from
a single marker (the corner error on rendered boards is printed by
``benchmarks/bench_calibrate.py``).

Boards as people print and film them: when the board is not found as it is, the image is
searched again colour-inverted (white markers on black: some tools print boards so, and a
board shown on a screen can look so) unless board.yaml says which, and flipped left to right.
A board that reads only in the flipped image is either filmed by a mirrored camera (a webcam
in "selfie" mode) or seen from behind, through the paper; the detection cannot tell which, so
:func:`detect_captures` maps the corners back to the image as recorded (``u -> W-1-u``, the
same corner ids) and marks the view ``flipped``; :mod:`.readings` decides between the two by
the geometry of the rig.

Plain chessboards: ``cv2.findChessboardCorners`` (``findChessboardCornersSB`` when it fails;
whole views only) and ``cornerSubPix``, then the corners
numbered in the board's order: rows and columns turned so that the board's x and y axes keep
their handedness in the image (the printed face is seen from the front), and the half-turn
told by the colour of the square beyond corner 0 (black at the board's origin).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from annotator.calibration.board import BoardSpec
from annotator.calibration.captures import Captures, read_images
from annotator.calibration.records import View
from annotator.io.images import to_gray8


@dataclass(frozen=True)
class BoardDetection:
    """The board as found in one image.

    Attributes:
        ids: (n,) chessboard corner ids found (see :mod:`annotator.calibration.board`).
        corners: (n, 2) their pixel positions (OpenCV convention: pixel centres at integers),
            in the mirrored image if ``mirrored``.
        markers: How many of the board's markers were identified.
        foreign_markers: Markers of the dictionary identified in the image whose id is not on
            the board (a sign that the board description is wrong).
        inverted: The board was found in the colour-inverted image.
        mirrored: The board was found only in the mirrored image.
    """

    ids: np.ndarray
    corners: np.ndarray
    markers: int
    foreign_markers: int = 0
    inverted: bool = False
    mirrored: bool = False

    @property
    def found(self) -> bool:
        """True if at least one chessboard corner was found."""
        return len(self.ids) > 0


#: A reading with this fraction of the board's corners is taken without trying the others.
GOOD_ENOUGH = 0.5


class BoardDetector:
    """Detects one :class:`BoardSpec` board in images (one detector object, reused).

    Args:
        spec: The board.
        mirrored: Look for the board in the mirrored image: None (default) when it is not
            found as it is, True always first (a camera known to be mirrored), False never.
    """

    def __init__(self, spec: BoardSpec, *, mirrored: bool | None = None) -> None:
        self.spec = spec
        self.mirrored = mirrored
        #: Try the mirrored / inverted image first (set once a camera's images read so).
        self.prefer_mirrored = False
        self.prefer_inverted = False
        if spec.has_markers:
            charuco = cv2.aruco.CharucoParameters()
            charuco.minMarkers = 2
            charuco.tryRefineMarkers = True
            self._detector = cv2.aruco.CharucoDetector(
                spec.cv_board, charuco, cv2.aruco.DetectorParameters(), cv2.aruco.RefineParameters()
            )

    def _attempts(self) -> list[tuple[bool, bool]]:
        """(inverted, mirrored) readings to try, in order."""
        polarities = [False, True] if self.spec.inverted is None else [bool(self.spec.inverted)]
        if self.prefer_inverted:
            polarities.reverse()
        if not self.spec.has_markers:
            # A plain chessboard's corners are found in either polarity (inverted, it is the
            # same board turned half a turn), and it looks the same mirrored.
            return [(False, False)]
        if self.mirrored is False:
            mirrors = [False]
        else:
            mirrors = [True] if self.mirrored else [False, True]
            if self.prefer_mirrored:
                mirrors.reverse()
        return [(inv, mir) for mir in mirrors for inv in polarities]

    def detect(self, image: np.ndarray) -> BoardDetection:
        """Find the board's chessboard corners in an 8/16-bit grey or colour image."""
        gray = to_gray8(image)
        best: BoardDetection | None = None
        for inverted, mirrored in self._attempts():
            img = 255 - gray if inverted else gray
            img = cv2.flip(img, 1) if mirrored else img
            det = self._read(img, inverted, mirrored)
            if (
                best is None
                or len(det.ids) > len(best.ids)
                or (not best.found and det.markers > best.markers)
            ):
                best = det
            if len(best.ids) >= GOOD_ENOUGH * self.spec.corner_count:
                break
        assert best is not None
        return best

    def _read(self, gray: np.ndarray, inverted: bool, mirrored: bool) -> BoardDetection:
        if not self.spec.has_markers:
            ids, corners = chessboard_corners(gray, self.spec)
            return BoardDetection(ids, corners, 0, 0, inverted, mirrored)
        corners, ids, _marker_corners, marker_ids = self._detector.detectBoard(gray)
        marker_ids = np.zeros(0, int) if marker_ids is None else np.asarray(marker_ids).reshape(-1)
        on_board = marker_ids < self.spec.marker_count
        counts = (int(on_board.sum()), int((~on_board).sum()))
        if ids is None or corners is None or len(ids) == 0:
            return BoardDetection(
                np.zeros(0, np.int64), np.zeros((0, 2)), *counts, inverted, mirrored
            )
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        corners = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
        order = np.argsort(ids, kind="stable")
        return BoardDetection(ids[order], corners[order], *counts, inverted, mirrored)


def chessboard_corners(gray: np.ndarray, spec: BoardSpec) -> tuple[np.ndarray, np.ndarray]:
    """The inner corners of a plain chessboard in a uint8 image, numbered as the board's
    (ids, (n, 2) pixels); none unless the whole board is in view."""
    cols, rows = spec.squares_x - 1, spec.squares_y - 1
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    found, pts = cv2.findChessboardCorners(gray, (cols, rows), flags=flags)
    if not found:  # the sector-based detector finds boards the classic one misses, slowly
        found, pts = cv2.findChessboardCornersSB(gray, (cols, rows))
    if not found or pts is None or len(pts) != cols * rows:
        return np.zeros(0, np.int64), np.zeros((0, 2))
    # Sub-pixel corners over a window of about half a square: on noisy, blurred boards it
    # beats OpenCV's customary 5x5 window (benchmarks/bench_calibrate.py).
    grid: np.ndarray = np.asarray(pts, np.float32).reshape(rows, cols, 2)
    step = min(
        float(np.linalg.norm(np.diff(grid, axis=1), axis=2).min()),
        float(np.linalg.norm(np.diff(grid, axis=0), axis=2).min()),
    )
    half = int(np.clip(0.25 * step, 3, 11))
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    pts = cv2.cornerSubPix(gray, grid.reshape(-1, 1, 2), (half, half), (-1, -1), criteria)
    grid = np.asarray(pts, np.float64).reshape(rows, cols, 2)
    # Handedness: the board's x (along a row) turned to its y (down the columns) is clockwise
    # in the image, as seen from the front.
    dx, dy = grid[0, -1] - grid[0, 0], grid[-1, 0] - grid[0, 0]
    if dx[0] * dy[1] - dx[1] * dy[0] < 0:
        grid = grid[:, ::-1]
    # The half turn: the square diagonally beyond corner 0 is the board's origin square, black.
    origin = grid[0, 0] + 0.5 * (grid[0, 0] - grid[1, 1])
    beside = grid[0, 0] + 0.5 * (grid[0, 1] - grid[1, 0])  # its neighbour along x: white
    if _grey_at(gray, origin) > _grey_at(gray, beside):
        grid = grid[::-1, ::-1]
    return np.arange(cols * rows, dtype=np.int64), grid.reshape(-1, 2)


def _grey_at(gray: np.ndarray, uv: np.ndarray) -> float:
    """Mean grey level of a 3x3 patch at ``uv`` (clipped to the image)."""
    h, w = gray.shape
    u = int(np.clip(round(uv[0]), 1, w - 2))
    v = int(np.clip(round(uv[1]), 1, h - 2))
    return float(gray[v - 1 : v + 2, u - 1 : u + 2].mean())


@dataclass(frozen=True)
class CapturesDetection:
    """The board in every image of a captures folder.

    Attributes:
        views: One per camera and shot, shot by shot (what :func:`solve_rig` takes).
        sizes: Each camera's image size ``(width, height)``, in camera order.
        foreign_markers: Markers of the dictionary seen with ids not on the board, in all.
        flipped: Per camera, the shots whose board read only in the flipped image.
        inverted: Per camera, the views whose board read colour-inverted.

    Every view's corners are in the image as recorded (:mod:`.readings` turns them into a
    mirrored camera's when it decides a camera is one).
    """

    views: list[View]
    sizes: list[tuple[int, int]]
    foreign_markers: int
    flipped: list[int] = field(default_factory=list)
    inverted: list[int] = field(default_factory=list)


def detect_captures(
    captures: Captures,
    board: BoardSpec,
    *,
    expected_sizes: Mapping[str, tuple[int, int]] | None = None,
    expected_source: Path | None = None,
    progress: Callable[[Iterator], Iterator] | None = None,
) -> CapturesDetection:
    """Detect ``board`` in every image of ``captures`` (the keywords are those of
    :func:`read_images`, whose UserErrors pass through)."""
    detectors = [BoardDetector(board) for _ in captures.cameras]
    views: list[View] = []
    sizes: dict[int, tuple[int, int]] = {}
    foreign = 0
    flipped = [0] * len(captures.cameras)
    found = [0] * len(captures.cameras)
    inverted = [0] * len(captures.cameras)
    for c, s, img in read_images(
        captures, expected_sizes=expected_sizes, expected_source=expected_source, progress=progress
    ):
        width = int(img.shape[1])
        sizes[c] = (width, int(img.shape[0]))
        det = detectors[c].detect(img)
        corners = det.corners.copy()
        if det.mirrored:  # back to the image as recorded
            corners[:, 0] = width - 1 - corners[:, 0]
        views.append(View(c, s, det.ids, corners, det.markers, det.mirrored and det.found))
        foreign += det.foreign_markers
        if det.found:
            found[c] += 1
            flipped[c] += int(det.mirrored)
            inverted[c] += int(det.inverted)
            detectors[c].prefer_mirrored = 2 * flipped[c] > found[c]
            detectors[c].prefer_inverted = 2 * inverted[c] > found[c]
    return CapturesDetection(
        views,
        [sizes[c] for c in range(len(captures.cameras))],
        foreign,
        flipped,
        inverted,
    )
