"""What every dataset format's reader returns, and the checks they share.

Units: millimetres for every pose handed to the evaluation, whatever the file's unit (the
paper's format stores metres); the reader converts.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from annotator.errors import UserError
from annotator.geometry.transforms import is_rotation, nearest_rotation
from annotator.io.documents import read_json
from annotator.symmetry.space import PoseSpace


@dataclass
class PoseSet:
    """Poses of one object in one scene, with one value each: the occlusion rate for ground
    truth (NaN: unknown), the score for results."""

    R: list[np.ndarray] = field(default_factory=list)
    t: list[np.ndarray] = field(default_factory=list)
    values: list[float] = field(default_factory=list)

    @classmethod
    def of(cls, R: np.ndarray, t: np.ndarray, values: np.ndarray) -> PoseSet:
        """Poses given as (N, 3, 3), (N, 3) and (N,) arrays."""
        poses = cls()
        poses.extend(R, t, values)
        return poses

    def add(self, R: np.ndarray, t: np.ndarray, value: float) -> None:
        self.R.append(R)
        self.t.append(t)
        self.values.append(value)

    def extend(self, R: np.ndarray, t: np.ndarray, values: Sequence[float] | np.ndarray) -> None:
        """Add (N, 3, 3), (N, 3) poses and their N values."""
        self.R.extend(R)
        self.t.extend(t)
        self.values.extend(float(v) for v in values)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = len(self.R)
        return (
            np.asarray(self.R, float).reshape(n, 3, 3),
            np.asarray(self.t, float).reshape(n, 3),
            np.asarray(self.values, float).reshape(n),
        )


Table = dict[tuple[str, str], PoseSet]  # (scene key, object) -> poses


@dataclass
class GroundTruth:
    """True poses of a dataset, as the evaluation needs them.

    Attributes:
        spaces: Pose space (distance, diameter) per object name.
        poses: True poses per (scene, object), occlusion rates as values.
        scenes: Every scene key, in order.
        format: The format's name (``ours``, ``bop``, ``sileane``).
        unit: The length unit of its files (``mm`` or ``m``), which results in the same
            format's per-scene JSON lists also use.
        object_ids: Numeric object ids (BOP CSV) to names.
        thresholds: Match thresholds (mm) that the dataset itself prescribes, per object
            (the paper's files carry one).

    >>> from annotator import read_ground_truth
    >>> gt = read_ground_truth("sample_scenes")
    >>> gt.format, len(gt.scenes), sorted(gt.spaces)
    ('ours', 4, ['bracket', 'brick', 'cylinder'])
    """

    spaces: dict[str, PoseSpace]
    poses: Table
    scenes: list[str]
    format: str
    unit: str = "mm"
    object_ids: dict[int, str] = field(default_factory=dict)
    thresholds: dict[str, float] = field(default_factory=dict)
    #: What the reader took as other than written (symmetries snapped, rotations
    #: projected), one line each, for the evaluation's header.
    notes: list[str] = field(default_factory=list)
    #: The (scene, object) pairs to score when the dataset lists its targets (BOP's
    #: test_targets files); None: every pair.
    targets: set[tuple[str, str]] | None = None
    #: The folder the ground truth was read from (our format: results name its scenes).
    root: Path | None = None


@dataclass
class PoseResults:
    """Results to score: poses per (scene, object) with scores as values; ``unknown_scenes``
    are scene keys found in the results but not in the ground truth (they are not scored);
    ``scenes`` the known scenes the results mention (a file with an empty list included).

    >>> from annotator import read_ground_truth, annotations_as_results
    >>> found = annotations_as_results("sample_scenes", read_ground_truth("sample_scenes"))
    >>> len(found.scenes), found.unknown_scenes
    (4, [])
    """

    poses: Table
    unknown_scenes: list[str] = field(default_factory=list)
    scenes: set[str] = field(default_factory=set)  # scenes mentioned, with results or not
    notes: list[str] = field(default_factory=list)  # as GroundTruth.notes

    def __post_init__(self) -> None:
        self.scenes |= {scene for scene, _ in self.poses}


def checked_pose(
    R: Any, t: Any, where: str, path: Path, *, scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """``R`` (9 numbers or 3x3) and ``t`` (3 numbers, times ``scale``) as arrays, or a
    one-line UserError naming the file, ``where`` (line or entry) and the field."""
    try:
        Rm = np.asarray(R, float).reshape(3, 3)
    except (TypeError, ValueError):
        raise UserError(f"{where}: R must be 9 numbers", path=path) from None
    try:
        tv = np.asarray(t, float).reshape(3) * scale
    except (TypeError, ValueError):
        raise UserError(f"{where}: t must be 3 numbers", path=path) from None
    if not np.all(np.isfinite(Rm)):
        raise UserError(f"{where}: R has a NaN or infinite value", path=path)
    if not np.all(np.isfinite(tv)):
        raise UserError(f"{where}: t has a NaN or infinite value", path=path)
    if not near_rotation(Rm):
        raise UserError(
            f"{where}: R is not a rotation matrix (R R^T differs from I by more than "
            f"{ROTATION_BOUND:g}, or det R < 0)",
            path=path,
        )
    return (Rm if is_rotation(Rm, tol=1e-3) else nearest_rotation(Rm)), tv


#: How far from orthonormal a rotation in a file may be (max |R R^T - I|) and still be
#: taken, projected to the nearest rotation: BOP's own scene_gt.json reaches 0.0096, and
#: bop_toolkit takes whatever it is given. A reflection (det < 0) is never taken.
ROTATION_BOUND = 0.05


def near_rotation(R: np.ndarray) -> bool:
    """True if ``R`` (3, 3) is within :data:`ROTATION_BOUND` of a rotation, not a reflection."""
    return bool(np.abs(R @ R.T - np.eye(3)).max() <= ROTATION_BOUND and np.linalg.det(R) > 0)


def projected_rotations(R: np.ndarray) -> tuple[np.ndarray, int]:
    """(N, 3, 3) near-rotations with those not orthonormal to 1e-3 projected to the nearest
    rotation (SVD), and how many were."""
    return _projected(R, *_orthonormality(R))


def _orthonormality(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """max |R R^T - I| and det R of each of (N, 3, 3) matrices."""
    return np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2)), np.linalg.det(R)


def _projected(R: np.ndarray, error: np.ndarray, det: np.ndarray) -> tuple[np.ndarray, int]:
    """:func:`projected_rotations` given :func:`_orthonormality` of ``R``."""
    off = (error >= 1e-3) | (np.abs(det - 1.0) >= 1e-3)
    if off.any():
        U, _, Vt = np.linalg.svd(R[off])
        d = np.sign(np.linalg.det(U @ Vt))
        U[:, :, 2] *= d[:, None]
        R = R.copy()
        R[off] = U @ Vt
    return R, int(off.sum())


def projected_note(count: int, total: int, what: str) -> list[str]:
    """The header line for ``count`` projected rotations among ``total`` (none if 0)."""
    if not count:
        return []
    return [
        f"{count} of {total} rotations in {what} were not orthonormal to 1e-3 and were taken "
        "as the nearest rotation (SVD)"
    ]


def checked_poses(
    Rs: list[Any], ts: list[Any], where: Callable[[int], str], path: Path, *, scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`checked_pose` for many poses at once: (N, 3, 3) and (N, 3) arrays, and how many
    rotations were projected to the nearest rotation. The first bad pose is reported as
    :func:`checked_pose` would (``where(i)`` names entry i)."""
    n = len(Rs)
    try:
        R = np.asarray(Rs, float).reshape(n, 3, 3)
        t = np.asarray(ts, float).reshape(n, 3) * scale
        finite = np.isfinite(R).all(axis=(1, 2)) & np.isfinite(t).all(axis=1)
        if not finite.all():
            R = np.where(finite[:, None, None], R, np.eye(3))  # NaN would warn in det
        error, det = _orthonormality(R)
        ok = finite & (error <= ROTATION_BOUND) & (det > 0)
    except (TypeError, ValueError):
        ok = np.zeros(n, bool)
    if not ok.all():
        for i in np.flatnonzero(~ok):
            checked_pose(Rs[i], ts[i], where(int(i)), path, scale=scale)  # raises for the culprit
        raise AssertionError("unreachable: a pose failed the batch check but not its own")
    R, projected = _projected(R, error, det)
    return R, t, projected


def checked_entries(
    entries: list[dict[str, Any]], path: Path, *, scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray, int]:
    """The ``R`` and ``t`` of a JSON list's entries, checked (see :func:`checked_poses`)."""
    return checked_poses(
        [e.get("R") for e in entries],
        [e.get("t") for e in entries],
        lambda i: f"entry {i}",
        path,
        scale=scale,
    )


def checked_score(value: Any, where: str, path: Path) -> float:
    """A finite score, or a one-line UserError."""
    try:
        score = float(value)
    except (TypeError, ValueError):
        raise UserError(f"{where}: score must be a number, got {value!r}", path=path) from None
    if not math.isfinite(score):
        raise UserError(f"{where}: score is {value!r}; it must be finite", path=path)
    return score


def _objects_and_scores(
    doc: list[Any], gt: GroundTruth, single: str | None, path: Path
) -> tuple[list[str], list[float]]:
    """The object and the score of each entry of a results list, checked."""
    if single is not None and all(type(r) is dict and "object" not in r for r in doc):
        objects = [single] * len(doc)  # the usual case, checked at once
        try:
            scores = [r["score"] for r in doc]
            values = np.asarray(scores, float)
            if np.isfinite(values).all() and all(type(v) in (int, float) for v in scores):
                return objects, [float(v) for v in scores]
        except (KeyError, TypeError, ValueError):
            pass  # the entry-wise checks below name the culprit
    objects, floats = [], []
    for i, r in enumerate(doc):
        where = f"entry {i}"
        if not isinstance(r, dict):
            raise UserError(f"{where}: expected an object {{R, t, score}}", path=path)
        obj = str(r["object"]) if "object" in r else single
        if obj not in gt.spaces:
            what = f"unknown object {obj!r}" if obj else "'object' is required"
            raise UserError(f"{where}: {what} (objects: {', '.join(gt.spaces)})", path=path)
        if "score" not in r:
            raise UserError(f"{where}: 'score' is missing", path=path)
        objects.append(obj)
        floats.append(checked_score(r["score"], where, path))
    return objects, floats


def read_json_lists(
    folder: Path,
    gt: GroundTruth,
    *,
    scale: float,
    scene_key: Callable[[str], str] = lambda stem: stem,
    nested: bool = False,
) -> PoseResults:
    """A folder of ``<scene>.json`` files, each a list of ``{"object"?, "R", "t", "score"}``
    (the paper's results format; ``object`` may be left out when there is one object).
    ``t`` is multiplied by ``scale`` to give millimetres. ``nested``: a sequence's
    ``<scene>/<frame>.json`` instead, named ``<scene>/<frame>``."""
    table: Table = {}
    unknown = []
    mentioned = set()
    known = set(gt.scenes)
    single = next(iter(gt.spaces)) if len(gt.spaces) == 1 else None
    projected = total = 0
    # Files of the other layout would be left out without a word, and score as misses.
    other = sorted(folder.glob("*.json" if nested else "*/*.json"))
    if other and (nested or not any(folder.glob("*.json"))):
        raise UserError(
            "the scenes are sequences: each frame's results go in <scene>/<frame>.json, "
            f"not <scene>.json ({other[0].name} would be left out)"
            if nested
            else "the scenes are single shots: each scene's results go in <scene>.json, not "
            f"<scene>/<frame>.json ({other[0].parent.name}/{other[0].name} would be left out)",
            path=folder,
        )
    for f in sorted(folder.glob("*/*.json" if nested else "*.json")):
        doc = read_json(f)
        if not isinstance(doc, list):
            raise UserError("expected a JSON list of {R, t, score}", path=f)
        stem = f"{f.parent.name}/{f.stem}" if nested else f.stem
        key = scene_key(stem)
        if key not in known:
            unknown.append(stem)
            continue
        mentioned.add(key)
        objects, scores = _objects_and_scores(doc, gt, single, f)
        R, t, n = checked_entries(doc, f, scale=scale)
        projected += n
        total += len(R)
        if single is not None:
            table.setdefault((key, single), PoseSet()).extend(R, t, scores)
            continue
        for i, obj in enumerate(objects):
            table.setdefault((key, obj), PoseSet()).add(R[i], t[i], scores[i])
    return PoseResults(table, unknown, mentioned, projected_note(projected, total, "the results"))
