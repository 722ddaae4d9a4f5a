"""A board that reads only in the flipped image: a mirrored camera, or a board seen from behind.

Two different things make a camera's board read only once its image is flipped left to right:

- a **mirrored camera** (a webcam in "selfie" mode) stores every image mirrored: its proper
  pinhole image is the flipped one, the corners are kept where the flipped image has them,
  and its rig entry says ``flip: horizontal``;
- a **board seen from behind** (a camera on the far side of the board, or a board turned
  round in some shots) shows its print through the paper, mirrored: the camera is an ordinary
  one, and the corners found in the flipped image belong, mapped back (``u -> W-1-u``, the
  same ids), to the image as recorded: the board's points lie in its plane, so seen from
  behind they are just a board pose with the camera on the other side.

Each camera alone fits either reading equally well (the mirror image of a planar board's
view is another planar view), so only the other cameras can tell. Per camera, a single
question decides: is it mirrored (then its views' corners are flipped, in every shot) or
not. Which side of the board a view saw then follows per shot (it read flipped exactly when
it is mirrored or saw the back, not both). The test: each camera alone (OpenCV's
``calibrateCamera``) gives the board pose in each of its views; against a camera already
placed, the relative pose over the shots both saw is rigid under the right reading and
drifts under the wrong one (a mirror in one camera's frame is no rigid motion of the
board). The spread is measured as the distance (mm, RMS over the board's corners) between
each shot's board seen through the robust mean relative pose and the board as the camera saw
it; the smaller spread wins. Geometry cannot tell a whole rig mirrored from one that is not:
turning every camera's reading the other way turns each camera's pair (mirrored, mostly
behind the board) into its opposite. Of the two, the one that asks for fewer of those
oddities (mirrored cameras and cameras that saw mostly the board's back, summed over the
cameras) is taken: a board printed mirrored (every camera in front reads it flipped, a
camera behind it reads it as it is) is then a board seen from behind by ordinary cameras,
not a rig of mirrored cameras one of which sees the back. When both ask for as many (every
camera reads the board flipped), the one in which more cameras saw mostly the board's front
(of two as good, the one with fewer mirrored cameras).

A view whose pose does not agree with the camera it is compared with while its board read
the other way than in that camera's other shots (an image stored mirrored among plain ones)
is left out, with the reason.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from annotator.calibration.board import BoardSpec
from annotator.calibration.records import CalibrationSettings, View
from annotator.calibration.rig import robust_mean_transform
from annotator.calibration.single import calibrate_camera, opencv_flags, screen_views
from annotator.errors import UserError
from annotator.geometry.transforms import invert

#: The winning reading's spread must be below this fraction of the other's to count as
#: decided by the geometry (else the majority of the camera's views decides).
DECISIVE = 0.5
#: A view is off when its board lies this many times the camera's median spread away ...
OFF_FACTOR = 8.0
#: ... and at least this fraction of the board's diagonal.
OFF_BOARD = 0.05


@dataclass(frozen=True)
class CameraReading:
    """How one camera's views are read.

    Attributes:
        camera: Its name.
        mirrored: A mirrored camera (``flip: horizontal``): its corners are the flipped
            image's.
        behind: Shots in which it saw the board from behind.
        flipped: Shots whose board read only in the flipped image.
        spread_mm: Spread of its board poses against the camera it was compared with, as
            read (``chosen``) and the other way (``other``); NaN when not measured.
        reason: One line for the summary and the report.
    """

    camera: str
    mirrored: bool
    behind: tuple[str, ...]
    flipped: tuple[str, ...]
    spread_mm: tuple[float, float]
    reason: str

    def to_dict(self) -> dict:
        """For report.json."""
        return {
            "mirrored": self.mirrored,
            "behind_shots": list(self.behind),
            "flipped_shots": list(self.flipped),
            "spread_mm": [None if not np.isfinite(v) else round(v, 3) for v in self.spread_mm],
            "reason": self.reason,
        }


@dataclass(frozen=True)
class Readings:
    """Every camera's reading and the views as the calibration takes them."""

    cameras: tuple[CameraReading, ...]
    views: list[View]

    @property
    def mirrored(self) -> list[str]:
        """The mirrored cameras (``flip: horizontal``)."""
        return [r.camera for r in self.cameras if r.mirrored]


_MIRROR = np.diag([-1.0, 1.0, 1.0])
_PLANE = np.diag([1.0, 1.0, -1.0])


def mirrored_pose(cam_T_board: np.ndarray) -> np.ndarray:
    """The board pose that the flipped image's corners give, from the recorded image's: a
    mirror ``x -> -x`` in the camera frame, made a proper rotation by the mirror ``z -> -z``
    of the board frame, which moves no point of the board (they lie at z = 0)."""
    out = cam_T_board.copy()
    out[:3, :3] = _MIRROR @ cam_T_board[:3, :3] @ _PLANE
    out[:3, 3] = _MIRROR @ cam_T_board[:3, 3]
    return out


