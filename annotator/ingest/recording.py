"""What every recorder's file gives ingest: colour frames with their times, depth frames
paired with them, the cameras' calibration, and the frames that could not be used.

The readers (:mod:`.rosbag`, :mod:`.kinect`, :mod:`.record3d`, :mod:`.video`) each build a
:class:`Recording`; :mod:`.scene` reads frames from it without knowing which recorder wrote
it. Depth comes in millimetres on the depth camera's own grid; :mod:`.registration` redraws
it on the colour camera's grid when the recorder did not.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from annotator.errors import UserError
from annotator.geometry.camera import Camera


@dataclass(frozen=True)
class DepthGeometry:
    """The depth camera of a recording.

    Attributes:
        camera: Its intrinsics and size (the grid its depth frames are on).
        colour_T_depth: 4x4, mm: depth-camera points into the colour camera; None when the
            depth frames already lie on the colour camera's grid (aligned by the recorder).
        unit_mm: Millimetres per unit of its raw 16-bit frames (what the file says).
    """

    camera: Camera
    colour_T_depth: np.ndarray | None
    unit_mm: float

    @property
    def registered(self) -> bool:
        """Whether the depth frames already lie on the colour camera's grid."""
        return self.colour_T_depth is None


@dataclass(frozen=True)
class Calibration:
    """The cameras as the file describes them: ``colour`` (named ``colour``), optional
    ``depth``, and ``origin``, where in the file they were read (the summary says it)."""

    colour: Camera
    depth: DepthGeometry | None
    origin: str


@dataclass(frozen=True)
class Decoded:
    """One frame read from a recording: its colour image (BGR or grey, as stored), its depth
    (float mm on the depth camera's grid, NaN = none; None when not asked for or absent), or
    ``problem``, why it cannot be used (a frame that failed to decode, or decoded partly)."""

    index: int
    colour: np.ndarray | None
    depth_mm: np.ndarray | None = None
    problem: str | None = None


@dataclass
class Recording:
    """A recorder's file opened for ingest (built by the readers).

    Attributes:
        path: The file (or bag folder).
        kind: What it is (``ROS 1 bag``, ``Azure Kinect recording``...).
        times: Each colour frame's time (s, the file's own clock), in order.
        labels: How frames.json names each colour frame's origin (its message or frame index).
        depth_for: For each colour frame, the index of its depth partner (None: none).
        streams: The streams read: ``{"colour": topic or track, "depth": ...}``.
        calibration: The cameras (None when the file carries none: a plain video).
        dropped: Frames already known to be unusable: ``(label, why)``.
        ended_early: Why the file stops before its end (None if it does not).
        notes: What else the summary must say (a stream left out, and why).
        depth_times: Each depth frame's time (s, the same clock), when the file has them:
            how far apart the streams are when none pair.
    """

    path: Path
    kind: str
    times: list[float | None]
    labels: list[str | int]
    depth_for: list[int | None]
    streams: dict[str, str]
    calibration: Calibration | None = None
    dropped: list[tuple[str | int, str]] = field(default_factory=list)
    ended_early: str | None = None
    notes: list[str] = field(default_factory=list)
    depth_times: list[float | None] = field(default_factory=list)

    def decode(self, indices: Sequence[int], *, depth: bool) -> Iterator[Decoded]:
        """The colour frames ``indices`` (increasing), with their depth when ``depth``."""
        raise NotImplementedError

    def depth_unit(self) -> float:
        """Millimetres per unit of the raw depth frames: what the file's calibration says
        (1 without one)."""
        cal = self.calibration
        return cal.depth.unit_mm if cal is not None and cal.depth is not None else 1.0

    def depth_label(self, i: int) -> str | int | None:
        """How frames.json names colour frame ``i``'s depth: its depth frame's index (a
        reader of files names the file)."""
        return self.depth_for[i]

    def depth_where(self, i: int) -> Path | str:
        """Where colour frame ``i``'s depth is, as a message names it."""
        return f"{self.path} (depth of frame {self.labels[i]})"


