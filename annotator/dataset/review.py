"""Human decisions: ``review.json`` (FORMAT.md), written by the viewer, read by the export.

::

    {"status": "accepted" | "rejected" | "pending",
     "instances": {"<object>/<instance>": "accepted" | "rejected"},
     "decided_at": "2026-11-22T16:04:00+00:00",
     "annotation_fingerprint": "<sha256 of the judged poses>",
     "reason": "a part has no pose",
     "missing": [{"camera": "left", "pixel": [612.0, 433.5], "at": "2026-11-22T16:03:58+00:00"}],
     "decided_by": "page-3f9a2c-1",
     "frames": {"<frame>": "rejected"},
     "poses": {"<object>/<instance>": {"cam_R_m2c": [9 floats], "cam_t_m2c": [3 floats],
               "source": "edited", "steps": [{"op": "refine", ...}, ...],
               "decided_by": "page-3f9a2c-1", "at": "2026-11-22T16:04:10+00:00",
               "auto_fingerprint": "<sha256 of the auto pose it was made from> | null"}}}

The first four fields are those of FORMAT.md. The others are optional and written only when
they have a value:

- ``reason``: why the scene has its status, in words (the viewer writes
  :data:`NO_POSE_REASON` when a reviewer marks a part that has no pose);
- ``missing``: the "a part has no pose here" marks, each the camera it was made in, the
  pixel (OpenCV convention, full resolution) and when;
- ``decided_by``: an opaque id of the page (browser tab) that made the last decision, so
  that a page can tell that another reviewer has since decided the same scene;
- ``poses``: poses a reviewer repaired in the viewer (:class:`EditedPose`), which replace
  annotation.json's pose of that instance for the export and the evaluation (annotation.json
  stays what ``annotate`` wrote). ``auto_fingerprint`` is that of the instance's auto pose
  the edit started from (null: an instance ``annotate`` did not pose, added by hand); when
  the auto pose is no longer that one, the edit is *stale* (:func:`apply_edits`);
- ``frames``: a sequence's frames rejected on their own (the scene's other frames go on).

A decision is *stale* when the scene's annotation.json no longer has the fingerprint the
decision was made on (its poses have changed since). Unknown keys are kept (``extra``) and
written back unchanged.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from enum import StrEnum
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from annotator.dataset.poses import InstancePose
from annotator.errors import UserError
from annotator.geometry.transforms import is_rotation
from annotator.io.atomic import write_json
from annotator.io.documents import read_json

#: The ``reason`` of a scene rejected because a part in it has no pose.
NO_POSE_REASON = "a part has no pose"


class ReviewStatus(StrEnum):
    """The state of a decision about a scene or an instance; the values are the JSON strings.

    It is a ``str``, so ``status == "accepted"`` and JSON encoding work as with plain strings.
    Instances are only ever ``accepted`` or ``rejected`` (no entry means no decision).

    >>> [s.value for s in ReviewStatus]
    ['pending', 'accepted', 'rejected']
    """

    PENDING = "pending"
    ACCEPTED = "accepted"
    REJECTED = "rejected"


#: The JSON strings of a scene's and an instance's decision.
SCENE_STATUSES = tuple(s.value for s in ReviewStatus)
INSTANCE_STATUSES = (ReviewStatus.ACCEPTED.value, ReviewStatus.REJECTED.value)


@dataclass(frozen=True)
class MissingPart:
    """A reviewer's mark: a part lies at ``pixel`` of ``camera`` and has no pose."""

    camera: str
    pixel: tuple[float, float]
    at: str | None = None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"camera": self.camera, "pixel": [self.pixel[0], self.pixel[1]]}
        if self.at is not None:
            out["at"] = self.at
        return out


class RepairOp(StrEnum):
    """What a repair step did (review.json ``steps[].op``); the values are the JSON strings."""

    REFINE = "refine"  # ICP against the depth and the markers (R)
    ALTERNATIVE = "alternative"  # another candidate pose from the markers (A)
    NUDGE = "nudge"  # moved or turned by a step (1-6)
    GIZMO = "gizmo"  # dragged in the 3D view
    ADD = "add"  # an instance without a pose, started where a reviewer clicked


