"""``annotation.json`` as typed records: what ``annotate`` writes and every reader (viewer,
evaluation, export, check) reads, so that a field added here reaches all of them.

A fixed rig's annotation is its :class:`InstanceAnnotation` list with the scene's figures
(:mod:`annotator.dataset.figures`). A sequence's (a moving rig's) has its instances in the
*scene frame* (the reference camera of :attr:`SceneAnnotation.scene_frame`) and, under
:attr:`SceneAnnotation.frames`, where the rig was for each frame (:class:`FramePose`).
The JSON written is exactly the layout of docs/FORMAT.md; fields a record does not know are
kept in its ``extra`` and written back after the known ones.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from annotator.dataset.figures import (
    DepthCheck,
    ImageQuality,
    MarkerUse,
    Occlusion,
    PhysicsCheck,
    Reprojection,
    SceneWarning,
    image_qualities,
)
from annotator.dataset.flags import Flag, FrameFlag, known_member
from annotator.dataset.model import FORMAT_VERSION
from annotator.dataset.poses import InstancePose, read_pose_file, write_poses
from annotator.errors import UserError
from annotator.geometry.transforms import is_rotation, make_transform

__all__ = [
    "FramePose",
    "InstanceAnnotation",
    "SceneAnnotation",
    "frames_from_json",
    "frames_to_json",
]


def _optional(record: Any, doc: Any) -> Any:
    """``record.from_json(doc)`` for a mapping; None for None (read_pose_file has checked
    that these fields are mappings, and their numbers)."""
    return None if doc is None else record.from_json(doc)


@dataclass
class InstanceAnnotation:
    """One posed instance and the figures that say how far to trust it.

    Attributes:
        object, instance: Which physical part.
        R, t: Its pose in the reference camera (``x_cam = R x_model + t``, mm).
        uncertainty_mm: Estimated 1-sigma pose error as RMS surface displacement.
        reprojection: Reprojection error of the markers used (``reprojection_px`` in JSON).
        markers: Per camera, the markers used, rejected and recovered.
        views: Number of cameras whose markers were used.
        depth: Agreement with the measured depth, or None (no depth, too few pixels).
        occlusion: Occlusion rates, or None.
        physics: Whether the pose is physically possible in its pile, or None (not checked).
        flags: Reasons to look (:class:`Flag`).
        frames_seen: A sequence's: how many frames read its markers (None: a fixed rig's).
        depth_agreement_median: A sequence's: the median over frames of its depth agreement.
        extra: Fields this version does not know, kept as read.

    >>> ann = SceneAnnotation.read("sample_scenes/scenes/000003/annotation.json")
    >>> i = ann.instances[0]
    >>> i.key, sorted(i.marker_ids())[:2], i.reprojection.rms < 1.0
    ('bracket/01', [2, 9], True)
    """

    object: str
    instance: str
    R: np.ndarray
    t: np.ndarray
    uncertainty_mm: float | None = None
    reprojection: Reprojection | None = None
    markers: dict[str, MarkerUse] = field(default_factory=dict)
    views: int = 0
    depth: DepthCheck | None = None
    occlusion: Occlusion | None = None
    physics: PhysicsCheck | None = None
    flags: list[Flag | str] = field(default_factory=list)
    frames_seen: int | None = None
    depth_agreement_median: float | None = None
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
        """4x4 ``cam_T_model`` in the reference camera."""
        return make_transform(self.R, self.t)

    @property
    def occlusion_rate(self) -> float | None:
        return None if self.occlusion is None else self.occlusion.rate

    @property
    def depth_agreement(self) -> float | None:
        return None if self.depth is None else self.depth.agreement

    @property
    def reprojection_rms(self) -> float | None:
        return None if self.reprojection is None else self.reprojection.rms

    def count(self, use: str) -> int:
        """Markers ``used``, ``rejected`` or ``recovered``, over every camera."""
        return sum(len(getattr(m, use)) for m in self.markers.values())

    def marker_ids(self, use: str = "used") -> set[int]:
        """Ids of the markers ``used`` (or ``rejected``, ``recovered``) in any camera."""
        return {i for m in self.markers.values() for i in getattr(m, use)}

    def to_json_fields(self) -> dict[str, Any]:
        """Everything but the pose, as JSON fields."""
        out: dict[str, Any] = {}
        if self.frames_seen is not None:
            out["frames_seen"] = self.frames_seen
        if self.depth_agreement_median is not None:
            out["depth_agreement_median"] = self.depth_agreement_median
        out.update(self.extra)
        out.update(
            uncertainty_mm=self.uncertainty_mm,
            reprojection_px=None if self.reprojection is None else self.reprojection.to_json(),
            markers={c: m.to_json() for c, m in self.markers.items()},
            views=self.views,
            depth=None if self.depth is None else self.depth.to_json(),
            occlusion=None if self.occlusion is None else self.occlusion.to_json(),
            flags=[str(f) for f in self.flags],
        )
        if self.physics is not None:
            out["physics"] = self.physics.to_json()
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
            reprojection=_optional(Reprojection, known.get("reprojection_px")),
            markers={
                str(c): MarkerUse.from_json(m)
                for c, m in (known.get("markers") or {}).items()
                if isinstance(m, dict)
            },
            views=int(known.get("views") or 0),
            depth=_optional(DepthCheck, known.get("depth")),
            occlusion=_optional(Occlusion, known.get("occlusion")),
            physics=_optional(PhysicsCheck, known.get("physics")),
            flags=[known_member(Flag, str(f)) for f in known.get("flags") or []],
            frames_seen=known.get("frames_seen"),
            depth_agreement_median=known.get("depth_agreement_median"),
            extra=e,
        )


_INSTANCE_KEYS = (
    "frames_seen",
    "depth_agreement_median",
    "physics",
    "uncertainty_mm",
    "reprojection_px",
    "markers",
    "views",
    "depth",
    "occlusion",
    "flags",
)


@dataclass
class FramePose:
    """One frame of a sequence: where the rig was, and annotate's figures for it.

    Attributes:
        frame: The frame's name (its folder under ``frames/``).
        scene_T_rig: 4x4, mm: the rig's reference camera in the scene frame; None for a frame
            that could not be posed (its ``flags`` say why: never a guess).
        flags: Why a reviewer should look at the frame (:class:`FrameFlag`); None where the
            frame was not assessed (the frames of a truth file).
        reason: The flags' reasons in words.
        reprojection_px, markers_used, uncertainty_mm, uncertainty_deg: A posed frame's
            corner RMS, marker observations and 1-sigma pose uncertainty.
        instances: Per instance key in the frame's view, what the frame saw of it
            (``occlusion`` per camera; annotate's also ``markers_used``).
        image_quality: Per camera, its :class:`ImageQuality`.
        time_s, motion_blur_px, exposure_s: A rendered sequence's truth: when the frame was
            taken, its motion streak and exposure.
        extra: Fields this version does not know, kept as read.
    """

    frame: str
    scene_T_rig: np.ndarray | None
    flags: list[FrameFlag | str] | None = None
    reason: str | None = None
    reprojection_px: float | None = None
    markers_used: int | None = None
    uncertainty_mm: float | None = None
    uncertainty_deg: float | None = None
    instances: dict[str, dict[str, Any]] | None = None
    image_quality: dict[str, ImageQuality] | None = None
    time_s: float | None = None
    motion_blur_px: float | None = None
    exposure_s: float | None = None
    extra: dict[str, Any] = field(default_factory=dict, compare=False)

    @property
    def posed(self) -> bool:
        return self.scene_T_rig is not None

    def has(self, flag: FrameFlag) -> bool:
        """Whether the frame carries ``flag``."""
        return flag in (self.flags or [])

    def to_json(self) -> dict[str, Any]:
        """The frame's entry under ``frames``: the fields that are set, in FORMAT.md's
        order, then the unknown ones."""
        T = self.scene_T_rig
        out: dict[str, Any] = {
            "scene_T_rig": None if T is None else [float(x) for x in np.asarray(T).reshape(16)]
        }
        for name in _FRAME_FIELDS:
            value = getattr(self, name)
            if value is not None:
                out[name] = [str(f) for f in value] if name == "flags" else value
        if self.image_quality is not None:
            out["image_quality"] = {c: q.to_json() for c, q in self.image_quality.items()}
        out.update(self.extra)
        return out

    @classmethod
    def from_json(cls, name: str, entry: dict[str, Any], T: np.ndarray | None) -> FramePose:
        """A frame from its entry (``scene_T_rig`` already read as ``T``)."""
        rest = {k: v for k, v in entry.items() if k != "scene_T_rig"}
        known = {k: rest.pop(k) for k in (*_FRAME_FIELDS, "image_quality") if k in rest}
        if known.get("flags") is not None:
            known["flags"] = [known_member(FrameFlag, str(f)) for f in known["flags"]]
        if "image_quality" in known:
            known["image_quality"] = image_qualities(known["image_quality"])
        return cls(name, T, **known, extra=rest)


#: FramePose's JSON fields after ``scene_T_rig``, in the order written (``image_quality``
#: then follows).
_FRAME_FIELDS = (
    "time_s",
    "motion_blur_px",
    "exposure_s",
    "reprojection_px",
    "markers_used",
    "uncertainty_mm",
    "uncertainty_deg",
    "instances",
    "flags",
    "reason",
)


def frames_from_json(doc: Any, path: Path) -> dict[str, FramePose]:
    """The ``frames`` mapping of a pose file (an empty dict when absent).

    Raises:
        UserError: naming the file and the frame, for an entry that is not a mapping or a
            ``scene_T_rig`` that is not null or 16 finite numbers of a rigid transform.
    """
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise UserError("frames must map frame -> {scene_T_rig: [16 floats], ...}", path=path)
    out: dict[str, FramePose] = {}
    for name, entry in doc.items():
        if not isinstance(entry, dict) or "scene_T_rig" not in entry:
            raise UserError(f"frames[{name!r}] needs scene_T_rig (16 floats or null)", path=path)
        raw = entry["scene_T_rig"]
        T = None
        if raw is not None:
            try:
                T = np.asarray(raw, dtype=np.float64).reshape(4, 4)
            except (TypeError, ValueError):
                raise UserError(
                    f"frames[{name!r}].scene_T_rig must be 16 numbers or null", path=path
                ) from None
            if (
                not np.all(np.isfinite(T))
                or not is_rotation(T[:3, :3], tol=1e-3)
                or np.any(np.abs(T[3] - [0, 0, 0, 1]) > 1e-6)
            ):
                raise UserError(
                    f"frames[{name!r}].scene_T_rig is not a finite rigid transform", path=path
                )
        out[str(name)] = FramePose.from_json(str(name), entry, T)
    return out


def frames_to_json(frames: Mapping[str, FramePose]) -> dict[str, Any]:
    """The ``frames`` mapping to write, in sorted frame order."""
    return {name: frames[name].to_json() for name in sorted(frames)}


@dataclass
class SceneAnnotation:
    """A scene's annotation.json.

    Attributes:
        instances: The posed instances.
        warnings: Scene-level warnings (completeness and image quality).
        image_quality: Per camera, its :class:`ImageQuality`.
        unknown_markers: ``{camera: [ids]}`` read but belonging to no instance.
        unconfirmed_markers: ``{camera: [ids]}`` of poses left out because the measured depth
            contradicted them and nothing else supported them.
        duplicates: ``{camera: [ids]}`` seen twice in one image.
        unexplained_mask: File name of the unexplained-depth mask beside annotation.json
            (uint8 PNG on the depth camera's grid, 255 = unexplained), or None.
        created_at, description_digest, errors: Provenance.
        scene_frame: A sequence's: the frame whose reference camera is the scene frame.
        frames: A sequence's frames (empty for a fixed rig).
        depth_scale: A sequence's depth scale where it is not 1 (``annotator sites``
            measures it).
        extra: Top-level fields this version does not know.

    >>> ann = SceneAnnotation.read("sample_scenes/scenes/000003/annotation.json")
    >>> len(ann.instances), ann.instances[0].key
    (10, 'bracket/01')
    """

    instances: list[InstanceAnnotation] = field(default_factory=list)
    warnings: list[SceneWarning] = field(default_factory=list)
    image_quality: dict[str, ImageQuality] = field(default_factory=dict)
    unknown_markers: dict[str, list[int]] = field(default_factory=dict)
    unconfirmed_markers: dict[str, list[int]] = field(default_factory=dict)
    duplicates: dict[str, list[int]] = field(default_factory=dict)
    unexplained_mask: str | None = None
    created_at: str | None = None
    description_digest: str | None = None
    errors: list[str] = field(default_factory=list)
    scene_frame: str | None = None
    frames: dict[str, FramePose] = field(default_factory=dict)
    depth_scale: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def flagged(self) -> bool:
        """True if a reviewer should look: a warning or a flagged instance."""
        return bool(self.warnings) or any(i.flags for i in self.instances)

    def write(self, path: str | Path) -> None:
        """Write annotation.json atomically."""
        top: dict[str, Any] = {}
        if self.scene_frame is not None:
            top["scene_frame"] = self.scene_frame
        if self.frames:
            top["frames"] = frames_to_json(self.frames)
        if self.depth_scale is not None:
            top["depth_scale"] = self.depth_scale
        top.update(self.extra)
        top.update(
            format=FORMAT_VERSION,
            created_at=self.created_at,
            description_digest=self.description_digest,
            unknown_markers=self.unknown_markers,
            unconfirmed_markers=self.unconfirmed_markers,
            duplicates=self.duplicates,
            image_quality={c: q.to_json() for c, q in self.image_quality.items()},
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
            scene_frame=top.pop("scene_frame", None),
            frames=frames_from_json(top.pop("frames", None), Path(path)),
            depth_scale=top.pop("depth_scale", None),
            instances=[InstanceAnnotation.from_pose(p) for p in poses],
            warnings=[SceneWarning.from_json(w) for w in top.pop("warnings", None) or []],
            image_quality=image_qualities(top.pop("image_quality", None)),
            unknown_markers=top.pop("unknown_markers", None) or {},
            unconfirmed_markers=top.pop("unconfirmed_markers", None) or {},
            duplicates=top.pop("duplicates", None) or {},
            unexplained_mask=top.pop("unexplained_mask", None),
            created_at=top.pop("created_at", None),
            description_digest=top.pop("description_digest", None),
            errors=list(top.pop("errors", None) or []),
            extra=top,
        )
