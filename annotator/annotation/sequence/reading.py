"""Reading a sequence's frames: the markers of every camera of one frame, with the measured
depth at each marker's centre (:func:`read_frame`), and what a frame saw of each instance
(:class:`Seen`)."""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from annotator.annotation.completeness import image_quality
from annotator.annotation.consensus import pose_instance
from annotator.annotation.frame_quality import Streak, frame_streak
from annotator.annotation.settings import AnnotateSettings
from annotator.dataset import Dataset
from annotator.dataset.figures import (
    ImageQuality,
    MarkerUse,
)
from annotator.dataset.model import Frame
from annotator.detection import MarkerDetector
from annotator.detection.aruco import ImageReading
from annotator.io.images import to_gray8
from annotator.markers.texture import marker_bits
from annotator.pnp import (
    Observation,
)


@dataclass
class FrameReading:
    """What one frame's cameras read: per camera its :class:`ImageReading` (markers only:
    the unread candidates are dropped), the measured depth (mm, NaN: none) at the centre of
    each marker of the depth camera, in the order of its markers, and image quality."""

    frame: str
    readings: list[ImageReading]
    marker_depth: np.ndarray
    quality: dict[str, ImageQuality]
    #: Per camera, the motion streak its markers show (None: none told).
    streaks: list[Streak | None] = field(default_factory=list)

    def streak_px(self, camera: int, marker: int | None = None) -> float:
        """The streak's length (px) in camera ``camera`` (at ``marker`` when it was measured
        there), 0 when not measured."""
        s = self.streaks[camera] if camera < len(self.streaks) else None
        if s is None:
            return 0.0
        return s.per_marker.get(marker, s.length_px) if marker is not None else s.length_px


def read_frame(ds: Dataset, frame: Frame, detector: MarkerDetector) -> FrameReading:
    """Read the markers of every camera of ``frame`` (UserError for a missing or mis-sized
    image, naming the file), and the motion streak of each camera's image."""
    return read_frame_sampled(ds, frame, detector, step=1)[0]


def read_frame_sampled(
    ds: Dataset, frame: Frame, detector: MarkerDetector, *, step: int
) -> tuple[FrameReading, np.ndarray | None]:
    """:func:`read_frame`, and the frame's depth map (None: none) at every ``step``-th pixel
    of every ``step``-th row: what :func:`~.visibility.frame_visibility` reads of it, kept
    so that each depth file is decoded once (decoding costs as much as what it is read for)."""
    grays = [to_gray8(frame.read_image(cam)) for cam in ds.rig.cameras]
    readings = [detector.read(g) for g in grays]
    quality = image_quality(ds, readings, grays)
    streaks = []
    for cam, r, g in zip(ds.rig.cameras, readings, grays):
        streak = frame_streak(g, [(d.id, d.corners, _grid(ds.dictionary, d.id)) for d in r.markers])
        streaks.append(streak)
        if streak is not None:
            quality[cam.name].extra["motion_blur_px"] = streak.length_px
            quality[cam.name].extra["motion_blur_deg"] = streak.angle_deg
    kept = [
        ImageReading(
            r.markers, np.zeros((0, 4, 2)), np.zeros((0, 1, 1), bool), np.zeros(0), r.blur_px
        )
        for r in readings
    ]
    depth = frame.read_depth(ds.rig)
    marker_depth = np.zeros(0)
    samples = None
    if depth is not None and ds.rig.depth is not None:
        j = [c.name for c in ds.rig.cameras].index(ds.rig.depth.camera)
        marker_depth = _depths_at(depth, [d.corners for d in readings[j].markers])
        samples = depth if step == 1 else depth[::step, ::step].copy()
    return FrameReading(frame.name, kept, marker_depth, quality, streaks), samples


@functools.cache
def _grid(dictionary_name: str, marker_id: int) -> np.ndarray:
    """A marker's cells as printed (border included), cached: every frame reads the same."""
    return marker_bits(dictionary_name, marker_id)


def _depths_at(depth: np.ndarray, corners: list[np.ndarray]) -> np.ndarray:
    """Per marker (its (4, 2) corners; its centre in the image, as a detected marker's is),
    the median measured depth (mm) in the 5x5 pixels round its centre (those in the image),
    NaN where fewer than 5 were measured: all markers at once (a frame has dozens, and
    ``np.median`` called per marker took longer than the rest of this)."""
    if not corners:
        return np.zeros(0)
    h, w = depth.shape
    centres = np.round(np.stack(corners).mean(axis=1)).astype(int)  # (M, 2): u, v
    d = np.arange(-2, 3)
    v = centres[:, 1, None, None] + d[None, :, None]
    u = centres[:, 0, None, None] + d[None, None, :]
    inside = (v >= 0) & (v < h) & (u >= 0) & (u < w)
    patch = np.where(inside, depth[np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)], np.nan)
    patch = np.sort(patch.reshape(len(corners), -1), axis=1)  # NaN (none) last
    n = np.isfinite(patch).sum(axis=1)
    rows = np.arange(len(corners))
    lo = patch[rows, np.maximum(n - 1, 0) // 2]
    hi = patch[rows, np.maximum(n, 1) // 2]
    # np.median's own arithmetic: the middle value, or the mean of the middle two in the
    # depth's own precision.
    middle = np.where(n % 2 == 1, lo, (lo + hi) / lo.dtype.type(2))
    return np.where(n >= 5, middle.astype(np.float64), np.nan)


@dataclass
class _Edge:
    """One instance as one frame saw it: its pose in that frame's rig (the fixed rig's
    consensus) and the observations that consensus used."""

    rig_T_model: np.ndarray
    obs: list[Observation]


@dataclass
class Seen:
    """One frame: every observation of each instance (with the measured depth at each
    marker, NaN where none), and each instance as the frame's own consensus poses it
    (:meth:`edge`, worked out when first asked: most frames are placed by tracking)."""

    raw: dict[tuple[str, str], list[tuple[Observation, float]]]
    _edges: dict[tuple[str, str], _Edge | None] = field(default_factory=dict)

    def edge(self, ds: Dataset, key: tuple[str, str], s: AnnotateSettings) -> _Edge | None:
        """The instance posed from this frame alone (None: its markers do not pose it)."""
        if key not in self._edges:
            cams = ds.rig.cameras
            obs = [o for o, _ in self.raw[key]]
            r = pose_instance(ds, key[0], key[1], obs, s)
            edge = None
            if r is not None:
                used = {(c.name, i) for c in cams for i in r.markers.get(c.name, MarkerUse()).used}
                kept = [o for o in obs if (cams[o.camera].name, o.marker_id) in used]
                edge = _Edge(r.T, kept)
            self._edges[key] = edge
        return self._edges[key]

    def edges(self, ds: Dataset, s: AnnotateSettings) -> dict[tuple[str, str], _Edge]:
        """Every instance the frame poses on its own."""
        found = {k: self.edge(ds, k, s) for k in sorted(self.raw)}
        return {k: e for k, e in found.items() if e is not None}


def depth_lookup(reading: FrameReading, depth_cam: int | None) -> dict[tuple[int, int], float]:
    if depth_cam is None or reading.marker_depth.size == 0:
        return {}
    markers = reading.readings[depth_cam].markers
    return {(depth_cam, d.id): float(z) for d, z in zip(markers, reading.marker_depth)}