@dataclass(frozen=True)
class RepairStep:
    """One step of a repaired pose's making (review.json ``steps``): what was done and its
    figures (``{"op": "nudge", "kind": "move", "axis": "x", "amount": 1.0}`` is
    ``RepairStep(RepairOp.NUDGE, {"kind": "move", "axis": "x", "amount": 1.0})``).

    >>> RepairStep.from_json({"op": "gizmo"}).to_json()
    {'op': 'gizmo'}
    """

    op: RepairOp
    details: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"op": self.op.value, **self.details}

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> RepairStep:
        """The step a JSON object describes; ValueError if its ``op`` is not a
        :class:`RepairOp`."""
        op = doc.get("op")
        if op not in set(RepairOp):
            ops = ", ".join(o.value for o in RepairOp)
            raise ValueError(f"op must be one of {ops}, not {op!r}")
        return cls(RepairOp(op), {k: v for k, v in doc.items() if k != "op"})


def as_step(step: RepairStep | dict[str, Any]) -> RepairStep:
    """``step`` as a record (a JSON object is read by :meth:`RepairStep.from_json`)."""
    return step if isinstance(step, RepairStep) else RepairStep.from_json(step)


#: The ``source`` of a pose in review.json's ``poses``.
EDITED_SOURCE = "edited"
#: A repaired rotation must be this close to orthonormal (max |R R^T - I|).
_ROTATION_TOLERANCE = 1e-5


@dataclass
class EditedPose:
    """A pose repaired by a reviewer (review.json ``poses``), in the reference camera.

    Attributes:
        R, t: The pose (``x_cam = R x_model + t``, mm).
        steps: What was done to the auto pose to get here, oldest first (JSON objects
            given here are read as :class:`RepairStep`).
        decided_by: The page that made it; at: when (ISO 8601).
        auto_fingerprint: :func:`instance_fingerprint` of the auto pose it was made from;
            None for an instance that had no auto pose (added by hand).
    """

    R: np.ndarray
    t: np.ndarray
    steps: list[RepairStep] = field(default_factory=list)
    decided_by: str | None = None
    at: str | None = None
    auto_fingerprint: str | None = None

    def __post_init__(self) -> None:
        # Steps may come as their JSON objects (scripts, tests): records inside.
        self.steps = [as_step(s) for s in self.steps]

    def to_json(self) -> dict[str, Any]:
        return {
            "cam_R_m2c": [float(x) for x in np.asarray(self.R).reshape(9)],
            "cam_t_m2c": [float(x) for x in np.asarray(self.t).reshape(3)],
            "source": EDITED_SOURCE,
            "steps": [s.to_json() for s in self.steps],
            "decided_by": self.decided_by,
            "at": self.at,
            "auto_fingerprint": self.auto_fingerprint,
        }


@dataclass
class Review:
    """A scene's review decisions (see the module docstring for the file)."""

    status: ReviewStatus = ReviewStatus.PENDING
    instances: dict[str, ReviewStatus] = field(default_factory=dict)
    decided_at: str | None = None
    annotation_fingerprint: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    reason: str | None = None
    missing: list[MissingPart] = field(default_factory=list)
    decided_by: str | None = None
    poses: dict[str, EditedPose] = field(default_factory=dict)
    #: A sequence's frames a reviewer rejected on their own (frame -> ``rejected``): left out
    #: of the export while the rest of the scene goes.
    frames: dict[str, ReviewStatus] = field(default_factory=dict)

    def __post_init__(self) -> None:
        # Callers may pass plain strings; keep the enum inside.
        self.status = ReviewStatus(self.status)
        self.instances = {k: ReviewStatus(v) for k, v in self.instances.items()}
        self.frames = {k: ReviewStatus(v) for k, v in self.frames.items()}

    @property
    def rejected_frames(self) -> set[str]:
        """The frames rejected on their own."""
        return {f for f, v in self.frames.items() if v == ReviewStatus.REJECTED}

    def is_stale(self, fingerprint: str | None) -> bool:
        """True if a decision was made on poses other than those with ``fingerprint``."""
        return self.status != ReviewStatus.PENDING and self.annotation_fingerprint != fingerprint

    def to_json(self) -> dict[str, Any]:
        out = dict(self.extra)
        out.update(
            status=self.status.value,
            instances={k: v.value for k, v in sorted(self.instances.items())},
            decided_at=self.decided_at,
            annotation_fingerprint=self.annotation_fingerprint,
        )
        if self.reason is not None:
            out["reason"] = self.reason
        if self.missing:
            out["missing"] = [m.to_json() for m in self.missing]
        if self.decided_by is not None:
            out["decided_by"] = self.decided_by
        if self.poses:
            out["poses"] = {k: v.to_json() for k, v in sorted(self.poses.items())}
        if self.frames:
            out["frames"] = {k: v.value for k, v in sorted(self.frames.items())}
        return out