def flip_view(view: View, width: int) -> View:
    """``view`` with its corners in the flipped image (``u -> W-1-u``)."""
    corners = view.corners.copy()
    corners[:, 0] = width - 1 - corners[:, 0]
    return replace(view, corners=corners)


def decide_readings(
    views: Sequence[View],
    *,
    cameras: Sequence[str],
    sizes: Sequence[tuple[int, int]],
    shots: Sequence[str],
    board: BoardSpec,
    options: CalibrationSettings | None = None,
) -> Readings:
    """Decide for each camera whether it is mirrored (see the module docstring); the views
    come back with a mirrored camera's corners flipped and the views left out marked."""
    opts = options or CalibrationSettings()
    flipped = [[v.shot for v in views if v.camera == c and v.flipped] for c in range(len(cameras))]
    if not any(flipped):  # the common case: nothing read flipped, nothing to decide
        return Readings(
            tuple(CameraReading(name, False, (), (), (np.nan, np.nan), "") for name in cameras),
            list(views),
        )
    poses = _camera_poses(views, cameras, sizes, shots, board, opts)
    mirrored, spreads, parent = _choose(poses, views, cameras, board)
    off = _off_views(poses, mirrored, parent, views, cameras, board)
    out_views = []
    for v in views:
        if (v.camera, v.shot) in off:
            v = replace(v, rejected=off[(v.camera, v.shot)])
        out_views.append(flip_view(v, sizes[v.camera][0]) if mirrored[v.camera] else v)
    readings = tuple(
        _reading(c, cameras, shots, views, mirrored, spreads, parent) for c in range(len(cameras))
    )
    return Readings(readings, out_views)


def _camera_poses(
    views: Sequence[View],
    cameras: Sequence[str],
    sizes: Sequence[tuple[int, int]],
    shots: Sequence[str],
    board: BoardSpec,
    opts: CalibrationSettings,
) -> list[dict[int, np.ndarray]]:
    """Per camera, ``shot -> cam_T_board`` of its views as recorded, from OpenCV's
    calibrateCamera on that camera alone (empty for a camera it cannot calibrate: the
    calibration itself will say why)."""
    usable = screen_views(views, cameras, shots, board, opts, [])
    out: list[dict[int, np.ndarray]] = []
    for c, name in enumerate(cameras):
        mine = [v for v in usable if v.camera == c]
        if len(mine) < 3:
            out.append({})
            continue
        try:
            _, _, poses, _ = calibrate_camera(
                mine, board, sizes[c], opencv_flags(4), [], name, shots, 5
            )
        except UserError:
            out.append({})
            continue
        out.append({s: T for (_, s), T in poses.items()})
    return out


def _spread(
    a: dict[int, np.ndarray], b: dict[int, np.ndarray], board: BoardSpec
) -> tuple[float, dict[int, float]]:
    """The spread (mm) of ``b``'s board poses against ``a``'s over their common shots: per
    shot, the RMS distance over the board's corners between the board moved into ``b``'s
    frame by the robust mean relative pose and as ``b`` saw it; and its median."""
    common = sorted(set(a) & set(b))
    if len(common) < 2:
        return float("nan"), {}
    rel = np.stack([b[s] @ invert(a[s]) for s in common])
    mean = robust_mean_transform(rel)
    X = board.corners
    per_shot = {}
    for s in common:
        p = X @ (mean @ a[s])[:3, :3].T + (mean @ a[s])[:3, 3]
        q = X @ b[s][:3, :3].T + b[s][:3, 3]
        per_shot[s] = float(np.sqrt(np.mean(np.sum((p - q) ** 2, axis=1))))
    return float(np.median(list(per_shot.values()))), per_shot


def _choose(
    poses: list[dict[int, np.ndarray]],
    views: Sequence[View],
    cameras: Sequence[str],
    board: BoardSpec,
) -> tuple[list[bool], list[tuple[float, float]], list[int | None]]:
    """Each camera mirrored or not, the spreads (chosen, other) that decided, and the camera
    each was compared with (None: the first placed, or none shared shots with it)."""
    C = len(cameras)
    mirrored = [False] * C
    spreads = [(float("nan"), float("nan"))] * C
    parent: list[int | None] = [None] * C
    as_read = [poses[c] for c in range(C)]
    as_mirrored = [{s: mirrored_pose(T) for s, T in poses[c].items()} for c in range(C)]
    placed = {0}
    while len(placed) < C:
        common, a, b = max(
            (len(set(poses[a]) & set(poses[b])), a, b)
            for a in placed
            for b in range(C)
            if b not in placed
        )
        placed.add(b)
        if common < 3:  # the geometry cannot tell: the majority of its views decides
            mirrored[b] = _mostly_flipped(views, b)
            continue
        ref = as_mirrored[a] if mirrored[a] else as_read[a]
        plain, _ = _spread(ref, as_read[b], board)
        mirror, _ = _spread(ref, as_mirrored[b], board)
        if not (np.isfinite(plain) and np.isfinite(mirror)):
            mirrored[b] = _mostly_flipped(views, b)
            continue
        parent[b] = a
        if min(plain, mirror) <= DECISIVE * max(plain, mirror):
            mirrored[b] = mirror < plain
        else:
            mirrored[b] = _mostly_flipped(views, b)
        spreads[b] = (mirror, plain) if mirrored[b] else (plain, mirror)
    if C == 1:
        return [_mostly_flipped(views, 0)], spreads, parent
    # A whole rig mirrored fits as well as the rig (see the module docstring): the one with
    # fewer oddities, then the one in which more cameras saw mostly the board's front, then
    # the one with fewer mirrored cameras (per camera, not per view, so that a camera with a
    # few more views does not tip it). Turned round, a camera's oddities o become 2 - o.
    behind = [_mostly_flipped(views, c) != mirrored[c] for c in range(C)]
    odd = sum(mirrored) + sum(behind)
    front = C - sum(behind)
    if odd > C or (odd == C and (2 * front < C or (2 * front == C and 2 * sum(mirrored) > C))):
        mirrored = [not m for m in mirrored]
    return mirrored, spreads, parent


