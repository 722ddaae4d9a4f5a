"""Human decisions: ``review.json`` (FORMAT.md), written by the viewer, read by the export.

::

    {"status": "accepted" | "rejected" | "pending",
     "instances": {"<object>/<instance>": "accepted" | "rejected"},
     "decided_at": "2026-11-22T16:04:00+00:00",
     "annotation_fingerprint": "<sha256 of the judged poses>",
     "reason": "a part has no pose",
     "missing": [{"camera": "left", "pixel": [612.0, 433.5], "at": "2026-11-22T16:03:58+00:00"}],
     "decided_by": "page-3f9a2c-1"}

The first four fields are those of FORMAT.md. The others are optional and written only when
they have a value:

- ``reason``: why the scene has its status, in words (the viewer writes
  :data:`NO_POSE_REASON` when a reviewer marks a part that has no pose);
- ``missing``: the "a part has no pose here" marks, each the camera it was made in, the
  pixel (OpenCV convention, full resolution) and when;
- ``decided_by``: an opaque id of the page (browser tab) that made the last decision, so
  that a page can tell that another reviewer has since decided the same scene.

A decision is *stale* when the scene's annotation.json no longer has the fingerprint the
decision was made on (its poses have changed since). Unknown keys are kept (``extra``) and
written back unchanged.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from datetime import datetime, timezone
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np

from annotator.dataset.poses import InstancePose
from annotator.errors import UserError
from annotator.io.atomic import write_json
from annotator.io.documents import read_json

#: The ``reason`` of a scene rejected because a part in it has no pose.
NO_POSE_REASON = "a part has no pose"


class ReviewStatus(str, Enum):
    """The state of a decision about a scene or an instance; the values are the JSON strings.

    It is a ``str``, so ``status == "accepted"`` and JSON encoding work as with plain strings.
    Instances are only ever ``accepted`` or ``rejected`` (no entry means no decision).
    """

    PENDING = "pending"
    ACCEPTED = "accepted"
    REJECTED = "rejected"

    def __str__(self) -> str:
        return self.value


#: Kept for callers written before :class:`ReviewStatus`.
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

    def __post_init__(self) -> None:
        # Callers may pass plain strings; keep the enum inside.
        self.status = ReviewStatus(self.status)
        self.instances = {k: ReviewStatus(v) for k, v in self.instances.items()}

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
        return out


def now_iso() -> str:
    """The current UTC time, ISO 8601, second precision."""
    return datetime.now(timezone.utc).replace(microsecond=0).isoformat()


def poses_fingerprint(poses: list[InstancePose]) -> str:
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
    known = {
        "status",
        "instances",
        "decided_at",
        "annotation_fingerprint",
        "reason",
        "missing",
        "decided_by",
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
    )


def write_review(path: str | Path, review: Review) -> None:
    """Write review.json atomically. An ``OSError`` (read-only folder, full disk) reaches the
    caller, which must tell the person who made the decision."""
    write_json(path, review.to_json())