def now_iso() -> str:
    """The current UTC time, ISO 8601, second precision."""
    return datetime.now(UTC).replace(microsecond=0).isoformat()


class Posed(Protocol):
    """Anything with a pose: :class:`InstancePose`, an annotation.json instance."""

    @property
    def object(self) -> str: ...
    @property
    def instance(self) -> str: ...
    @property
    def R(self) -> np.ndarray: ...
    @property
    def t(self) -> np.ndarray: ...


def poses_fingerprint(poses: Sequence[Posed]) -> str:
    """SHA-256 of the poses (object, instance, R to 1e-6, t to 1e-4 mm), order-independent.

    It ignores everything but the poses, so re-running ``annotate`` with identical results
    does not make earlier decisions stale.
    """
    rows = sorted(
        (
            p.object,
            p.instance,
            [round(float(x), 6) for x in np.ravel(p.R)],
            [round(float(x), 4) for x in np.ravel(p.t)],
        )
        for p in poses
    )
    return hashlib.sha256(json.dumps(rows).encode()).hexdigest()


def instance_fingerprint(pose: Posed) -> str:
    """The fingerprint of one auto pose (:func:`poses_fingerprint` of it alone)."""
    return poses_fingerprint([pose])


@dataclass
class EditedPoses:
    """A scene's poses with the reviewer's repairs applied (:func:`apply_edits`)."""

    poses: list[Any]
    edited: set[str] = field(default_factory=set)  # keys whose pose is a current edit
    stale: set[str] = field(default_factory=set)  # keys whose edit was made on another auto pose


def apply_edits(poses: list[Any], review: Review | None, added: Any = InstancePose) -> EditedPoses:
    """``poses`` (records with ``object``, ``instance``, ``R``, ``t``: InstancePose or
    InstanceAnnotation) with the current edits of ``review`` applied, and the instances added
    by hand appended (made by ``added(object, instance, R, t)``).

    An edit is *current* when the auto pose it was made from is the one in ``poses`` (for an
    added instance: when ``poses`` still has none of it); a stale edit is not applied: the
    auto pose is kept, and the edit is listed, as a stale decision is.
    """
    from dataclasses import replace as _replace

    edits = dict(review.poses) if review is not None else {}
    out = EditedPoses([])
    for p in poses:
        edit = edits.pop(p.key, None)
        if edit is None:
            out.poses.append(p)
        elif edit.auto_fingerprint == instance_fingerprint(p):
            out.poses.append(_replace(p, R=np.array(edit.R), t=np.array(edit.t)))
            out.edited.add(p.key)
        else:
            out.poses.append(p)
            out.stale.add(p.key)
    for key, edit in sorted(edits.items()):
        if edit.auto_fingerprint is not None:  # its auto pose has gone since
            out.stale.add(key)
            continue
        obj, _, inst = key.partition("/")
        out.poses.append(added(obj, inst, np.array(edit.R), np.array(edit.t)))
        out.edited.add(key)
    return out


def _numbers(value: Any, n: int) -> bool:
    return (
        isinstance(value, list)
        and len(value) == n
        and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)
            for v in value
        )
    )


