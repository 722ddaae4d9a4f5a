"""Human decisions: ``review.json`` (FORMAT.md), written by the viewer, read by the export.

::

    {"status": "accepted" | "rejected" | "pending",
     "instances": {"<object>/<instance>": "accepted" | "rejected"},
     "decided_at": "2026-11-22T16:04:00+00:00",
     "annotation_fingerprint": "<sha256 of the judged poses>"}

A decision is *stale* when the scene's annotation.json no longer has the fingerprint the
decision was made on (its poses have changed since).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from annotator.dataset.poses import InstancePose
from annotator.errors import UserError
from annotator.io.atomic import write_json

SCENE_STATUSES = ("pending", "accepted", "rejected")
INSTANCE_STATUSES = ("accepted", "rejected")


@dataclass
class Review:
    """A scene's review decisions."""

    status: str = "pending"
    instances: dict[str, str] = field(default_factory=dict)
    decided_at: str | None = None
    annotation_fingerprint: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def is_stale(self, fingerprint: str | None) -> bool:
        """True if a decision was made on poses other than those with ``fingerprint``."""
        return self.status != "pending" and self.annotation_fingerprint != fingerprint

    def to_json(self) -> dict[str, Any]:
        out = dict(self.extra)
        out.update(
            status=self.status,
            instances=dict(sorted(self.instances.items())),
            decided_at=self.decided_at,
            annotation_fingerprint=self.annotation_fingerprint,
        )
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


def read_review(path: str | Path) -> Review | None:
    """Read review.json; None if the file does not exist. UserError if it is corrupt."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"corrupt review file ({exc})", path=path) from None
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
    known = {"status", "instances", "decided_at", "annotation_fingerprint"}
    return Review(
        status=status,
        instances={str(k): str(v) for k, v in instances.items()},
        decided_at=doc.get("decided_at"),
        annotation_fingerprint=doc.get("annotation_fingerprint"),
        extra={k: v for k, v in doc.items() if k not in known},
    )


def write_review(path: str | Path, review: Review) -> None:
    """Write review.json atomically."""
    write_json(path, review.to_json())