def check_calibration(cal: Calibration, path: Path) -> None:
    """Refuse, in one line naming the file, a calibration no camera can have (zero, negative
    or non-finite focal lengths or sizes, non-finite distortion): read before anything is
    written, so that ``--rig-from-source`` never puts it in a dataset."""
    cams = [("colour", cal.colour)] + ([("depth", cal.depth.camera)] if cal.depth else [])
    for what, cam in cams:
        K = np.asarray(cam.K, np.float64)
        why = None
        if not (cam.width > 0 and cam.height > 0):
            why = f"a size of {cam.width}x{cam.height}"
        elif K.shape != (3, 3) or not np.isfinite(K).all():
            why = "intrinsics that are not finite numbers"
        elif not (K[0, 0] > 0 and K[1, 1] > 0):
            why = f"focal lengths fx {K[0, 0]:g}, fy {K[1, 1]:g} (they must be above 0)"
        elif not np.isfinite(np.asarray(cam.dist, np.float64)).all():
            why = "distortion coefficients that are not finite numbers"
        if why:
            raise UserError(
                f"its {cal.origin} gives the {what} camera {why}: the file's calibration is "
                "unusable (nothing was written)",
                path=path,
            )


def damaged_rows(depth_mm: np.ndarray) -> tuple[int, int] | None:
    """The first and last row of a depth frame that hold noise rather than a surface (bytes
    of a damaged file decoded as depth: most of a row's pixels jump by more than 10 % from
    both of their neighbours), or None. Real depth jumps only at edges, a few pixels a row.

    >>> d = np.full((40, 50), 700.0)
    >>> d[10:14] = np.random.default_rng(0).uniform(0, 65535, (4, 50))
    >>> damaged_rows(d), damaged_rows(np.full((40, 50), 700.0))
    ((10, 13), None)
    """
    d = np.asarray(depth_mm, np.float64)
    if d.ndim != 2 or d.shape[1] < 3:
        return None
    mid, left, right = d[:, 1:-1], d[:, :-2], d[:, 2:]
    with np.errstate(invalid="ignore"):
        tol = 0.1 * mid
        spike = (np.abs(mid - left) > tol) & (np.abs(mid - right) > tol)
        valid = np.isfinite(mid) & np.isfinite(left) & np.isfinite(right) & (mid > 0)
    counted = valid.sum(axis=1)
    bad = np.flatnonzero((counted >= 8) & ((spike & valid).sum(axis=1) > 0.3 * counted))
    return (int(bad[0]), int(bad[-1])) if bad.size else None


def nearest_gaps(colour: Sequence[float | None], depth: Sequence[float | None]) -> list[float]:
    """For each colour time, how far (s) the nearest depth time is.

    >>> nearest_gaps([0.0, 1.0, None], [0.1, 0.8])
    [0.1, 0.19999999999999996]
    """
    known = sorted(t for t in depth if t is not None)
    out: list[float] = []
    for t in colour:
        if t is None or not known:
            continue
        k = bisect.bisect_left(known, t)
        out.append(min(abs(known[j] - t) for j in (k - 1, k) if 0 <= j < len(known)))
    return out


def isolated_spikes(depth_mm: np.ndarray) -> np.ndarray:
    """The pixels of a depth frame unlike all of their four neighbours (two or three at the
    frame's border), which agree among themselves (a damaged byte, or a sensor's speckle):
    more than 5 % off their median, which the neighbours are within 2 % of. An edge's pixels
    are not: their neighbours differ.

    >>> d = np.full((5, 5), 700.0); d[2, 2] = 538.0; d[0, 0] = 900.0; d[:, 4] = 900.0
    >>> np.argwhere(isolated_spikes(d)).tolist()
    [[0, 0], [2, 2]]
    """
    d = np.asarray(depth_mm, np.float64)
    if d.ndim != 2 or min(d.shape) < 2:
        return np.zeros(d.shape, bool)
    p = np.pad(np.where(d > 0, d, np.inf).astype(np.float32), 1, constant_values=np.inf)
    a, b, c, e = p[:-2, 1:-1], p[2:, 1:-1], p[1:-1, :-2], p[1:-1, 2:]  # no depth: +inf
    # The four neighbours sorted (a <= b <= c <= e) by a sorting network: the finite first.
    a, b = np.minimum(a, b), np.maximum(a, b)
    c, e = np.minimum(c, e), np.maximum(c, e)
    a, c = np.minimum(a, c), np.maximum(a, c)
    b, e = np.minimum(b, e), np.maximum(b, e)
    b, c = np.minimum(b, c), np.maximum(b, c)
    three, four = np.isfinite(c), np.isfinite(e)
    with np.errstate(invalid="ignore"):
        mid = np.where(four, (b + c) / 2, np.where(three, b, (a + b) / 2))
        top = np.where(four, e, np.where(three, c, b))
        out = (top - a <= 0.02 * mid) & (np.abs(d - mid) > 0.05 * mid)
    return out & np.isfinite(b) & np.isfinite(d) & (d > 0)