def _edited_poses(value: Any, path: Path) -> dict[str, EditedPose]:
    if not isinstance(value, dict):
        raise UserError("'poses' must map object/instance to an edited pose", path=path)
    out = {}
    for key, rec in value.items():
        where = f"poses[{key!r}]"
        if not isinstance(key, str) or key.count("/") != 1 or not all(key.split("/")):
            raise UserError(f"{where}: the key must be 'object/instance'", path=path)
        if not isinstance(rec, dict):
            raise UserError(f"{where}: must be an object", path=path)
        if not _numbers(rec.get("cam_R_m2c"), 9) or not _numbers(rec.get("cam_t_m2c"), 3):
            raise UserError(
                f"{where}: cam_R_m2c must be 9 finite numbers and cam_t_m2c 3", path=path
            )
        R = np.array(rec["cam_R_m2c"], float).reshape(3, 3)
        if not is_rotation(R, tol=_ROTATION_TOLERANCE):
            raise UserError(f"{where}: cam_R_m2c is not a rotation", path=path)
        if rec.get("source", EDITED_SOURCE) != EDITED_SOURCE:
            raise UserError(f"{where}: source must be {EDITED_SOURCE!r}", path=path)
        steps = rec.get("steps", [])
        if not isinstance(steps, list) or not all(isinstance(s, dict) for s in steps):
            raise UserError(f"{where}: steps must be a list of objects", path=path)
        try:
            steps = [RepairStep.from_json(s) for s in steps]
        except ValueError as exc:
            raise UserError(f"{where}: a step's {exc}", path=path) from None
        for name in ("decided_by", "at", "auto_fingerprint"):
            if rec.get(name) is not None and not isinstance(rec[name], str):
                raise UserError(f"{where}: {name} must be a string", path=path)
        out[key] = EditedPose(
            R=R,
            t=np.array(rec["cam_t_m2c"], float),
            steps=steps,
            decided_by=rec.get("decided_by"),
            at=rec.get("at"),
            auto_fingerprint=rec.get("auto_fingerprint"),
        )
    return out


def _missing_parts(value: Any, path: Path) -> list[MissingPart]:
    bad = UserError(
        "'missing' must be a list of {camera, pixel: [x, y]} (a part with no pose)", path=path
    )
    if not isinstance(value, list):
        raise bad
    out = []
    for rec in value:
        if not isinstance(rec, dict) or not isinstance(rec.get("camera"), str):
            raise bad
        pixel = rec.get("pixel")
        if (
            not isinstance(pixel, list)
            or len(pixel) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in pixel)
        ):
            raise bad
        at = rec.get("at")
        out.append(
            MissingPart(
                rec["camera"], (float(pixel[0]), float(pixel[1])), None if at is None else str(at)
            )
        )
    return out


def read_review(path: str | Path) -> Review | None:
    """Read review.json; None if the file does not exist. UserError if it is corrupt or
    cannot be read."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        doc = read_json(path)
    except UserError as exc:
        raise UserError(f"corrupt review file ({exc.message})", path=path) from None
    if not isinstance(doc, dict):
        raise UserError("corrupt review file (expected a JSON object)", path=path)
    status = doc.get("status", "pending")
    instances = doc.get("instances", {})
    if status not in SCENE_STATUSES:
        raise UserError(f"unknown scene status {status!r}", path=path)
    if not isinstance(instances, dict) or any(
        v not in INSTANCE_STATUSES for v in instances.values()
    ):
        raise UserError("'instances' must map object/instance to accepted or rejected", path=path)
    reason = doc.get("reason")
    if reason is not None and not isinstance(reason, str):
        raise UserError("'reason' must be a string", path=path)
    for name in ("decided_at", "annotation_fingerprint", "decided_by"):
        if doc.get(name) is not None and not isinstance(doc[name], str):
            raise UserError(f"'{name}' must be a string", path=path)
    decided_by = doc.get("decided_by")
    frames = doc.get("frames", {})
    if not isinstance(frames, dict) or any(v != ReviewStatus.REJECTED for v in frames.values()):
        raise UserError("'frames' must map a frame to rejected", path=path)
    known = {
        "frames",
        "status",
        "instances",
        "decided_at",
        "annotation_fingerprint",
        "reason",
        "missing",
        "decided_by",
        "poses",
    }
    return Review(
        status=ReviewStatus(status),
        instances={str(k): ReviewStatus(v) for k, v in instances.items()},
        decided_at=doc.get("decided_at"),
        annotation_fingerprint=doc.get("annotation_fingerprint"),
        extra={k: v for k, v in doc.items() if k not in known},
        reason=reason,
        missing=_missing_parts(doc.get("missing", []), path),
        decided_by=None if decided_by is None else str(decided_by),
        poses=_edited_poses(doc.get("poses", {}), path),
        frames={str(k): ReviewStatus(v) for k, v in frames.items()},
    )


def write_review(path: str | Path, review: Review) -> None:
    """Write review.json atomically. An ``OSError`` (read-only folder, full disk) reaches the
    caller, which must tell the person who made the decision."""
    write_json(path, review.to_json())
