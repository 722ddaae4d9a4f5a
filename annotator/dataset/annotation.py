"""``annotation.json`` as typed records: what ``annotate`` writes and every reader (viewer,
evaluation, export, check) reads, so that a field added here reaches all of them.

The JSON layout is described in :mod:`annotator.annotation`; unknown keys are kept (in
``extra``) and written back unchanged.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from annotator.dataset.model import FORMAT_VERSION
from annotator.dataset.poses import InstancePose, read_pose_file, write_poses

_INSTANCE_KEYS = (
    "uncertainty_mm",
    "reprojection_px",
    "markers",
    "views",
    "depth",
    "occlusion",
    "flags",
)


@dataclass
class InstanceAnnotation:
    """One posed instance and the figures that say how far to trust it.

    Attributes:
        object, instance: Which physical part.
        R, t: Its pose in the reference camera (``x_cam = R x_model + t``, mm).
        uncertainty_mm: Estimated 1-sigma pose error as RMS surface displacement.
        reprojection_px: ``{"rms", "max", "per_camera": {camera: rms}}`` over the markers used.
        markers: ``{camera: {"used": [ids], "rejected": [ids], "recovered": [ids]}}``;
            ``recovered`` markers were read only with the pose's help (soft bits).
        views: Number of cameras whose markers were used.
        depth: ``{"agreement", "median_abs_mm", "pixels"}`` or None.
        occlusion: ``{"rate", "per_camera": {camera: rate}}`` or None.
        flags: Reasons to look (:data:`annotator.annotation.FLAGS`).
        extra: Fields this version does not know, kept as read.
    """

    object: str
    instance: str
    R: np.ndarray
    t: np.ndarray
    uncertainty_mm: float | None = None
    reprojection_px: dict[str, Any] | None = None
    markers: dict[str, dict[str, list[int]]] = field(default_factory=dict)
    views: int = 0
    depth: dict[str, Any] | None = None
    occlusion: dict[str, Any] | None = None
    flags: list[str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def key(self) -> str:
        """``object/instance``, the key used in review.json."""
        return f"{self.object}/{self.instance}"

    @property
    def pose(self) -> InstancePose:
        return InstancePose(self.object, self.instance, self.R, self.t, self.to_json_fields())

    @property
    def T(self) -> np.ndarray:  # noqa: N802 - matrix name
        return self.pose.T

    @property
    def occlusion_rate(self) -> float | None:
        return None if self.occlusion is None else self.occlusion.get("rate")

    @property
    def depth_agreement(self) -> float | None:
        return None if self.depth is None else self.depth.get("agreement")

    @property
    def reprojection_rms(self) -> float | None:
        return None if self.reprojection_px is None else self.reprojection_px.get("rms")

    def count(self, use: str) -> int:
        """Markers ``used``, ``rejected`` or ``recovered``, over every camera."""
        return sum(len(m.get(use, [])) for m in self.markers.values())

    def to_json_fields(self) -> dict[str, Any]:
        """Everything but the pose, as JSON fields."""
        out = dict(self.extra)
        out.update(
            uncertainty_mm=self.uncertainty_mm,
            reprojection_px=self.reprojection_px,
            markers=self.markers,
            views=self.views,
            depth=self.depth,
            occlusion=self.occlusion,
            flags=list(self.flags),
        )
        return out

    @classmethod
    def from_pose(cls, p: InstancePose) -> InstanceAnnotation:
        e = dict(p.extra)
        known = {k: e.pop(k) for k in _INSTANCE_KEYS if k in e}
        return cls(
            p.object,
            p.instance,
            p.R,
            p.t,
            uncertainty_mm=known.get("uncertainty_mm"),
            reprojection_px=known.get("reprojection_px"),
            markers=known.get("markers") or {},
            views=int(known.get("views") or 0),
            depth=known.get("depth"),
            occlusion=known.get("occlusion"),
            flags=list(known.get("flags") or []),
            extra=e,
        )


@dataclass
class SceneWarning:
    """Something about the whole scene a reviewer must know.

    ``kind`` is one of ``no_markers``, ``unexplained_depth``, ``blurred``, ``under_exposed``,
    ``over_exposed``; ``details`` holds the kind's own fields (``regions`` for unexplained
    depth: ``[{"box", "pixels", "depth_mm", "unread_markers"}]``; ``cameras``).
    """

    kind: str
    message: str
    details: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "message": self.message, **self.details}

    @classmethod
    def from_json(cls, doc: Any) -> SceneWarning:
        if isinstance(doc, str):  # files of earlier versions held plain strings
            return cls("note", doc)
        if not isinstance(doc, dict):  # never drop a warning: keep what it says
            return cls("note", json.dumps(doc))
        d = dict(doc)
        return cls(str(d.pop("kind", "note")), str(d.pop("message", "")), d)


COMPLETENESS_KINDS = ("no_markers", "unexplained_depth", "blurred", "under_exposed", "over_exposed")


@dataclass
class SceneAnnotation:
    """A scene's annotation.json.

    Attributes:
        instances: The posed instances.
        warnings: Scene-level warnings (completeness and image quality).
        image_quality: ``{camera: {"edge_blur_px", "median", "saturated"}}``.
        unknown_markers: ``{camera: [ids]}`` read but belonging to no instance.
        unconfirmed_markers: ``{camera: [ids]}`` of poses left out because the measured depth
            contradicted them and nothing else supported them.
        duplicates: ``{camera: [ids]}`` seen twice in one image.
        unexplained_mask: File name of the unexplained-depth mask beside annotation.json
            (uint8 PNG on the depth camera's grid, 255 = unexplained), or None.
        created_at, description_digest, errors: Provenance.
        extra: Top-level fields this version does not know.
    """

    instances: list[InstanceAnnotation] = field(default_factory=list)
    warnings: list[SceneWarning] = field(default_factory=list)
    image_quality: dict[str, dict[str, Any]] = field(default_factory=dict)
    unknown_markers: dict[str, list[int]] = field(default_factory=dict)
    unconfirmed_markers: dict[str, list[int]] = field(default_factory=dict)
    duplicates: dict[str, list[int]] = field(default_factory=dict)
    unexplained_mask: str | None = None
    created_at: str | None = None
    description_digest: str | None = None
    errors: list[str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def flagged(self) -> bool:
        """True if a reviewer should look: a warning or a flagged instance."""
        return bool(self.warnings) or any(i.flags for i in self.instances)

    def write(self, path: str | Path) -> None:
        """Write annotation.json atomically."""
        top = dict(self.extra)
        top.update(
            format=FORMAT_VERSION,
            created_at=self.created_at,
            description_digest=self.description_digest,
            unknown_markers=self.unknown_markers,
            unconfirmed_markers=self.unconfirmed_markers,
            duplicates=self.duplicates,
            image_quality=self.image_quality,
            unexplained_mask=self.unexplained_mask,
            warnings=[w.to_json() for w in self.warnings],
            errors=self.errors,
        )
        write_poses(path, [i.pose for i in self.instances], **top)

    @classmethod
    def read(cls, path: str | Path) -> SceneAnnotation:
        """Read annotation.json (UserError naming the file if it is malformed)."""
        poses, top = read_pose_file(path)
        top = dict(top)
        top.pop("format", None)
        return cls(
            instances=[InstanceAnnotation.from_pose(p) for p in poses],
            warnings=[SceneWarning.from_json(w) for w in top.pop("warnings", None) or []],
            image_quality=top.pop("image_quality", None) or {},
            unknown_markers=top.pop("unknown_markers", None) or {},
            unconfirmed_markers=top.pop("unconfirmed_markers", None) or {},
            duplicates=top.pop("duplicates", None) or {},
            unexplained_mask=top.pop("unexplained_mask", None),
            created_at=top.pop("created_at", None),
            description_digest=top.pop("description_digest", None),
            errors=list(top.pop("errors", None) or []),
            extra=top,
        )