def pair_by_time(
    colour: Sequence[float | None], depth: Sequence[float | None], tolerance_s: float
) -> list[int | None]:
    """For each colour time, the index of the nearest depth time within ``tolerance_s``
    (None if there is none, or no time).

    >>> pair_by_time([0.0, 0.033, 0.1], [0.001, 0.034, 0.5], 0.005)
    [0, 1, None]
    """
    known = sorted((t, i) for i, t in enumerate(depth) if t is not None)
    times = [t for t, _ in known]
    out: list[int | None] = []
    for t in colour:
        if t is None or not known:
            out.append(None)
            continue
        k = bisect.bisect_left(times, t)
        near = [j for j in (k - 1, k) if 0 <= j < len(known)]
        best = min(near, key=lambda j: (abs(times[j] - t), j))
        out.append(known[best][1] if abs(times[best] - t) <= tolerance_s else None)
    return out


def transform(R: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
    """A 4x4 transform from a rotation and a translation (mm)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, np.float64).reshape(3, 3)
    T[:3, 3] = np.asarray(t_mm, np.float64).reshape(3)
    return T


def quaternion_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """The rotation of a unit quaternion ``(x, y, z, w)`` (ROS order), normalised first.

    >>> np.round(quaternion_matrix(0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)), 6).tolist()
    [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    """
    q = np.array([x, y, z, w], np.float64)
    n = float(np.linalg.norm(q))
    if n < 1e-12:
        return np.eye(3)
    x, y, z, w = q / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def join_depth(
    events: Iterator[tuple[str, int, Decoded | np.ndarray | str]],
    depth_wanted: dict[int, list[int]],
) -> Iterator[Decoded]:
    """Colour frames joined with their depth partners, in colour order.

    ``events`` come in file order: ``("colour", i, Decoded)`` and ``("depth", j, depth mm
    or why it is unusable)``; ``depth_wanted`` maps a depth index to the colour indices it
    belongs to (one depth frame may be the nearest of two colour frames). A colour frame waits for its depth (later frames wait behind it, so that the
    order holds); a frame whose depth is damaged or never comes is given as a problem.
    """
    pending: dict[int, Decoded] = {}
    depth_of: dict[int, np.ndarray | str] = {}
    waiting_for = {i for own in depth_wanted.values() for i in own}

    def ready(final: bool) -> Iterator[Decoded]:
        for i in sorted(pending):
            if i in waiting_for and i not in depth_of and not final:
                return
            d = pending.pop(i)
            got = depth_of.pop(i, None)
            if d.problem is not None:
                yield d
            elif isinstance(got, str):
                yield Decoded(i, None, None, f"its depth frame: {got}")
            elif isinstance(got, np.ndarray) and (rows := damaged_rows(got)) is not None:
                noise = f"rows {rows[0]}-{rows[1]} hold noise (the file is damaged there)"
                yield Decoded(i, None, None, f"its depth frame: {noise}")
            elif isinstance(got, np.ndarray):
                yield Decoded(i, d.colour, got)
            elif i in waiting_for:
                yield Decoded(i, None, None, "its depth frame is missing from the file")
            else:
                yield d

    for kind, k, item in events:
        if kind == "colour":
            assert isinstance(item, Decoded)
            pending[k] = Decoded(k, item.colour, item.depth_mm, item.problem)
        elif k in depth_wanted:
            assert not isinstance(item, Decoded)
            for i in depth_wanted[k]:
                depth_of[i] = item
        yield from ready(False)
    yield from ready(True)