def _mostly_flipped(views: Sequence[View], c: int) -> bool:
    """Whether most of camera ``c``'s views with the board read flipped."""
    mine = [v for v in views if v.camera == c and len(v.ids)]
    return 2 * sum(v.flipped for v in mine) > len(mine)


def _off_views(
    poses: list[dict[int, np.ndarray]],
    mirrored: list[bool],
    parent: list[int | None],
    views: Sequence[View],
    cameras: Sequence[str],
    board: BoardSpec,
) -> dict[tuple[int, int], str]:
    """``(camera, shot) -> why`` of the views left out: against the camera compared with,
    far off, and read the other way than the camera's other views."""
    by_key = {(v.camera, v.shot): v for v in views}
    diagonal = float(np.hypot(*board.size_mm))
    off: dict[tuple[int, int], str] = {}
    for b, a in enumerate(parent):
        if a is None:
            continue
        pa = {s: mirrored_pose(T) if mirrored[a] else T for s, T in poses[a].items()}
        pb = {s: mirrored_pose(T) if mirrored[b] else T for s, T in poses[b].items()}
        median, per_shot = _spread(pa, pb, board)
        limit = max(OFF_FACTOR * median, OFF_BOARD * diagonal)
        for s, e in per_shot.items():
            if e <= limit:
                continue
            for c, other in ((b, a), (a, b)):
                v = by_key[(c, s)]
                if v.flipped != _mostly_flipped(views, c):
                    how = "only in the flipped image" if v.flipped else "as recorded"
                    off[(c, s)] = (
                        f"its board pose is {e:.0f} mm off what camera {cameras[other]}'s view of the "
                        f"shot and the rig say, and its board read {how}, unlike in most of "
                        "its shots: is this image mirrored?"
                    )
                    break
    return off


def _reading(
    c: int,
    cameras: Sequence[str],
    shots: Sequence[str],
    views: Sequence[View],
    mirrored: list[bool],
    spreads: list[tuple[float, float]],
    parent: list[int | None],
) -> CameraReading:
    """Camera ``c``'s reading and the line that says it."""
    name = cameras[c]
    mine = [v for v in views if v.camera == c and len(v.ids)]
    flipped = tuple(shots[v.shot] for v in mine if v.flipped)
    behind = tuple(shots[v.shot] for v in mine if v.flipped != mirrored[c])
    chosen, other = spreads[c]
    a = parent[c]
    if a is not None:
        why = (
            f"its board poses agree with camera {cameras[a]}'s (spread {chosen:.1f} mm) "
            f"and would not {'as a board seen from behind' if mirrored[c] else 'as a mirrored camera'}"
            f" ({other:.1f} mm)"
        )
    elif c == 0 or len(cameras) == 1:
        why = (
            "the rig's other cameras decide, and a whole rig mirrored fits as well as one that "
            "is not: the reading in which more cameras saw mostly the board's front"
            if len(cameras) > 1
            else "one camera: no other camera to tell a mirrored camera from a board seen "
            "from behind; the reading in which most views saw the board's front"
        )
    else:
        why = "too few shots shared with another camera to tell: most of its views decide"
    if mirrored[c]:
        text = (
            f"camera {name}: a mirrored camera (the board reads only in the flipped image in "
            f"{len(flipped)} of its {len(mine)} shots with the board; {why}): its rig entry "
            "gets flip: horizontal, and its images are flipped wherever they are read"
        )
    elif behind:
        text = (
            f"camera {name}: sees the board from behind, through the paper (or a board printed "
            f"mirrored from the front), in {len(behind)} of its {len(mine)} shots with the board "
            f"(it reads only in the flipped image; {why}): an ordinary camera, its corners "
            "mapped back to the images as recorded"
        )
    else:
        text = ""
    return CameraReading(name, mirrored[c], behind, flipped, spreads[c], text)
